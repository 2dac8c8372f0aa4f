"""`python -m fakes.sim`: the simulated cell's own command line, from its options to a running process.

Every option of the cell is defined here once (`add_sim_arguments`) and turned into `SimOptions` here
(`sim_options`); `hil sim` is the same command under the `hil` CLI and adds these arguments to its parser.
`fakes.launch` starts this module, so the fakes never go through the `hil` command.
"""

from __future__ import annotations

import argparse
import sys

from fakes.cell import CELL_EFFECTS, COUPLED_ROBOTS, EffectFlags, parse_effect_flags
from fakes.launch import is_loopback_host
from fakes.sim_process import SimOptions, run_cell
from hil.geometry.robots import ROBOT_NAMES
from hil.instruments.plugins import PluginOptionError

DESCRIPTION = (
    "Start the simulated cell; prints one JSON line (hosts, ports, control channel) once every server "
    "listens, then runs until SIGINT/SIGTERM."
)


AIR_RANGE_C = (-20.0, 60.0)  # the air temperatures a tracker's refraction model accepts


class SimOptionError(PluginOptionError):
    """An option the simulated cell cannot start with: `message` (what is wrong) and `remedy` (what to give)."""


def add_effects_argument(parser: argparse.ArgumentParser) -> None:
    """Add `--effects` (comma-separated physical effects of the simulated cell, default gravity_compliance)."""
    parser.add_argument(
        "--effects",
        default="gravity_compliance",
        help=f"physical effects of the simulated cell, comma-separated from {', '.join(CELL_EFFECTS)} (the "
        "diagnosis' effect names), or 'none' (default: gravity_compliance, the PT paper's undeclared effect)",
    )


def effects_from_args(args: argparse.Namespace) -> EffectFlags:
    """SimCellConfig flags from `--effects`; an unknown name is a SimOptionError listing the known ones."""
    try:
        return parse_effect_flags(args.effects)
    except ValueError as exc:
        raise SimOptionError(
            str(exc), f"name effects from {', '.join(CELL_EFFECTS)}, comma-separated, or none"
        ) from exc


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """Every option of the simulated cell process."""
    parser.add_argument("--host", default="127.0.0.2", help="loopback address to bind (default 127.0.0.2)")
    parser.add_argument(
        "--robot",
        default="ur10",
        choices=[n for n in ROBOT_NAMES if n.startswith("ur") or n in COUPLED_ROBOTS],
        help="the simulated arm, a built-in Universal Robots model or one whose controller couples its joints "
        f"({', '.join(COUPLED_ROBOTS)}: the controller speaks RTDE in the maker's joints) (default ur10)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.add_argument(
        "--personality",
        choices=["cb3", "eseries"],
        default=None,
        help="controller generation (default: eseries for ur*e robots, else cb3)",
    )
    parser.add_argument(
        "--tracker-port", type=int, default=7000, help="port of the tracker fake (default 7000)"
    )
    parser.add_argument("--control-port", type=int, default=0, help="control channel port (0: any free)")
    parser.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="simulated seconds per wall second (default 1; tests use 5-20)",
    )
    parser.add_argument(
        "--script-start-delay",
        type=float,
        default=0.05,
        help="seconds the controller takes to start an uploaded program (default 0.05)",
    )
    add_effects_argument(parser)
    parser.add_argument("--powered-off", action="store_true", help="start with the arm powered off")
    parser.add_argument(
        "--tracker-air-c",
        type=float,
        default=None,
        help="air temperature (degC) the tracker's weather station reads whatever the hall does (a station in "
        "the sun, a fixed setting): distances scale 0.93 ppm per K of the difference (default: the hall's air)",
    )
    parser.add_argument(
        "--no-weather-monitor",
        action="store_true",
        help="the tracker has no weather monitor: its refraction uses the meteo a client enters "
        "(SetEnvironmentParams; 20 degC, 1013.25 hPa, 50 %% until then)",
    )


def sim_options(args: argparse.Namespace) -> SimOptions:
    """SimOptions from the arguments of `add_sim_arguments`; a bad value is a SimOptionError."""
    if not is_loopback_host(args.host):
        raise SimOptionError(
            f"--host {args.host} is not a loopback address", "give an IPv4 address in 127.0.0.0/8"
        )
    if args.time_scale <= 0:
        raise SimOptionError(
            f"--time-scale {args.time_scale:g} is not positive",
            "give simulated seconds per wall second, e.g. 10",
        )
    air = args.tracker_air_c
    if air is not None and not AIR_RANGE_C[0] <= air <= AIR_RANGE_C[1]:
        raise SimOptionError(
            f"--tracker-air-c {air:g} is outside {AIR_RANGE_C[0]:g}..{AIR_RANGE_C[1]:g} degC",
            "give the air temperature in degrees Celsius, e.g. 20",
        )
    if air is not None and args.no_weather_monitor:
        raise SimOptionError(
            "--tracker-air-c sets what the tracker's weather station reads, and --no-weather-monitor removes it",
            "give one of them (without a monitor the client enters the meteo, e.g. with SetEnvironmentParams)",
        )
    return SimOptions(
        host=args.host,
        robot=args.robot,
        seed=args.seed,
        personality=args.personality,
        time_scale=args.time_scale,
        control_port=args.control_port,
        tracker_port=args.tracker_port,
        script_start_delay_s=args.script_start_delay,
        powered=not args.powered_off,
        tracker_air_c=air,
        weather_monitor=not args.no_weather_monitor,
        effects=effects_from_args(args),
    )


def main(argv: list[str] | None = None) -> int:
    """Parse the options and run the cell until SIGINT/SIGTERM; exit 2 on a bad option, 3 if the address is taken."""
    parser = argparse.ArgumentParser(prog="python -m fakes.sim", description=DESCRIPTION)
    add_sim_arguments(parser)
    args = parser.parse_args(argv)
    try:
        options = sim_options(args)
    except SimOptionError as exc:
        parser.error(str(exc))
    return run_cell(options)


if __name__ == "__main__":
    sys.exit(main())
