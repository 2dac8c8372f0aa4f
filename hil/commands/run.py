"""`hil run PROCEDURE --cell cell.toml --campaign FILE [--dry-run] [options]`: run a shop-floor procedure.

Re-running the same procedure on the same campaign resumes it: recorded points are skipped, nothing is
measured twice. `--dry-run` prints the plan (poses, order, estimated duration, bounding box) and connects to
nothing. Ctrl-C stops the robot, closes the campaign and exits; a second Ctrl-C exits at once.
"""

from __future__ import annotations

import argparse
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from hil.commands.errors import CliError
from hil.commands.interrupts import interrupt_guard
from hil.compensation.target_update import GENERATORS
from hil.runner.cell_config import CellConfigError, load_cell_config
from hil.runner.envelope import EnvelopeError
from hil.runner.operator import OperatorAbortError
from hil.runner.session import CampaignStopped

# name -> (module, options: list of (flag, kwargs for argparse))
PROCEDURE_OPTIONS: dict[str, list[tuple[str, dict[str, Any]]]] = {
    "registration": [
        ("--poses", {"type": int, "default": 12, "help": "poses to measure (default 12)"}),
        ("--nest", {"type": int, "default": 1, "help": "tool nest holding the SMR (default 1)"}),
        ("--inlier-mm", {"type": float, "default": 3.0, "help": "RANSAC inlier distance, mm (default 3)"}),
        ("--seed", {"type": int, "default": 0, "help": "seed of the random poses (default 0)"}),
    ],
    "tool_fit": [
        ("--poses", {"type": int, "default": 3, "help": "flange poses, each with all holes, the face and the nests (default 3)"}),
        ("--check-poses", {"type": int, "default": 12, "help": "poses of the distance-constraint cross-check (default 12)"}),
        ("--shots", {"type": int, "default": 10, "help": "tracker shots per point (default 10)"}),
        ("--seed", {"type": int, "default": 0, "help": "seed of the poses (default 0)"}),
    ],
    "grid_sampling": [
        ("--step-mm", {"type": float, "default": 100.0, "help": "grid step, mm (default 100; the papers use 100-200)"}),
        ("--box-min-mm", {"type": float, "nargs": 3, "default": None, "help": "sampling box corner x y z, mm, base frame (default: a box facing the tracker)"}),
        ("--box-max-mm", {"type": float, "nargs": 3, "default": None, "help": "opposite box corner x y z, mm"}),
        ("--orientations", {"type": int, "default": 1, "help": "tool orientations per grid vertex (default 1)"}),
        ("--order", {"choices": ["travel", "random"], "default": "travel", "help": "visiting order (default travel)"}),
        ("--both-directions", {"action": "store_true", "help": "approach each vertex from below and from above"}),
        ("--validation", {"type": int, "default": 50, "help": "random held-out validation poses (default 50)"}),
        ("--nest", {"type": int, "default": 1, "help": "tool nest holding the SMR (default 1)"}),
        ("--tilt-deg", {"type": float, "default": 20.0, "help": "max tilt of the SMR from the tracker line, deg (default 20)"}),
        ("--seed", {"type": int, "default": 0, "help": "seed of the orientations and validation poses (default 0)"}),
    ],
    "pseudo_target": [
        ("--model", {"required": True, "help": "calibrated model (model.json from hil calibrate / hil diagnose)"}),
        ("--targets", {"default": "20", "help": "N random held-out targets in the sampled volume, or a CSV: x_mm, y_mm, z_mm (tracker frame) [, rx_deg, ry_deg, rz_deg] (default 20)"}),
        ("--generator", {"choices": list(GENERATORS), "default": "yin", "help": "pseudo-target generator (default yin)"}),
        ("--threshold-mm", {"type": float, "default": 0.01, "help": "stop below this measured error, mm (default 0.01)"}),
        ("--max-iter", {"type": int, "default": 3, "help": "measured corrections per target (default 3)"}),
        ("--patience", {"type": int, "default": 2, "help": "stop a target after this many corrections in a row that do not beat its best error by more than the measurement noise (1 sigma of the tracker's noise model or the shot spread, whichever is larger); status no_improvement, best joints kept; 0 = off (default 2)"}),
        ("--smrs", {"type": int, "choices": [1, 3], "default": 1, "help": "1: position (SMR in nest 1); 3: pose (SMRs in nests 1-3) (default 1)"}),
        ("--seed", {"type": int, "default": 0, "help": "seed of the random targets (default 0)"}),
    ],
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("run", help="run a measurement procedure on a cell", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    procedures = parser.add_subparsers(dest="procedure", metavar="PROCEDURE", required=True)
    for name, options in PROCEDURE_OPTIONS.items():
        doc = _procedure_module(name).__doc__ or ""
        sub = procedures.add_parser(name, help=doc.splitlines()[0], description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
        sub.add_argument("--cell", required=True, help="cell configuration (TOML)")
        sub.add_argument("--campaign", required=True, help="campaign file (SQLite); created if missing, resumed if present")
        sub.add_argument("--dry-run", action="store_true", help="print the plan and move nothing")
        sub.add_argument("--operator", choices=["auto", "console", "sim"], default="auto", help="who does the manual steps (default auto: sim on a simulated cell, else console)")
        for flag, kwargs in options:
            sub.add_argument(flag, **kwargs)
        sub.set_defaults(func=run)


def _procedure_module(name: str):
    import importlib

    return importlib.import_module(f"procedures.{name}")


def procedure_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The procedure's own options from the parsed arguments (flag --step-mm -> keyword step_mm)."""
    return {flag.lstrip("-").replace("-", "_"): getattr(args, flag.lstrip("-").replace("-", "_")) for flag, _ in PROCEDURE_OPTIONS[args.procedure]}


def plan_kwargs(name: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """The subset of options the procedure's plan() takes."""
    import inspect

    accepted = inspect.signature(_procedure_module(name).plan).parameters
    return {k: v for k, v in kwargs.items() if k in accepted}


def run(args: argparse.Namespace) -> int:
    try:
        config = load_cell_config(args.cell)
    except CellConfigError as exc:
        raise CliError(str(exc), "fix the keys named above (hil cell check shows the same list)") from exc
    campaign = Path(args.campaign)
    if not campaign.parent.exists():
        raise CliError(f"campaign folder {campaign.parent} does not exist", "create it or choose another --campaign path")
    module = _procedure_module(args.procedure)
    kwargs = procedure_kwargs(args)
    try:
        the_plan = module.plan(config, **plan_kwargs(args.procedure, kwargs))
        config.envelope.check_poses(config.nominal, the_plan.joints(), config.nests_flange_m, [p.point_id for p in the_plan.poses])
    except (ValueError, EnvelopeError) as exc:
        raise CliError(str(exc), "change the options or the cell config; nothing moved") from exc
    if args.dry_run:
        print(the_plan.describe())
        return 0
    from hil.commands.instruments import choose_operator, open_session

    try:
        operator = choose_operator(config, args.operator)
    except ValueError as exc:
        raise CliError(str(exc), "pick another --operator") from exc
    from hil.instruments.robot import RobotError
    from hil.instruments.tracker import TrackerError

    with interrupt_guard(), ExitStack() as stack:
        try:
            session = open_session(config, campaign, operator, stack)
        except RobotError as exc:
            raise CliError(f"cannot connect to the robot at {config.robot_host}: {exc.message}", exc.remedy) from exc
        except (TrackerError, OSError) as exc:
            raise CliError(f"cannot connect to the tracker at {config.tracker_url}: {exc}", "check the tracker, its URL and the network") from exc
        try:
            with session:
                result = module.run(session, **kwargs)
        except CampaignStopped as exc:
            raise CliError(exc.message, exc.remedy) from exc
        except OperatorAbortError as exc:
            raise CliError(str(exc), "re-run the same command to resume; recorded points are kept") from exc
        except EnvelopeError as exc:
            raise CliError(str(exc), "nothing moved") from exc
    print(summarise(args.procedure, result))
    return 0


def summarise(name: str, result: Any) -> str:
    """One readable paragraph per procedure result."""
    if name == "registration":
        fit = result.fit
        return (
            f"registration: {int(fit.inliers.sum())} of {len(fit.inliers)} points agree; RMS {fit.rms_m * 1e3:.3f} mm, "
            f"max {fit.max_m * 1e3:.3f} mm (the robot's uncompensated error)"
        )
    if name == "tool_fit":
        lines = ["tool fit (flange frame, mm):"]
        for j, p in result.nests_flange_m.items():
            lines.append(f"  nest {j}: {p[0] * 1e3:9.4f} {p[1] * 1e3:9.4f} {p[2] * 1e3:9.4f}  +- {result.uncertainty_m[j] * 1e3:.4f}")
        lines.append(f"  worst circle residual {result.circle_residual_m * 1e3:.4f} mm; distance-method check {result.distance_check_m * 1e3:.3f} mm")
        return "\n".join(lines)
    if name == "grid_sampling":
        dropped = ", ".join(f"{n} {r}" for r, n in sorted(result.dropped.items())) or "none"
        return (
            f"grid sampling: {result.recorded}/{result.planned} grid points and {result.validation_recorded}/"
            f"{result.validation_planned} validation points recorded; left out when planning: {dropped}"
        )
    if name == "pseudo_target":
        return result.table()
    return str(result)
