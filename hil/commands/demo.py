"""`hil demo`: the main job on a simulated cell, end to end.

1. Sample a Cartesian grid (default 100 mm) and random held-out poses on the simulated cell, as a
   tracker would measure them, and write both campaigns in the dataset contract.
2. Calibrate and diagnose: find what the geometric model misses, add it, and print the error
   before and after on held-out and validation data.
3. Write the JSON report, the HTML report and the final model.
4. Close the loop on live instruments: start the same cell as a `hil sim` process, drive the robot
   through ur-rtde and the tracker through emScon, aim the tracker where the calibrated model
   predicts the SMR, measure, and report predicted vs measured.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from fakes.campaign import grid_joints, random_joints, simulate_campaign
from fakes.cell import CellConfig, SimulatedCell
from hil.calibrated_model import CalibratedModel
from hil.commands.cell_options import add_effects_argument, effect_flags
from hil.dataset import POSITION_COLUMNS, joint_columns, joints_rad, points_m, write_dataset
from hil.diagnosis import run_diagnosis
from hil.report import write_html, write_json
from hil.robots import ROBOT_NAMES


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the main job on a simulated cell: grid campaign, calibration, diagnosis, report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--robot", default="ur10", choices=ROBOT_NAMES, help="robot model (default ur10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.add_argument("--step-mm", type=float, default=100.0, help="grid step in mm (default 100)")
    parser.add_argument("--validate", type=int, default=100, help="random validation poses (default 100)")
    add_effects_argument(parser)
    parser.add_argument("--out", default="demo-out", help="output folder (default ./demo-out)")
    parser.add_argument("--live", type=int, default=6, help="poses measured live through hil sim (0: skip)")
    parser.add_argument(
        "--time-scale", type=float, default=10.0, help="simulated seconds per wall second of the live cell"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    flags = effect_flags(args)
    if args.step_mm <= 0:
        raise SystemExit("--step-mm must be positive")
    if args.live > 0 and not args.robot.startswith("ur"):
        raise SystemExit(
            f"the live loop drives a UR arm through ur-rtde: use a ur* robot or --live 0 for {args.robot}"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cell = SimulatedCell(CellConfig(robot=args.robot, seed=args.seed, **flags))
    on = [k for k, v in flags.items() if v] or ["none"]
    print(f"simulated cell: {cell.robot_name}, seed {args.seed}, hidden geometric errors + {', '.join(on)}")

    q_grid = grid_joints(cell, step_m=args.step_mm / 1000.0, seed=args.seed)
    train = simulate_campaign(cell, q_grid)
    validate = simulate_campaign(cell, random_joints(cell, args.validate, seed=args.seed + 1))
    write_dataset(train, out / "grid.csv")
    write_dataset(validate, out / "validate.csv")
    print(f"measured {len(train)} grid poses at {args.step_mm:g} mm and {len(validate)} validation poses")

    report = run_diagnosis(train, cell.nominal, df_validate=validate, seed=args.seed)
    print()
    print(report.table())
    added = ", ".join(
        f"{e['name']}" + (f" (joint {e['joint']})" if e["joint"] else "") for e in report.effects_added
    )
    print(f"effects added: {added or 'none'}")
    print(report.conclusion)

    write_json(report, out / "report.json")
    write_html(report, out / "report.html")
    report.model.save(out / "model.json")
    print(f"\nwrote {out}/grid.csv, validate.csv, report.json, report.html, model.json")
    if args.live > 0:
        q_live = joints_rad(validate)[: args.live]
        live_loop(args, report.model, q_live, out / "live.csv")
    return 0


def live_loop(args: argparse.Namespace, model: CalibratedModel, q_poses, csv_path: Path) -> None:
    """Move the live robot to each pose, aim the tracker at the model's prediction, measure, compare."""
    from drivers.emscon import EmsconTracker
    from drivers.ur import URConfig, URRobot
    from fakes.launch import sim_cell

    print(f"\nlive: the same cell as a hil sim process, {len(q_poses)} poses through ur-rtde and emScon")
    with sim_cell(
        robot=args.robot, seed=args.seed, time_scale=args.time_scale, extra_args=("--effects", args.effects)
    ) as cell:
        robot = URRobot(URConfig(cell.host))
        rows = []
        try:
            with EmsconTracker(url=cell.info["tracker"]["url"], meas_time_s=0.5) as tracker:
                print(
                    f"{'pose':>4} {'predicted x,y,z (mm)':>32}  {'measured - predicted (mm)':>28}  {'|d| mm':>7}"
                )
                for k, q in enumerate(q_poses, start=1):
                    robot.move_joints(q)
                    robot.wait_settled()
                    q_now = robot.joints()
                    row = {c: float(v) for c, v in zip(joint_columns(), q_now, strict=True)}
                    p_pred = model.predict(pd.DataFrame([row]))[0]
                    tracker.point_at(p_pred)
                    m = tracker.measure(shots=3)
                    d_mm = (m.p_tracker_m - p_pred) * 1e3
                    row |= {c: float(v * 1e3) for c, v in zip(POSITION_COLUMNS, m.p_tracker_m, strict=True)}
                    rows.append(row)
                    pd.DataFrame(rows).to_csv(csv_path, index=False)  # nothing measured is lost
                    print(
                        f"{k:>4} {p_pred[0] * 1e3:10.3f} {p_pred[1] * 1e3:10.3f} {p_pred[2] * 1e3:10.3f}  "
                        f"{d_mm[0]:+8.4f} {d_mm[1]:+8.4f} {d_mm[2]:+8.4f}  {np.linalg.norm(d_mm):7.4f}"
                    )
        finally:
            robot.close()
    live = pd.DataFrame(rows)
    errors = np.linalg.norm(points_m(live) - model.predict(live), axis=1) * 1e3
    print(f"live prediction error: mean {errors.mean():.4f} mm, max {errors.max():.4f} mm; wrote {csv_path}")
