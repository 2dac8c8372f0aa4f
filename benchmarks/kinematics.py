"""Kinematics benchmark: batch FK and IK throughput, IK success, and (if installed) roboticstoolbox's C++ ik_LM.

Run:  PYTHONPATH=. python benchmarks/kinematics.py [--robot ur10] [--n-ik 1000] [--repeats 3]

Honesty rules: both solvers get the same targets, their answers are judged by the same criterion (our FK,
position error < 1e-10 m and rotation error < 1e-9 rad), roboticstoolbox's tolerance on its residual
E = 1/2 |e|^2 is set so that its own success implies that criterion, and the FK of both is compared on the
same joints before any IK timing (the maximum disagreement is printed).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from hil.geometry import ik
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.robots import get_robot
from hil.geometry.se3 import pose_error

TOL_POSITION = 1e-10  # m
TOL_ROTATION = 1e-9  # rad
# E = 1/2 (|dp|^2 + |dr|^2) below this guarantees both tolerances above.
RTB_TOL = 0.5 * min(TOL_POSITION, TOL_ROTATION) ** 2
CALIBRATION_ERRORS = {
    "beta2": 2e-3,
    "beta3": -1.5e-3,
    "a2": 1e-3,
    "a3": -5e-4,
    "theta4": 2e-3,
    "alpha5": 1e-3,
}


def best_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Smallest wall time of `repeats` runs (the machine is shared) and the last result."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def judged(model: KinematicModel, q: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our success criterion applied to any solver's joints: (success (N,), position error (N,) m)."""
    e = pose_error(forward_kinematics(model, q), targets)
    pos, rot = np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)
    return (pos < TOL_POSITION) & (rot < TOL_ROTATION) & model.within_limits(q, tol=1e-9), pos


class Table:
    def __init__(self) -> None:
        self.rows: list[tuple[str, ...]] = []

    def add(self, *cols: object) -> None:
        self.rows.append(tuple(str(c) for c in cols))

    def print(self, header: tuple[str, ...]) -> None:
        rows = [header, *self.rows]
        widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
        for k, r in enumerate(rows):
            print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)))
            if k == 0:
                print("  ".join("-" * w for w in widths))


def rtb_ets(model: KinematicModel):
    """The model as a roboticstoolbox ETS: per joint [Rz(theta)] Rz(q) tz(d) tx(a) Rx(alpha) [Ry(beta)]."""
    from roboticstoolbox import ET

    ets = None
    for i in range(model.n_joints):
        parts = []
        if model.theta[i] != 0:
            parts.append(ET.Rz(float(model.theta[i])))
        parts.append(ET.Rz(qlim=model.joint_limits[i]))
        if model.d[i] != 0:
            parts.append(ET.tz(float(model.d[i])))
        if model.a[i] != 0:
            parts.append(ET.tx(float(model.a[i])))
        if model.alpha[i] != 0:
            parts.append(ET.Rx(float(model.alpha[i])))
        if model.beta[i] != 0:
            parts.append(ET.Ry(float(model.beta[i])))
        for p in parts:
            ets = p if ets is None else ets * p
    if not np.allclose(model.T_last_flange, np.eye(4)):
        raise NotImplementedError("benchmark ETS conversion assumes T_last_flange = I")
    return ets


