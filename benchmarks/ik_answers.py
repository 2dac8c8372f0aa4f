"""IK answers before and after a speed change: solve_ik, newton_ik and pose_and_jacobian compared array by array.

Run:  PYTHONPATH=. python benchmarks/ik_answers.py --save before.npz      (on the old code)
      PYTHONPATH=. python benchmarks/ik_answers.py --against before.npz   (on the new code)

Problems: four arms (a UR10, and the LR Mate, IRB 2600 and KR 6 R900, whose joints turn less than a full
turn, so LM holds joints at their limits), each with calibration-sized errors, and a UR10 with a fixed
flange transform; 1, 2, 5, 30 and 200 targets (the small-batch chain and the column-wise one); poses and
tool points, some moved off the arm's reach; `solve_ik` with restarts, with the compensation loop's
update fallback (LM from the seeds only) and with a short LM budget; `newton_ik` from perturbed seeds.
Printed: the arrays that differ and by how much. `benchmarks/compensation_answers.py` does the same for
compensation; a change meant to be faster only should leave every array here bit for bit the same.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from hil.geometry.ik import IKOptions, NewtonOptions, newton_ik, random_joints, solve_ik
from hil.geometry.kinematics import KinematicModel, forward_kinematics, pose_and_jacobian
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform

ARMS = ("ur10", "lrmate200id", "irb2600", "kr6r900", "ur10 with a flange transform")
SIZES = (1, 2, 5, 30, 200)
TOOL = np.array([0.03, -0.02, 0.11])
SOLVE_OPTIONS = {
    "restarts": IKOptions(restarts=3),
    "update fallback": IKOptions(restarts=0, use_analytic=False, newton_first=False),
    "short": IKOptions(restarts=2, max_iter=40),
}
NEWTON = NewtonOptions(max_steps=16, tol_position=1e-8, tol_rotation=1e-7)  # the compensation loop's budget


def arm(name: str, rng: np.random.Generator) -> KinematicModel:
    """The named robot with errors of a real arm's size (lengths 0.3 mm, angles 0.5 mrad, 1-sigma)."""
    nominal = get_robot(name.split()[0])
    if name.endswith("flange transform"):
        flange = make_transform(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [0.01, -0.02, 0.05])
        nominal = dataclasses.replace(nominal, T_last_flange=flange)
    return nominal.with_errors(
        {p: rng.normal(0.0, 3e-4 if p[0] in "ad" else 5e-4) for p in nominal.param_names}
    )


def answers(seed: int) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    rng = np.random.default_rng(seed)
    for name in ARMS:
        kin = arm(name, rng)
        for n in SIZES:
            q = random_joints(kin, n, rng)
            T = forward_kinematics(kin, q)
            T[:, :3, 3] += rng.normal(0.0, 0.02, (n, 3)) * (rng.random((n, 1)) < 0.3)  # some moved
            T[rng.random(n) < 0.1, :3, 3] *= 1.6  # some beyond reach
            seeds = q + rng.normal(0.0, 0.3, q.shape)
            points = T[:, :3, :3] @ TOOL + T[:, :3, 3]
            for mode, targets, tool in (("pose", T, None), ("position", points, TOOL)):
                key = f"{name}/{n}/{mode}"
                for label, options in SOLVE_OPTIONS.items():
                    res = solve_ik(kin, targets, seeds, mode, p_flange_tool=tool, options=options)
                    for f in ("q", "success", "iterations", "error", "rotation_error"):
                        out[f"{key}/solve_ik {label}/{f}"] = getattr(res, f)
                    out[f"{key}/solve_ik {label}/reason"] = res.reason.astype(str)
                newton = newton_ik(kin, targets, seeds, mode, tool, NEWTON)
                for f in ("q", "error", "converged", "steps", "pose", "jacobian"):
                    out[f"{key}/newton_ik/{f}"] = getattr(newton, f)
            T_chain, J_chain = pose_and_jacobian(kin, q, TOOL)
            out[f"{name}/{n}/pose_and_jacobian/T"], out[f"{name}/{n}/pose_and_jacobian/J"] = T_chain, J_chain
    return out


def compare(old: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> None:
    differ = 0
    for key, a in old.items():
        b = new[key]
        if a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
            continue
        differ += 1
        size = np.nanmax(np.abs(a - b)) if a.dtype.kind == "f" and a.shape == b.shape else None
        print(f"differs: {key}" + ("" if size is None else f", max |difference| {size:.2e}"))
    print(f"{len(old)} arrays, {differ} differ")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--save", help="write this code's answers to this .npz")
    ap.add_argument("--against", help="compare this code's answers with those saved in this .npz")
    args = ap.parse_args()
    new = answers(args.seed)
    if args.save:
        np.savez_compressed(args.save, **new)
    if args.against:
        with np.load(args.against) as f:
            compare({k: f[k] for k in f.files}, new)


if __name__ == "__main__":
    main()
