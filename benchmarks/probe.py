"""Several SMRs per pose and a 6-DoF probe's orientation: what they add to the geometric calibration.

Run:  PYTHONPATH=. python benchmarks/probe.py [--seeds 0,1,2,3,4] [--step-mm 150]

On simulated UR10 cells (hidden geometric errors only, so that the figures are about identifiability) a
grid campaign is calibrated four ways: one SMR (nest 1), three SMRs read at every pose (nests 1-3), one SMR
with a 6-DoF probe's orientation (0.01 deg per axis), and three SMRs with the probe (every row a fresh
orientation reading, each nest its own probe frame). Per way, over the seeds (median): the condition number after the identifiability step, the standard errors of joint 5's
parameters (theta5, d5, a5, alpha5, which positions see only through the short tool lever) and the RMS
error of all kinematic parameters kept in every way against the injected errors (angles in urad, lengths
in um), the held-out orientation error of the probe ways (30 random poses, noise-free readings), and the
time of one ridge + IGG3 calibration.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from fakes.campaign import Probe, simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.calibration.solve import calibrate
from hil.data.dataset import ORIENTATION_COLUMNS, orientations
from hil.runner.planners import facing_poses, grid_points, plan_joints, random_points, workspace_box

WRIST = ("theta5", "d5", "a5", "alpha5")
WAYS = ("1 SMR", "3 SMRs", "1 SMR + probe", "3 SMRs + probe")


def planned_joints(cell: SimulatedCell, points_in_box, seed: int) -> np.ndarray:
    """Usable joints for the points `points_in_box(box, rng)` of the default box, facing the tracker."""
    rng = np.random.default_rng(seed)
    p_base_tracker = np.linalg.inv(cell.T_tracker_base)[:3, 3]
    points = points_in_box(workspace_box(cell.nominal, p_base_tracker), rng)
    poses = facing_poses(points, p_base_tracker, rng, tilt_deg=20.0)
    p_nest = np.asarray(cell.config.tool_nests_flange_m[0])
    plan = plan_joints(cell.nominal, poses, p_nest, np.asarray(cell.config.q_home_rad), singular_sigma_m=0.0)
    return plan.q[plan.usable]


def one_seed(seed: int, step_m: float) -> dict[str, dict]:
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, compliance=False))
    truth = cell.ground_truth()["parameter_errors"]
    probe = Probe.drawn(seed)
    q = planned_joints(cell, lambda box, rng: grid_points(box, step_m), seed)
    both = simulate_campaign(cell, q, nests=[1, 2, 3], probe=probe)
    frames = {
        "3 SMRs + probe": both,
        "1 SMR + probe": both[both["smr"] == 1].reset_index(drop=True),
    }
    frames["3 SMRs"] = both.drop(columns=list(ORIENTATION_COLUMNS))
    frames["1 SMR"] = frames["1 SMR + probe"].drop(columns=list(ORIENTATION_COLUMNS))
    q_val = planned_joints(cell, lambda box, rng: random_points(box, 60, rng), seed + 7)[:30]
    val = simulate_campaign(cell, q_val, probe=Probe(probe.R_flange_probe, 0.0))
    out = {}
    for way in WAYS:
        t0 = time.perf_counter()
        res = calibrate(frames[way], "ur10")
        seconds = time.perf_counter() - t0
        table = {r["name"]: r for r in res.parameter_table()}
        row = {
            "rows": len(frames[way]),
            "condition": res.identifiability.condition_after if res.identifiability else float("nan"),
            "wrist_std": {n: table[n]["std_ls"] for n in WRIST},
            "errors": {n: table[n]["delta"] - truth[n] for n in cell.nominal.param_names if n in table},
            "seconds": seconds,
            "orientation_deg": float("nan"),
        }
        if "probe" in way:
            R = res.model.predict_rotation(val) @ np.swapaxes(orientations(val), 1, 2)
            row["orientation_deg"] = float(
                np.rad2deg(np.sqrt(np.mean(Rotation.from_matrix(R).magnitude() ** 2)))
            )
        out[way] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--step-mm", type=float, default=150.0)
    args = ap.parse_args()
    runs = [one_seed(int(s), args.step_mm / 1000) for s in args.seeds.split(",")]
    common = set.intersection(*(set(r[w]["errors"]) for r in runs for w in WAYS))
    ang = sorted(n for n in common if n.rstrip("0123456789") in ("theta", "alpha", "beta"))
    lin = sorted(n for n in common if n not in ang)
    print(f"UR10 grid {args.step_mm:g} mm, seeds {args.seeds}; medians over the seeds")
    head = f"{'way':<16}{'rows':>6}{'cond':>7}" + "".join(f"{'std ' + n:>13}" for n in WRIST)
    print(head + f"{'err ang':>10}{'err len':>10}{'held-out rot':>14}{'time':>8}")
    units = "".join(f"{'(urad|um)':>13}" for _ in WRIST)
    print(f"{'':<29}{units}{'urad':>10}{'um':>10}{'deg':>14}{'s':>8}")
    for way in WAYS:
        rows = [r[way] for r in runs]
        cols = [
            _median(rows, lambda r: r["rows"]),
            _median(rows, lambda r: r["condition"]),
            *(_median(rows, lambda r, n=n: r["wrist_std"][n] * 1e6) for n in WRIST),
            _median(rows, lambda r: _rms(r, ang)),
            _median(rows, lambda r: _rms(r, lin)),
            _median(rows, lambda r: r["orientation_deg"]),
            _median(rows, lambda r: r["seconds"]),
        ]
        fmt = ["6.0f", "7.1f", *["13.2f"] * len(WRIST), "10.2f", "10.2f", "14.4f", "8.2f"]
        print(f"{way:<16}" + "".join(format(v, f) for v, f in zip(cols, fmt, strict=True)))


def _median(rows: list[dict], f) -> float:
    return float(np.median([f(r) for r in rows]))


def _rms(row: dict, names: list[str]) -> float:
    """RMS error of the named parameters against the injected ones, x 1e6 (urad or um)."""
    return float(np.sqrt(np.mean([row["errors"][n] ** 2 for n in names])) * 1e6)


if __name__ == "__main__":
    main()
