"""`hil demo`: the main job on a simulated cell, through the real drivers, end to end.

1. Start the simulated cell (`hil sim`: a fake UR controller and a fake emScon tracker) and write its
   cell.toml, as an engineer would for a real cell.
2. Run the shop-floor procedures through ur-rtde and emScon, into one campaign file: registration
   (tracker <-> robot base), tool fit (flange holes; the scripted operator moves the simulated SMR), grid
   sampling at 100 mm plus random held-out validation poses.
3. Export the grid and the validation set from the campaign, calibrate and diagnose: find what the
   geometric model misses, add it, and print the error before and after on held-out and validation data.
4. When the diagnosis leaves anything undecided that poses can decide, run the active loop (`--active-rounds`
   rounds of at most `--active-poses` poses into the same campaign, diagnosed again after each; 0: skip).
5. Close the loop on held-out targets: the cell runs again, the robot goes to the model-based compensated
   joints of random targets in the sampled volume and the measured pseudo-target loop corrects what is left
   (uncompensated -> model-based -> measured loop, all measured by the tracker).
6. Write the JSON report, the HTML report and the final model.

Interrupted (Ctrl-C, a crash), the same command resumes the campaign: recorded points are not measured again.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from hil.commands.cell_options import add_effects_argument, effect_flags, simulator
from hil.commands.errors import CliError
from hil.geometry.robots import ROBOT_NAMES

if TYPE_CHECKING:
    from hil.runner.session import Session

UR_ROBOTS = [name for name in ROBOT_NAMES if name.startswith("ur")]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the main job on a simulated cell: procedures through the drivers, diagnosis, report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--robot", default="ur10", choices=UR_ROBOTS, help="robot model (default ur10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.add_argument("--step-mm", type=float, default=100.0, help="grid step in mm (default 100)")
    parser.add_argument("--validate", type=int, default=100, help="random validation poses (default 100)")
    add_effects_argument(parser)
    parser.add_argument(
        "--loop-targets",
        type=int,
        default=10,
        help="held-out targets of the measured loop (default 10; 0: skip)",
    )
    parser.add_argument(
        "--active-rounds", type=int, default=1,
        help="rounds of the active loop when the diagnosis leaves anything undecided (default 1; 0: skip)",
    )  # fmt: skip
    parser.add_argument(
        "--active-poses", type=int, default=40, help="poses per active-loop round at most (default 40)"
    )
    parser.add_argument(
        "--tool-check-poses", type=int, default=25,
        help="poses of the tool fit's distance-constraint check (default 25, the tool paper's; at least 6)",
    )  # fmt: skip
    parser.add_argument(
        "--tool-validation-poses", type=int, default=20,
        help="validation poses of the tool fit (default 20, the tool paper's; at least 4)",
    )  # fmt: skip
    parser.add_argument("--out", default="demo-out", help="output folder (default ./demo-out)")
    parser.add_argument(
        "--time-scale", type=float, default=20.0, help="simulated seconds per wall second (default 20)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    flags = effect_flags(args)
    if not 20.0 <= args.step_mm <= 500.0:
        raise CliError(f"--step-mm {args.step_mm:g} is outside 20..500", "use a grid step of 100-200 mm")
    if args.validate < 10:
        raise CliError("--validate must be at least 10", "give more validation poses")
    if not 0 <= args.loop_targets <= 200:
        raise CliError(f"--loop-targets {args.loop_targets} is outside 0..200", "use e.g. 10")
    if args.tool_check_poses < 6 or args.tool_validation_poses < 4:
        raise CliError(
            f"--tool-check-poses {args.tool_check_poses} / --tool-validation-poses {args.tool_validation_poses}"
            " is too few",
            "give at least 6 check poses and 4 validation poses (the tool paper: 25 and 20)",
        )
    if not 0 <= args.active_rounds <= 5:
        raise CliError(f"--active-rounds {args.active_rounds} is outside 0..5", "use e.g. 1, or 0 to skip")
    if not 1 <= args.active_poses <= 500:
        raise CliError(f"--active-poses {args.active_poses} is outside 1..500", "use e.g. 40")
    if not 0.5 <= args.time_scale <= 50.0:
        raise CliError(f"--time-scale {args.time_scale:g} is outside 0.5..50", "use e.g. 20")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    campaign = out / "campaign.sqlite"
    on = [k for k, v in flags.items() if v] or ["none"]
    resumed = campaign.exists()
    print(
        f"simulated cell: {args.robot}, seed {args.seed}, hidden geometric errors + {', '.join(on)}; "
        f"campaign {campaign}{' (resuming)' if resumed else ''}"
    )
    from hil.commands.interrupts import interrupt_guard
    from hil.runner.engine import CampaignStopped

    started = time.monotonic()
    with interrupt_guard():
        try:
            measure(args, out, campaign)
        except CampaignStopped as exc:
            raise CliError(exc.message, exc.remedy + " (run hil demo again to resume)") from exc
    print(f"measured through the drivers in {time.monotonic() - started:.0f} s")
    report = analyse(args, out, campaign)
    active = None
    if args.active_rounds and any(q.plannable for q in report.undecided):
        with interrupt_guard():
            try:
                report, active = active_loop(args, out, campaign)
            except CampaignStopped as exc:
                raise CliError(exc.message, exc.remedy + " (run hil demo again to resume)") from exc
    loop = None
    if args.loop_targets:
        with interrupt_guard():
            try:
                loop = measured_loop(args, out, campaign, report.model)
            except CampaignStopped as exc:
                raise CliError(exc.message, exc.remedy + " (run hil demo again to resume)") from exc
    from hil.data.store import CampaignStore
    from hil.report.html import write_html
    from hil.report.json_report import outcomes_section, write_json

    with CampaignStore(campaign, create=False) as store:
        tool = store.step_result("tool_fit", "fit")
        outcomes = outcomes_section(store.outcomes())
    write_html(
        report, out / "report.html", compensation=loop, active=active and active["html"], tool_fit=tool,
        outcomes=outcomes,
    )  # fmt: skip
    extra = {"tool_fit": tool, "measured_loop": loop, "outcomes": outcomes or None}
    if active:
        extra["active_loop"] = {"rounds": active["rounds"], "stop": active["stop"]}
    write_json(report, out / "report.json", {k: v for k, v in extra.items() if v is not None})
    print(
        f"\nwrote {out}/campaign.sqlite, cell.toml, grid.csv, validate.csv, report.json, report.html, model.json"
    )
    print(
        f"the simulated cell has stopped; {restart_command(args)} starts it again at the address {out / 'cell.toml'} names"
    )
    return 0


def restart_command(args: argparse.Namespace) -> str:
    """The `hil sim` command that brings the demo's cell back at the address its cell.toml names."""
    host, control_port = args.cell_address
    return (
        f"hil sim --host {host} --control-port {control_port} --robot {args.robot} --seed {args.seed} "
        f"--time-scale {args.time_scale:g} --effects {args.effects}"
    )


