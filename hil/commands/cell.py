"""`hil cell check cell.toml [--connect]`: check a cell configuration before anything moves.

Reports every problem with its key and what to fix. With --connect it then opens the robot (ur-rtde) and
the tracker (emScon) and reports their state; nothing moves.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import closing

import numpy as np

from hil.commands.errors import CliError
from hil.runner.cell_config import CellConfig, CellConfigError, load_cell_config


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cell",
        help="check a cell configuration (and optionally its instruments)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser("check", help="report every problem of a cell.toml, with its key")
    check.add_argument("config", help="cell configuration (TOML)")
    check.add_argument(
        "--connect",
        action="store_true",
        help="also connect to the robot and the tracker and report their state",
    )
    check.set_defaults(func=run_check)


def describe(config: CellConfig, connect: bool = False) -> str:
    env = config.envelope
    nests = ", ".join(f"({', '.join(f'{v * 1e3:.1f}' for v in p)})" for p in config.nests_flange_m)
    return "\n".join(
        [
            f"{config.source}: the configuration is valid"
            + (" (instruments not contacted: add --connect)" if not connect else ""),
            f"  robot   {config.robot_model} at {config.robot_host}",
            f"  tracker {config.tracker_url}, {config.shots_per_point} shot(s) of {config.meas_time_s:g} s per point, "
            f"about ({', '.join(f'{v * 1e3:.0f}' for v in config.p_base_tracker_m)}) mm from the robot base",
            f"  tool    {len(config.nests_flange_m)} nest(s) at {nests} mm (flange frame)",
            f"  envelope box ({', '.join(f'{v * 1e3:.0f}' for v in env.box_min_m)}) .. "
            f"({', '.join(f'{v * 1e3:.0f}' for v in env.box_max_m)}) mm; joints "
            + " ".join(
                f"[{a:.0f},{b:.0f}]"
                for a, b in zip(np.rad2deg(env.joint_min_rad), np.rad2deg(env.joint_max_rad), strict=True)
            )
            + " deg",
            f"  settle {config.settle_s:g} s",
            f"  speed   {config.speed_text()}",
            _collisions_line(config),
        ]
    )


def _collisions_line(config: CellConfig) -> str:
    """Whether collisions are checked, with which margins, and where the arm's body comes from."""
    bodies = config.envelope.bodies
    if bodies is None:
        return "  collisions not checked ([envelope] collisions = false): the box and the joint limits only"
    return (
        f"  collisions checked: {bodies.self_margin_m * 1e3:g} mm between links, {bodies.margin_m * 1e3:g} mm "
        f"from the tracker and {len(bodies.keep_out)} keep-out box(es); the arm's body: {bodies.body.source}"
    )


def _config_remedy(exc: CellConfigError) -> str:
    """What to do about a cell config that cannot be used: a missing file is not a key to fix."""
    if exc.problems and exc.problems[0].startswith("file not found"):
        return "give the path of the cell's TOML file (hil sim --write-cell FILE writes one for the simulated cell)"
    return "fix each key listed, then check again"


def run_check(args: argparse.Namespace) -> int:
    try:
        config = load_cell_config(args.config)
    except CellConfigError as exc:
        raise CliError(str(exc), _config_remedy(exc)) from exc
    print(describe(config, args.connect))
    from hil.runner.cell_warnings import cell_warnings

    for warning in cell_warnings(config):
        print(f"  warning: {warning}")
    if not args.connect:
        return 0
    from hil.instruments.robot import RobotError
    from hil.instruments.tracker import TrackerError
    from hil.station.instruments import drivers_of

    robots, trackers = drivers_of(config)
    failures = 0
    try:
        with closing(robots.open(config.robot_mapping())) as robot:
            state = robot.state()
            print(
                f"  robot connected: controller {getattr(robot, 'version', '?')}, mode {state.robot_mode}, safety {state.safety_mode}, ready {state.ready}"
            )
            q_now = np.asarray(robot.joints(), float)  # the controller's joints: the envelope's are kinematic
            q_now = q_now if config.coupling is None else config.coupling.to_kinematic(q_now[None])[0]
            if not config.envelope.joint_violations(q_now)[0]:
                print("  robot joints inside the envelope's limits")
            else:
                print(
                    "  robot joints OUTSIDE the envelope's limits: jog it inside before running a procedure"
                )
                failures += 1
    except RobotError as exc:
        print(f"  robot: {exc.message}\n    what to do: {exc.remedy}", file=sys.stderr)
        failures += 1
    try:
        with closing(trackers.open(config.tracker_mapping())) as tracker:
            tracker_state = tracker.state()
            print(
                f"  tracker connected: initialized {tracker_state.initialized}, target locked "
                f"{tracker_state.target_locked}, reflector {tracker_state.reflector_id}"
            )
    except (TrackerError, OSError, ValueError) as exc:
        remedy = getattr(exc, "remedy", "check the tracker URL in the cell config")
        print(f"  tracker: {getattr(exc, 'message', exc)}\n    what to do: {remedy}", file=sys.stderr)
        failures += 1
    if failures:
        print(
            f"hil cell: {failures} of 2 instruments did not answer as a procedure needs; fix what each line above "
            "says, then check again",
            file=sys.stderr,
        )
        return 2
    print("  both instruments answer: procedures can run on this cell")
    return 0