def rtb_solve(ets, targets: np.ndarray, q0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """One ik_LM call per target (its C++ path); returns (q (N, n), its own success flags)."""
    q = np.empty((len(targets), ets.n))
    ok = np.empty(len(targets), bool)
    for k, T in enumerate(targets):
        sol = ets.ik_LM(T, q0=None if q0 is None else q0[k], tol=RTB_TOL, joint_limits=True)
        q[k], ok[k] = sol.q, sol.success
    return q, ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--n-ik", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    nominal = get_robot(args.robot)
    applied = {k: v for k, v in CALIBRATION_ERRORS.items() if k in nominal.param_names}
    calibrated = nominal.with_errors(applied)

    table = Table()
    for n in (10**4, 10**5):
        q = rng.uniform(nominal.joint_limits[:, 0], nominal.joint_limits[:, 1], size=(n, 6))
        t, _ = best_time(lambda q=q: forward_kinematics(nominal, q), args.repeats)
        table.add(f"hil FK {args.robot}", n, f"{n / t:,.0f} poses/s", f"{t / n * 1e6:.2f}", "-", "-")
    if ik.is_ur_like(nominal):
        q = rng.uniform(-np.pi, np.pi, size=(10**4, 6))
        T = forward_kinematics(nominal, q)
        t, _ = best_time(lambda: ik.ur_analytic_ik(nominal, T), args.repeats)
        table.add(
            "hil analytic UR IK (8 branches)",
            10**4,
            f"{1e4 / t:,.0f} poses/s",
            f"{t / 1e4 * 1e6:.2f}",
            "-",
            "-",
        )

    n = args.n_ik
    cases = {}
    for label, model in (("nominal", nominal), ("calibrated", calibrated)):
        q_true = rng.uniform(model.joint_limits[:, 0], model.joint_limits[:, 1], size=(n, 6))
        cases[label] = (model, forward_kinematics(model, q_true))
    hil_time = {}
    for label, (model, targets) in cases.items():
        variants = [("analytic seed", True)] if ik.is_ur_like(model) else []
        variants.append(("unseeded (home + random restarts)", False))
        for vname, use_analytic in variants:
            t, res = best_time(
                lambda m=model, T=targets, u=use_analytic: ik.solve_ik(
                    m, T, options=ik.IKOptions(use_analytic=u)
                ),
                args.repeats,
            )
            ok, pos = judged(model, res.q, targets)
            assert np.array_equal(ok, res.success), "solve_ik success disagrees with the independent check"
            hil_time[(label, use_analytic)] = t / n
            table.add(
                f"hil solve_ik {label}, {vname}",
                n,
                f"{n / t:,.0f} solves/s",
                f"{t / n * 1e6:.1f}",
                f"{ok.mean():.4f}",
                f"{np.median(pos):.1e}",
            )

    notes = []
    try:
        import roboticstoolbox  # noqa: F401
    except ImportError as exc:  # optional extra `bench`
        notes.append(f"roboticstoolbox-python comparison skipped: {exc} (pip install -e .[bench])")
    else:
        for label, (model, targets) in cases.items():
            ets = rtb_ets(model)
            q_chk = rng.uniform(-np.pi, np.pi, size=(200, 6))
            fk_diff = max(
                np.abs(np.asarray(ets.fkine(qq).A) - T).max()
                for qq, T in zip(q_chk, forward_kinematics(model, q_chk), strict=True)
            )
            notes.append(f"FK agreement hil vs roboticstoolbox ETS ({label}): max |dT| = {fk_diff:.1e}")
            if fk_diff > 1e-12:
                notes.append("  FK disagree: skipping this IK comparison")
                continue
            variants = [("random q0 (its restarts)", False)]
            if ik.is_ur_like(model):
                variants.insert(0, ("same analytic seed (seed time included)", True))
            for sname, seeded in variants:
                t, (q_rtb, own_ok) = best_time(
                    lambda e=ets, m=model, T=targets, s=seeded: rtb_solve(
                        e, T, ik.ur_seed(m, T) if s else None
                    ),
                    args.repeats,
                )
                ok, pos = judged(model, q_rtb, targets)
                ratio = (t / n) / hil_time[(label, seeded)]
                table.add(
                    f"rtb ets.ik_LM C++ {label}, {sname}",
                    n,
                    f"{n / t:,.0f} solves/s",
                    f"{t / n * 1e6:.1f}",
                    f"{ok.mean():.4f} (own flag {own_ok.mean():.4f})",
                    f"{np.median(pos):.1e}",
                )
                notes.append(f"rtb/hil time per solve ({label}, {sname} vs hil same seeding): {ratio:.2f}x")

    print(
        f"Kinematics benchmark, robot {args.robot}; success = position error < {TOL_POSITION:g} m and "
        f"rotation error < {TOL_ROTATION:g} rad by hil FK (rtb tol E < {RTB_TOL:g}); best of {args.repeats}"
    )
    print(f"calibrated model: {calibrated.name} + {applied}")
    table.print(("case", "N", "throughput", "us/item", "success", "median pos err m"))
    for line in notes:
        print(line)


if __name__ == "__main__":
    main()