@contextmanager
def simulated_session(args: argparse.Namespace, out: Path, campaign: Path) -> Iterator[Session]:
    """Start the simulated cell, write its cell.toml (as for a real cell) and open a Session on it through
    ur-rtde and emScon, the scripted operator moving the simulated SMRs; the cell stops on leaving."""
    from hil.commands.interrupts import stop_on_interrupt
    from hil.commands.native_output import capture_native_output
    from hil.commands.sim_cell import write_sim_cell
    from hil.runner.cell_config import load_cell_config
    from hil.station.instruments import open_session, simulated_operator

    cell_path = out / "cell.toml"
    first = not hasattr(args, "cell_address")
    host, control_port = (None, 0) if first else args.cell_address
    launch = simulator().launch(
        args.robot, args.seed, args.time_scale, args.effects, host=host, control_port=control_port
    )
    with launch as cell:
        if first:  # later starts come back at this address, so the one cell.toml serves every stage and after
            args.cell_address = (cell.host, int(cell.info["control"].rsplit(":", 1)[1]))
            write_sim_cell(cell_path, cell.info, cell.control.call("ground_truth"), args.time_scale)
        config = load_cell_config(cell_path)
        what = f"wrote {cell_path}" if first else f"same address as {cell_path}"
        print(
            f"cell: {cell.info['robot']['personality']} controller at {cell.host}, tracker {config.tracker_url}; {what}"
        )
        with ExitStack() as stack:
            stack.enter_context(capture_native_output(verbose=getattr(args, "verbose", False)))
            session = open_session(
                config, campaign, simulated_operator(config.simulator_control), stack, holder="hil demo"
            )
            stack.enter_context(
                stop_on_interrupt(session.engine.request_stop)
            )  # Ctrl-C: the engine's stop path
            with session:
                yield session


