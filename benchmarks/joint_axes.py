"""Joint-axis identification on the simulated cell, through the drivers: axis errors against the cell's truth
and the held-out error of a calibration started from the measured robot file against one started from the
nominal model.

Run:  PYTHONPATH=. python benchmarks/joint_axes.py [--seed 3] [--points 25] [--smrs 3] [--shots 3] [--effects none]
      [--no-calibration] [--axis-sigma-deg 0.005]

The cell is `hil sim`'s default UR10 (hidden geometric errors, gravity compliance, tracker noise at its stated
MPE: 15 um + 6 um/m, 2 sigma). Registration, then the joint_axes procedure (its own reference pose search,
SMRs in every tool nest unless --smrs, the cell's shots per point unless --shots);
each measured axis is compared with the true axis at the reference pose (the cell's true geometry and joint
deflections there, in the tracker frame), beside the 1-sigma the fit states and the errors of a plain fit of
the same sweeps (per SMR a plane and a circle, normals and centres averaged). Joint 2 is swept from its own pose (the arm stretched, where the
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


def campaign_dataset_of(path: Path):
    """The joint_axes sweeps of a campaign file as a dataset with each row's sweep label."""
    from hil.data.store import campaign_dataset

    df = campaign_dataset(path, "joint_axes", "sweeps")
    df["sweep"] = [p.split("/")[0] for p in df["point_id"]]
    return df


def line_errors(point: np.ndarray, direction: np.ndarray, frame: np.ndarray) -> tuple[float, float]:
    """Angle (deg) between a fitted axis and the true one (z of `frame`), and the fitted point's distance
    (mm) from the true line."""
    z, o = frame[:3, 2], frame[:3, 3]
    angle = math.degrees(math.acos(min(1.0, abs(float(direction @ z)))))
    d = point - o
    return angle, float(np.linalg.norm(d - (d @ z) * z)) * 1e3


def plain_fit(df, joint: int) -> tuple[np.ndarray, np.ndarray]:
    """The textbook fit, for comparison: per SMR a plane (SVD) and a circle in it, then the mean of the
    normals (signs aligned) and the mean of the centres."""
    from hil.analysis.standards.joint_axes import fit_circle

    rows = df[df["sweep"] == f"j{joint + 1}"]
    fits = [fit_circle(g[["x_mm", "y_mm", "z_mm"]].to_numpy(float) / 1e3) for _, g in rows.groupby("smr")]
    normals = np.array([f[1] for f in fits])
    normals *= np.sign(normals @ normals[0])[:, None]
    n = normals.mean(axis=0)
    return np.mean([f[0] for f in fits], axis=0), n / np.linalg.norm(n)


def axis_table(axes, df, F: np.ndarray) -> str:
    """Per joint: our axis's errors against the truth beside the 1-sigma it states, and the plain fit's."""
    lines = [
        f"{'joint':<6}{'rows':>5}{'arc':>6}{'direction err deg':>30}{'position err mm':>30}{'resid':>8}",
        f"{'':<6}{'':>5}{'deg':>6}{'ours':>10}{'sigma':>10}{'plain':>10}{'ours':>10}{'sigma':>10}{'plain':>10}{'mm':>8}",
    ]
    worst = np.zeros(4)
    for a in axes.axes:
        ang, off = line_errors(a.point_m, a.direction, F[a.joint])
        plain_ang, plain_off = line_errors(*plain_fit(df, a.joint), F[a.joint])
        worst = np.maximum(worst, [ang, off, plain_ang, plain_off])
        lines.append(
            f"{a.joint + 1:<6}{a.points:5d}{math.degrees(a.arc_rad):6.1f}{ang:10.4f}{math.degrees(a.direction_sigma_rad):10.4f}"
            f"{plain_ang:10.4f}{off:10.4f}{a.point_sigma_m * 1e3:10.4f}{plain_off:10.4f}{a.residual_rms_m * 1e3:8.4f}"
        )
    lines.append(
        f"worst: ours {worst[0]:.4f} deg, {worst[1]:.4f} mm; plain {worst[2]:.4f} deg, {worst[3]:.4f} mm "
        "(goal 0.01 deg, 0.06 mm)"
    )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--points", type=int, default=25)
    ap.add_argument("--shots", type=int, default=None)
    ap.add_argument("--smrs", type=int, default=None)
    ap.add_argument(
        "--effects", default="gravity_compliance", help="the sim's effects (its --effects), or none"
    )
    ap.add_argument("--no-calibration", action="store_true", help="the axes alone, not the calibrations")
    ap.add_argument(
        "--axis-sigma-deg", type=float, default=None, help="the plan's axis_sigma (0: --points on every arc)"
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
        sigma = {} if args.axis_sigma_deg is None else {"axis_sigma_rad": math.radians(args.axis_sigma_deg)}
        result = joint_axes.PROCEDURE(
            session, points=args.points, smrs=args.smrs, output=str(robot_file), shots=args.shots, **sigma
        )
    measured_s = time.time() - t0
    effects = parse_effect_flags(args.effects)
    cell = SimulatedCell(SimCellConfig(seed=args.seed, **effects))
    q_ref = result.axes.q_ref_rad
    _, frames = cell.true_joint_offsets(q_ref, np.ones(6), 0.0)
    F = cell.T_tracker_base @ frames[0]
    print(
        f"simulated UR10 seed {args.seed}, effects {args.effects}: at least {args.points} points per arc, "
        f"{args.smrs or len(config.nests_flange_m)} SMR(s), shots {args.shots or config.shots_per_point}, "
        f"reference pose {np.round(np.rad2deg(q_ref), 1).tolist()} deg ({measured_s:.0f} s incl. registration)"
    )
    df = campaign_dataset_of(folder / "campaign.sqlite")
    print(axis_table(result.axes, df, F))

    if args.no_calibration:
        return
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
