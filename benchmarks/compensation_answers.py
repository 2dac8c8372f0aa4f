"""Compensation answers before and after a speed change: every target's joints and reached pose compared.

Run:  PYTHONPATH=. python benchmarks/compensation_answers.py --save before.npz      (on the old code)
      PYTHONPATH=. python benchmarks/compensation_answers.py --against before.npz   (on the new code)

The targets are those of benchmarks/compensation.py (its models, both cases, poses and points, 10 000 each).
Printed per case and kind: the largest joint difference, the largest difference in the predicted reached
position and orientation, success (below the threshold) and status counts of old and new, and the targets whose
status changed. A speed change is meant to leave answers within the solver's tolerance (IK_TOL_FRACTION of
the threshold), not to move them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from compensation import CASES, MAX_ITER, THRESHOLD_M, calibrated_ur10  # benchmarks/compensation.py

from hil.compensation.model_based import CompensationOptions, compensate
from hil.compensation.target_update import pose_errors

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from calib_data import ur10_joints  # noqa: E402 - the calibration tests' joint sampler


def answers(n: int, seed: int) -> dict[str, np.ndarray]:
    """Per case and kind: joints, the model's predicted poses at them, status and iterations."""
    out: dict[str, np.ndarray] = {}
    for case in CASES:
        model = calibrated_ur10(seed, case)
        T_all = model.predict_poses(ur10_joints(np.random.default_rng(seed + 1), n))
        for kind, full_pose in (("poses", True), ("points", False)):
            targets = T_all if full_pose else T_all[:, :3, 3]
            opts = CompensationOptions(
                generator="yin" if full_pose else None, threshold_m=THRESHOLD_M, max_iter=MAX_ITER
            )
            res = compensate(model, targets, opts)
            key = f"{case}/{kind}"
            good = np.all(np.isfinite(res.q), axis=1)
            T_reached = np.full((n, 4, 4), np.nan)
            T_reached[good] = model.predict_poses(res.q[good])
            out[f"{key}/q"] = res.q
            out[f"{key}/T"] = T_reached
            out[f"{key}/T_target"] = T_all
            out[f"{key}/status"] = res.status.astype(str)
            out[f"{key}/iterations"] = res.iterations
    return out


def compare(old: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> None:
    for case in CASES:
        for kind in ("poses", "points"):
            key = f"{case}/{kind}"
            q0, q1 = old[f"{key}/q"], new[f"{key}/q"]
            both = np.all(np.isfinite(q0), axis=1) & np.all(np.isfinite(q1), axis=1)
            dq = np.abs(q1[both] - q0[both]).max(axis=1)
            dp, dr = pose_errors(new[f"{key}/T"][both], old[f"{key}/T"][both])
            T_target = old[f"{key}/T_target"]
            s0, s1 = old[f"{key}/status"], new[f"{key}/status"]
            ok0, ok1 = (s0 == "ok").mean(), (s1 == "ok").mean()
            e0 = pose_errors(old[f"{key}/T"][both], T_target[both])[0]
            e1 = pose_errors(new[f"{key}/T"][both], T_target[both])[0]
            print(f"{key}: {len(q0)} targets, {both.sum()} with joints in both")
            print(
                f"  max |dq| {dq.max():.2e} rad (99.9 %: {np.quantile(dq, 0.999):.2e}); reached position "
                f"moved max {dp.max() * 1e6:.4f} um, orientation max {np.rad2deg(dr.max()) * 1e3:.4f} mdeg"
            )
            print(
                f"  success old {ok0:.4f} new {ok1:.4f}; remaining position error max old "
                f"{e0.max() * 1e6:.3f} um new {e1.max() * 1e6:.3f} um; mean iterations old "
                f"{old[f'{key}/iterations'].mean():.3f} new {new[f'{key}/iterations'].mean():.3f}"
            )
            changed = np.flatnonzero(s0 != s1)
            if changed.size:
                pairs = {
                    f"{a}->{b}": int(np.sum((s0 == a) & (s1 == b)))
                    for a, b in set(zip(s0[changed], s1[changed], strict=True))
                }
                print(f"  status changed on {changed.size} targets: {pairs}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", help="write this code's answers to this .npz")
    ap.add_argument("--against", help="compare this code's answers with those saved in this .npz")
    args = ap.parse_args()
    new = answers(args.n, args.seed)
    if args.save:
        np.savez_compressed(args.save, **new)
    if args.against:
        with np.load(args.against) as f:
            old = {k: f[k] for k in f.files}
        compare(old, new)


if __name__ == "__main__":
    main()