def measure(args: argparse.Namespace, out: Path, campaign: Path) -> None:
    """Run the procedures into the campaign: registration, tool fit, grid with held-out validation."""
    from hil.runner.registry import load

    registration, tool_fit, grid_sampling = (load(n) for n in ("registration", "tool_fit", "grid_sampling"))
    with simulated_session(args, out, campaign) as session:
        print(registration.summary(registration(session)))
        fit = tool_fit(
            session, check_poses=args.tool_check_poses, validation_poses=args.tool_validation_poses
        )
        print(tool_fit.summary(fit))
        result = grid_sampling(session, step_m=args.step_mm / 1e3, validation=args.validate, seed=args.seed)
        print(grid_sampling.summary(result))


def active_loop(args: argparse.Namespace, out: Path, campaign: Path):
    """Start the cell again and measure what the diagnosis left undecided (the active_loop procedure); the
    final diagnosis (its report and model replace the first) and the rounds (records, why the loop stopped,
    an HTML section)."""
    from hil.report.json_report import write_json
    from hil.report.rounds import rounds_html
    from hil.report.text import conclusion
    from hil.runner.registry import load

    procedure = load("active_loop")
    print(
        f"\nactive loop: at most {args.active_rounds} round(s) of at most {args.active_poses} poses that decide what is undecided:"
    )
    with simulated_session(args, out, campaign) as session:
        result = procedure(session, rounds=args.active_rounds, poses=args.active_poses, seed=args.seed)
    print(procedure.summary(result))
    report = result.report
    print(report.table())
    print(conclusion(report))
    write_json(report, out / "report.json")
    report.model.save(out / "model.json")
    return report, {
        "rounds": result.records,
        "stop": result.stop,
        "html": rounds_html(result.records, result.stop),
    }


def measured_loop(args: argparse.Namespace, out: Path, campaign: Path, model) -> dict:
    """Start the cell again and run the measured pseudo-target loop on held-out targets; its summary."""
    from hil.runner.registry import load

    pseudo_target = load("pseudo_target")
    print(f"\nmeasured pseudo-target loop on {args.loop_targets} held-out targets (model-based start):")
    with simulated_session(args, out, campaign) as session:
        result = pseudo_target(
            session, model=model, targets=args.loop_targets, max_iter=2, seed=args.seed + 1000,
            measure_uncompensated=True,
        )  # fmt: skip
    print(result.stage_table())
    return result.summary()


def analyse(args: argparse.Namespace, out: Path, campaign: Path):
    """Diagnose the grid against the validation set and write the JSON report and the model."""
    import numpy as np

    from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
    from hil.data.dataset import write_dataset
    from hil.data.store import CampaignStore, campaign_dataset
    from hil.geometry.robots import get_robot
    from hil.report.json_report import write_json
    from hil.report.text import conclusion

    with CampaignStore(campaign) as store:
        train = campaign_dataset(store, "grid_sampling", step="grid")
        validate = campaign_dataset(store, "grid_sampling", step="validation")
        fit = store.step_result("tool_fit", "fit")
    write_dataset(train, out / "grid.csv")
    write_dataset(validate, out / "validate.csv")
    print(f"exported {len(train)} grid and {len(validate)} validation points from the campaign")
    tool_guess = np.array(fit["nests_flange_mm"]["1"]) / 1e3 if fit else None
    options = DiagnosisOptions(seed=args.seed, tool_guess_m=tool_guess)
    report = run_diagnosis(train, get_robot(args.robot), df_validate=validate, options=options)
    print()
    print(report.table())
    added = ", ".join(
        f"{e['name']}" + (f" (joint {e['joint']})" if e["joint"] else "") for e in report.effects_added
    )
    print(f"effects added: {added or 'none'}")
    print(conclusion(report))
    write_json(report, out / "report.json")
    report.model.save(out / "model.json")
    return report
