"""`hil sim`: run one simulated cell (fake UR controller, control channel, ...) as a process."""

from __future__ import annotations

import argparse

from hil.commands.cell_options import add_effects_argument, effect_flags
from hil.commands.errors import CliError
from hil.robots import ROBOT_NAMES


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sim",
        help="run a simulated robot cell on a loopback address",
        description="Start the simulated cell; prints one JSON line (hosts, ports, control channel) once "
        "every server listens, then runs until SIGINT/SIGTERM.",
    )
    parser.add_argument("--host", default="127.0.0.2", help="loopback address to bind (default 127.0.0.2)")
    parser.add_argument("--robot", default="ur10", choices=[n for n in ROBOT_NAMES if n.startswith("ur")])
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.add_argument(
        "--personality",
        choices=["cb3", "eseries"],
        default=None,
        help="controller generation (default: eseries for ur*e robots, else cb3)",
    )
    parser.add_argument("--tracker-port", type=int, default=7000, help="port of the tracker fake")
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
        "--write-cell",
        metavar="FILE",
        default=None,
        help="write the cell.toml for this cell (robot, tracker, tool drawing, envelope) once it listens",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fakes.launch import is_loopback_host

    if not is_loopback_host(args.host):
        raise CliError(f"--host {args.host} is not a loopback address", "give an IPv4 address in 127.0.0.0/8")
    if args.time_scale <= 0:
        raise CliError(f"--time-scale {args.time_scale:g} is not positive", "give simulated seconds per wall second, e.g. 10")
    effects = effect_flags(args)
    from fakes.sim_process import SimOptions, main

    on_ready = None
    if args.write_cell:
        from pathlib import Path

        from hil.commands.sim_cell import write_sim_cell

        if not Path(args.write_cell).resolve().parent.is_dir():
            raise CliError(f"--write-cell: the folder of {args.write_cell} does not exist", "create it first")

        def on_ready(info: dict, truth: dict) -> None:
            write_sim_cell(args.write_cell, info, truth, args.time_scale)

    return main(
        SimOptions(
            host=args.host,
            robot=args.robot,
            seed=args.seed,
            personality=args.personality,
            time_scale=args.time_scale,
            control_port=args.control_port,
            tracker_port=args.tracker_port,
            script_start_delay_s=args.script_start_delay,
            powered=not args.powered_off,
            effects=effects,
            on_ready=on_ready,
        )
    )
