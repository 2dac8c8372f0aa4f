"""Joint-axis identification on the simulated cell, through the drivers: axis errors against the cell's truth
and the held-out error of a calibration started from the measured robot file against one started from the
nominal model.

Run:  PYTHONPATH=. python benchmarks/joint_axes.py [--seed 3] [--points 25] [--smrs 3] [--shots 3] [--effects none]

The cell is `hil sim`'s default UR10 (hidden geometric errors, gravity compliance, tracker noise at its stated
MPE: 15 um + 6 um/m, 2 sigma). Registration, then the joint_axes procedure (its own reference pose search,
SMRs in every tool nest unless --smrs, the cell's shots per point unless --shots);
each measured axis is compared with the true axis at the reference pose (the cell's true geometry and joint
deflections there, in the tracker frame). Joint 2 is swept from its own pose (the arm stretched, where the
other joints' gravity sag leaves its arc a circle); its axis depends on joint 1 alone, held as at the reference. Both calibrations use the same simulated grid campaign of the same
cell (150 mm step) and are judged on the same 100 held-out poses.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--points", type=int, default=25)
    ap.add_argument("--shots", type=int, default=None)
    ap.add_argument("--smrs", type=int, default=None)
    ap.add_argument(
        "--effects", default="gravity_compliance", help="the sim's effects (its --effects), or none"
    )
    args = ap.parse_args()

    from calib_data import cell_datasets
    from sim_session import running_cell, session_on

    from fakes.cell import SimCellConfig, SimulatedCell, parse_effect_flags
    from hil.analysis.calibration.solve import calibrate
    from hil.geometry.robots import get_robot
    from procedures import joint_axes, registration

    folder = Path(tempfile.mkdtemp(prefix="axes-bench-"))
    robot_file = folder / "measured.toml"
    t0 = time.time()
    with (
        running_cell(folder, seed=args.seed, time_scale=100.0, extra_args=("--effects", args.effects)) as (
            _,
            config,
        ),
        session_on(config, folder / "campaign.sqlite") as session,
    ):
        registration.PROCEDURE(session)
        result = joint_axes.PROCEDURE(
            session, points=args.points, smrs=args.smrs, output=str(robot_file), shots=args.shots
        )
    measured_s = time.time() - t0
    effects = parse_effect_flags(args.effects)
    cell = SimulatedCell(SimCellConfig(seed=args.seed, **effects))
    q_ref = result.axes.q_ref_rad
    _, frames = cell.true_joint_offsets(q_ref, np.ones(6), 0.0)
    F = cell.T_tracker_base @ frames[0]
    print(
        f"simulated UR10 seed {args.seed}, effects {args.effects}: {args.points} points per arc, "
        f"{args.smrs or len(config.nests_flange_m)} SMR(s), shots {args.shots or config.shots_per_point}, "
        f"reference pose {np.round(np.rad2deg(q_ref), 1).tolist()} deg ({measured_s:.0f} s incl. registration)"
    )
    print(f"{'joint':<6}{'arc deg':>8}{'direction err deg':>19}{'position err mm':>17}{'fit resid mm':>14}")
    worst = [0.0, 0.0]
    for a in result.axes.axes:
        z, o = F[a.joint, :3, 2], F[a.joint, :3, 3]
        ang = math.degrees(math.acos(min(1.0, float(a.direction @ z))))
        d = a.point_m - o
        off = float(np.linalg.norm(d - (d @ z) * z)) * 1e3
        worst = [max(worst[0], ang), max(worst[1], off)]
        print(
            f"{a.joint + 1:<6}{math.degrees(a.swept_rad):8.1f}{ang:19.4f}{off:17.4f}{a.residual_rms_m * 1e3:14.4f}"
        )
    print(f"worst: {worst[0]:.4f} deg, {worst[1]:.4f} mm (goal 0.02 deg, 0.1 mm)")

    _, train, val = cell_datasets(step_m=0.15, n_val=100, seed=args.seed, **effects)
    p_val = val[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3
    print(f"\ncalibration on {len(train)} grid poses, held-out error on {len(val)} poses (mm):")
    print(f"{'start':<22}{'train RMS':>10}{'held-out RMS':>14}{'held-out max':>14}")
    for label, start in (
        ("nominal ur10", get_robot("ur10")),
        ("measured axes file", get_robot(str(robot_file))),
    ):
        res = calibrate(train, start, "ridge")
        err = np.linalg.norm(res.model.predict(val) - p_val, axis=1) * 1e3
        print(f"{label:<22}{res.rms_mm:10.4f}{np.sqrt(np.mean(err**2)):14.4f}{err.max():14.4f}")


if __name__ == "__main__":
    main()
