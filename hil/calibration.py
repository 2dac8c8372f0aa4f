"""Identify base frame, tool points, kinematic errors (and effect coefficients) from a dataset.

Two solvers over the same model and the same identifiable parameter set:

- ``ridge``: ridge-regularised Gauss-Newton with IGG3 re-weighting (grid paper, methods.md 2b). The
  ridge term pulls the kinematic and effect parameters towards their nominal values in the scaled
  parameter space: mu = `ridge` x the largest eigenvalue of the scaled normal matrix. IGG3 acts on each
  measured point (one SMR reading is one observation): its standardised residual is the RMS over its
  three coordinates of v_i / (s sqrt(r_i)), r_i the redundancy number 1 - a_i N^-1 a_i^T and s a robust
  scale fixed once from the converged least-squares solution (1.4826 x the median absolute residual; the
  paper's a-posteriori sigma0 shrinks as points are rejected and can make the re-weighting reject ever
  more points). Weights
  are recomputed from the standardised residuals at every step, so a point rejected while the model was
  still far off can come back.
- ``lm``: scipy ``least_squares`` (trust-region, Levenberg-Marquardt-like) with a robust loss (soft L1,
  scale 1.5 sigma, sigma from a first least-squares pass by the median absolute deviation).

Both report parameter standard errors (sigma0^2 times the inverse of the normal matrix) and flag a point
as an outlier when its standardised residual exceeds k1.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from hil.calibrated_model import CalibratedModel, initial_model
from hil.dataset import data_rows, joints_rad, points_m, smr_ids
from hil.effects import EffectContext
from hil.folds import location_spacing, spatial_folds
from hil.identifiability import IdentifiabilityReport, analyse, scale_columns
from hil.kinematics import KinematicModel
from hil.se3 import fit_rigid

K0, K1 = 1.5, 2.5  # IGG3 thresholds of the grid paper
# Beyond this many rows the solvers converge on a fixed random subset of them, then finish on every row
# (IGG3 iterations linearised at the subset's solution until converged, at most FINISH_ITERS, or LM
# from that start).
CONVERGE_ROWS = 10000
FINISH_ITERS = 30


@dataclass
class Problem:
    """A dataset prepared for fitting: context, nest ids, measured points."""

    ctx: EffectContext
    smr: np.ndarray
    measured: np.ndarray  # (N, 3) m

    @classmethod
    def from_frame(cls, model: CalibratedModel, df: pd.DataFrame) -> Problem:
        ctx, _ = model.context(df)
        return cls(ctx, smr_ids(df), points_m(df))

    def subset(self, rows: np.ndarray) -> Problem:
        return Problem(self.ctx.subset(rows), self.smr[rows], self.measured[rows])

    def evaluate(self, model: CalibratedModel) -> tuple[np.ndarray, np.ndarray]:
        """Residuals measured - predicted (N, 3) and the Jacobian (N, 3, P) at `model`."""
        self.ctx.p_flange_tool = model._row_tools(self.smr)
        p, J = model.jacobian_ctx(self.ctx, self.smr)
        return self.measured - p, J

    def residuals(self, model: CalibratedModel) -> np.ndarray:
        self.ctx.p_flange_tool = model._row_tools(self.smr)
        return self.measured - model.predict_ctx(self.ctx)


@dataclass
class CalibrationResult:
    model: CalibratedModel
    solver: str
    free: list[str]
    std: dict[str, float]
    sigma0_m: float
    weights: np.ndarray  # (N,) final point weights
    outliers: np.ndarray  # (N,) bool
    residual_m: np.ndarray  # (N, 3) measured - predicted
    iterations: int
    identifiability: IdentifiabilityReport | None = None
    notes: list[str] = field(default_factory=list)
    row_numbers: np.ndarray | None = None  # data row (from 1) in the source file of each point
    std_folds: dict[str, float] = field(default_factory=dict)  # spread over spatial folds (jackknife)
    outlier_regions: list[dict] = field(default_factory=list)  # flagged rows that cluster in space

    @property
    def outlier_rows(self) -> list[int]:
        """Flagged points as data rows of the source file, counting from 1."""
        rows = np.arange(1, len(self.outliers) + 1) if self.row_numbers is None else self.row_numbers
        return [int(r) for r in rows[self.outliers]]

    @property
    def rms_mm(self) -> float:
        ok = ~self.outliers
        return float(np.sqrt(np.mean(np.sum(self.residual_m[ok] ** 2, axis=1))) * 1000)

    def honest_std(self, name: str) -> float | None:
        """The larger of the least-squares standard error and the spread over spatial folds."""
        ls, folds = self.std.get(name), self.std_folds.get(name)
        return None if ls is None else max(ls, folds or 0.0)

    def parameter_table(self) -> list[dict]:
        """Per free parameter: value, change from nominal (or start) and standard errors (the honest
        one, the least-squares one and the spatial-fold spread), SI units."""
        names = self.model.param_names
        nominal = dict(zip(self.model.nominal.param_names, self.model.nominal.params, strict=True))
        values = full_values(self.model)
        rows = []
        for nm in self.free:
            v = float(values[names.index(nm)])
            rows.append(
                {
                    "name": nm,
                    "value": v,
                    "delta": v - float(nominal[nm]) if nm in nominal else None,
                    "std": self.honest_std(nm),
                    "std_ls": self.std.get(nm),
                    "std_folds": self.std_folds.get(nm),
                    "unit": unit_of(nm),
                }
            )
        return rows

    def to_dict(self) -> dict:
        return {
            "solver": self.solver,
            "sigma0_mm": self.sigma0_m * 1000,
            "rms_mm": self.rms_mm,
            "iterations": self.iterations,
            "parameters": self.parameter_table(),
            "outlier_rows": self.outlier_rows,
            "outlier_regions": [
                {**reg, "rows": [int(self.row_numbers[i]) for i in reg["rows"]]}
                for reg in self.outlier_regions
            ]
            if self.row_numbers is not None
            else self.outlier_regions,
            "identifiability": self.identifiability.to_dict() if self.identifiability else None,
            "notes": self.notes,
        }


def unit_of(name: str) -> str:
    kind = name.rstrip("0123456789")
    if kind in ("theta", "alpha", "beta") or name in ("base_rx", "base_ry", "base_rz"):
        return "rad"
    if kind in ("a", "d") or name.startswith(("base_t", "tool")):
        return "m"
    return "coef"


def full_values(model: CalibratedModel) -> np.ndarray:
    """Current values in the full parameter order (base: translation and rotation vector of T)."""
    from scipy.spatial.transform import Rotation

    vals = list(model.kinematic.params)
    vals += list(model.T_tracker_base[:3, 3]) + list(
        Rotation.from_matrix(model.T_tracker_base[:3, :3]).as_rotvec()
    )
    for smr in sorted(model.tools):
        vals += list(model.tools[smr])
    for eff in model.effects:
        vals += list(eff.params)
    return np.asarray(vals, float)


def flatten_jacobian(J: np.ndarray) -> np.ndarray:
    """(N, 3, P) point Jacobian -> (3N, P) rows in the order of the flattened (N, 3) residual."""
    return J.reshape(-1, J.shape[-1])


def identify(model: CalibratedModel, problem: Problem, tol: float = 1e-3) -> IdentifiabilityReport:
    """Identifiability analysis of all parameters of `model` on `problem`."""
    _, J = problem.evaluate(model)
    return analyse(flatten_jacobian(J), model.param_names, tol=tol)


def _redundancy(Js: np.ndarray, Ninv: np.ndarray) -> np.ndarray:
    """Unit-weight redundancy numbers 1 - a_i N^-1 a_i^T of each row (clipped below at 0.05)."""
    h = np.einsum("ij,jk,ik->i", Js, Ninv, Js)
    return np.clip(1.0 - h, 0.05, None)


def igg3_weight(t: np.ndarray, k0: float = K0, k1: float = K1) -> np.ndarray:
    """IGG3 weight factor of standardised residuals t."""
    t = np.abs(t)
    w = np.ones_like(t)
    mid = (t > k0) & (t <= k1)
    w[mid] = (k0 / t[mid]) * ((k1 - t[mid]) / (k1 - k0)) ** 2
    w[t > k1] = 0.0
    return w


def solve_ridge_igg3(
    model: CalibratedModel,
    problem: Problem,
    free: np.ndarray,
    ridge: float = 1e-7,
    k0: float = K0,
    k1: float = K1,
    max_iter: int = 60,
    robust: bool = True,
    frozen_jacobian: bool = False,
) -> CalibrationResult:
    """Robust ridge estimation with IGG3 re-weighting (see module docstring).

    `frozen_jacobian` linearises once at `model` (which must be near the optimum, e.g. a subset's
    solution): the iterations then cost no kinematics, the model is updated once at the end.
    """
    free = np.asarray(free, bool)
    names = model.param_names
    start = model
    if frozen_jacobian:
        r0, J0 = problem.evaluate(model)
        r0v, J0f = r0.reshape(-1), flatten_jacobian(J0)[:, free]
        del J0
    prior_mask = np.array([not (n.startswith("base_") or n.startswith("tool")) for n in names])[free]
    N_pts = problem.measured.shape[0]
    w_pts = np.ones(N_pts)
    dev = np.zeros(int(free.sum()))  # accumulated change of the free parameters since the start
    warm = 0
    it = 0
    sigma_robust: float | None = None
    for it in range(1, max_iter + 1):  # noqa: B007
        if frozen_jacobian:
            r, Jf = (r0v - J0f @ dev).reshape(-1, 3), J0f
        else:
            r, J = problem.evaluate(model)
            Jf = flatten_jacobian(J)[:, free]
        Js, norms = scale_columns(Jf)
        rv = r.reshape(-1)
        w_rows = np.repeat(w_pts, 3)
        Nm = (Js * w_rows[:, None]).T @ Js
        mu = ridge * np.linalg.eigvalsh(Nm)[-1]
        M = Nm + mu * np.diag(prior_mask.astype(float))
        rhs = Js.T @ (w_rows * rv) - mu * prior_mask * (dev * norms)
        step_s = np.linalg.solve(M + 1e-14 * np.trace(M) / len(M) * np.eye(len(M)), rhs)
        step = step_s / norms
        # Backtrack when the step does not lower the penalised weighted cost (guards weak directions).
        cost0 = float(np.sum(w_rows * rv**2) + mu * np.sum(prior_mask * (dev * norms) ** 2))
        for _ in range(12):
            dx = np.zeros(len(names))
            dx[free] = step
            if frozen_jacobian:
                trial, r_new = model, r0v - J0f @ (dev + step)
            else:
                trial = model.apply_increment(dx)
                r_new = problem.residuals(trial).reshape(-1)
            cost = float(np.sum(w_rows * r_new**2) + mu * np.sum(prior_mask * ((dev + step) * norms) ** 2))
            if cost <= cost0 * (1 + 1e-12):
                break
            step, step_s = step / 2, step_s / 2
        model = trial
        dev += step
        small = np.max(np.abs(step_s)) < 1e-8 or cost >= cost0 * (1 - 1e-10)  # converged
        if not robust:
            if small:
                break
            continue
        warm += 1
        if warm < 15 and not small and np.all(w_pts == 1):
            continue  # plain Gauss-Newton to convergence before judging points (IGG3 is not convex)
        Minv = np.linalg.pinv(M)
        red = _redundancy(Js, Minv)
        # Robust scale, fixed once from the least-squares solution (1.4826 x median absolute residual of
        # all coordinates): a weighted sigma0 re-estimated each step shrinks as points are rejected and
        # lets the re-weighting reject ever more points.
        if sigma_robust is None:
            sigma_robust = max(1.4826 * float(np.median(np.abs(r_new))), 1e-12)
        t_rows = r_new / (sigma_robust * np.sqrt(red))
        t_pts = np.sqrt(np.mean(t_rows.reshape(-1, 3) ** 2, axis=1))
        w_new = igg3_weight(t_pts, k0, k1)
        changed = np.max(np.abs(w_new - w_pts)) > 1e-6
        w_pts = w_new
        if small and not changed:
            break
    if frozen_jacobian:
        dx = np.zeros(len(names))
        dx[free] = dev
        model = start.apply_increment(dx)
    r, J = problem.evaluate(model)
    Jf = flatten_jacobian(J)[:, free]
    Js, norms = scale_columns(Jf)
    w_rows = np.repeat(w_pts, 3)
    Nm = (Js * w_rows[:, None]).T @ Js
    mu = ridge * np.linalg.eigvalsh(Nm)[-1]
    dof = max(int(np.count_nonzero(w_rows)) - int(free.sum()), 1)
    sigma0 = float(np.sqrt(np.sum(w_rows * r.reshape(-1) ** 2) / dof))
    cov_s = np.linalg.inv(Nm + mu * np.diag(prior_mask.astype(float)) + 1e-14 * np.eye(len(Nm)))
    std = sigma0 * np.sqrt(np.diag(cov_s)) / norms
    free_names = [n for n, f in zip(names, free, strict=True) if f]
    return CalibrationResult(
        model=model,
        solver="ridge-igg3" if robust else "ridge",
        free=free_names,
        std=dict(zip(free_names, map(float, std), strict=True)),
        sigma0_m=sigma0,
        weights=w_pts,
        outliers=w_pts == 0,
        residual_m=r,
        iterations=it,
    )


def solve_lm(
    model: CalibratedModel,
    problem: Problem,
    free: np.ndarray,
    loss: str = "soft_l1",
    k1: float = K1,
    frozen_jacobian: bool = False,
) -> CalibrationResult:
    """Levenberg-Marquardt-type fit (scipy least_squares, trust region) with a robust loss.

    `frozen_jacobian`: linearised once at `model` (near the optimum), as in `solve_ridge_igg3`.
    """
    free = np.asarray(free, bool)
    names = model.param_names
    start = model
    if frozen_jacobian:
        r0, J0 = problem.evaluate(model)
        r0v, J0f = r0.reshape(-1), flatten_jacobian(J0)[:, free]
        del J0

    def at(x: np.ndarray) -> CalibratedModel:
        dx = np.zeros(len(names))
        dx[free] = x
        return start.apply_increment(dx)

    def fun(x: np.ndarray) -> np.ndarray:
        if frozen_jacobian:
            return J0f @ x - r0v
        return -problem.residuals(at(x)).reshape(-1)

    def jac(x: np.ndarray) -> np.ndarray:
        if frozen_jacobian:
            return J0f
        _, J = problem.evaluate(at(x))
        return flatten_jacobian(J)[:, free]

    x0 = np.zeros(int(free.sum()))
    first = least_squares(fun, x0, jac=jac, x_scale="jac", method="trf", max_nfev=30, xtol=1e-12, ftol=1e-12)
    sigma = 1.4826 * np.median(np.abs(first.fun - np.median(first.fun)))
    sigma = max(float(sigma), 1e-9)
    sol = least_squares(
        fun,
        first.x,
        jac=jac,
        x_scale="jac",
        method="trf",
        loss=loss,
        f_scale=K0 * sigma,
        max_nfev=60,
        xtol=1e-12,
    )
    fitted = at(sol.x)
    r, J = problem.evaluate(fitted)
    Jf = flatten_jacobian(J)[:, free]
    t_pts = np.sqrt(np.mean((r / sigma) ** 2, axis=1))
    outliers = t_pts > k1
    w_rows = np.repeat((~outliers).astype(float), 3)
    dof = max(int(w_rows.sum()) - int(free.sum()), 1)
    sigma0 = float(np.sqrt(np.sum(w_rows * r.reshape(-1) ** 2) / dof))
    Js, norms = scale_columns(Jf)
    cov_s = np.linalg.pinv((Js * w_rows[:, None]).T @ Js)
    std = sigma0 * np.sqrt(np.diag(cov_s)) / norms
    free_names = [n for n, f in zip(names, free, strict=True) if f]
    return CalibrationResult(
        model=fitted,
        solver=f"lm-{loss}",
        free=free_names,
        std=dict(zip(free_names, map(float, std), strict=True)),
        sigma0_m=sigma0,
        weights=(~outliers).astype(float),
        outliers=outliers,
        residual_m=r,
        iterations=int(first.nfev + sol.nfev),
    )


def calibrate(
    df: pd.DataFrame,
    robot: str | KinematicModel | CalibratedModel,
    solver: str = "ridge",
    tol: float = 1e-3,
    tool_guess_m: np.ndarray | None = None,
    ridge: float = 1e-7,
) -> CalibrationResult:
    """Full calibration of a dataset: initial registration, identifiability, robust solve.

    `robot` is a catalogue name, a nominal KinematicModel, or a CalibratedModel to start from (its
    effects are refitted together with the geometry). `solver` is "ridge" (IGG3) or "lm".
    """
    with threadpool_limits(1):  # small dense problems: BLAS threads only contend
        return _calibrate(df, robot, solver, tol, tool_guess_m, ridge)


def _calibrate(
    df: pd.DataFrame,
    robot: str | KinematicModel | CalibratedModel,
    solver: str,
    tol: float,
    tool_guess_m: np.ndarray | None,
    ridge: float,
) -> CalibrationResult:
    model = robot if isinstance(robot, CalibratedModel) else initial_model(robot, df, tool_guess_m)
    check_joint_limits(df, model.nominal)
    full = Problem.from_frame(model, df)
    # A big campaign converges on a fixed random subset first, then finishes on every row (below).
    big = len(df) > CONVERGE_ROWS
    problem = (
        full.subset(np.sort(np.random.default_rng(0).permutation(len(df))[:CONVERGE_ROWS])) if big else full
    )
    # Tool points first (the registration assumed a guess), so the identifiability sees a sane model.
    pre_free = np.array([n.startswith(("base_", "tool")) for n in model.param_names])
    model = solve_ridge_igg3(model, problem, pre_free, robust=False, max_iter=10).model
    report = identify(model, problem, tol)
    n_free = int(report.keep_mask.sum())
    if 3 * len(df) < 2 * n_free + 10:
        raise ValueError(
            f"{len(df)} points give {3 * len(df)} equations for {n_free} identifiable parameters; measure at "
            f"least {int(np.ceil((2 * n_free + 10) / 3))} well-spread poses (a 100-200 mm grid gives hundreds)"
        )
    if solver not in ("ridge", "lm"):
        raise ValueError(f"unknown solver '{solver}'; choose 'ridge' or 'lm'")
    if solver == "ridge":
        result = solve_ridge_igg3(model, problem, report.keep_mask, ridge=ridge)
        if big:  # IGG3 on every row, linearised at the subset's solution
            result = solve_ridge_igg3(
                result.model, full, report.keep_mask, ridge=ridge, max_iter=FINISH_ITERS, frozen_jacobian=True
            )
    elif solver == "lm":
        result = solve_lm(model, problem, report.keep_mask)
        if big:
            result = solve_lm(result.model, full, report.keep_mask, frozen_jacobian=True)
    else:
        raise ValueError(f"unknown solver '{solver}'; choose 'ridge' or 'lm'")
    problem = full
    result.identifiability = report
    result.row_numbers = data_rows(df)
    q = joints_rad(df, model.nominal.n_joints)
    result.model.info = {
        "solver": result.solver,
        "sigma0_mm": result.sigma0_m * 1000,
        "free": result.free,
        "std": result.std,
        "identifiability": report.to_dict(),
        "n_points": int(len(df)),
        "outlier_rows": result.outlier_rows,
        "training_joint_range_rad": [q.min(axis=0).tolist(), q.max(axis=0).tolist()],
    }
    result.notes += implausible_changes(result)
    _honest_numbers(result, problem)
    return result


def _honest_numbers(result: CalibrationResult, problem: Problem, k: int = 5) -> None:
    """Spatial-fold spread of the parameters, confounded pairs and outlier regions, into the result."""
    rows = np.flatnonzero(~result.outliers)
    inliers = problem.subset(rows)
    evaluated = inliers.evaluate(result.model)  # one Jacobian for both figures
    if len(rows) >= 4 * k:
        folds = spatial_folds(problem.measured[rows], k, 0)
        result.std_folds = fold_spread_std(result, inliers, folds, evaluated)
    pairs = confounded_pairs(result, inliers, evaluated=evaluated)
    for a, b, c in pairs:
        result.notes.append(
            f"confounded: {a} and {b} correlate {c:+.3f} on these poses; each alone is unreliable (their "
            "combination is); poses that move them differently separate them"
        )
    result.outlier_regions = outlier_regions(problem.measured, result.outliers)
    row_numbers = np.arange(1, len(result.outliers) + 1) if result.row_numbers is None else result.row_numbers
    for reg in result.outlier_regions:
        result.notes.append(
            f"outlier region: {reg['count']} flagged rows within {reg['radius_mm']:.0f} mm of "
            f"({', '.join(f'{v:.0f}' for v in reg['centre_mm'])}) mm (tracker frame), data rows "
            f"{', '.join(str(row_numbers[i]) for i in reg['rows'][:6])}{' ...' if reg['count'] > 6 else ''}: "
            "a region the model does not fit (a missing effect there), not blunders"
        )
    result.model.info["std_folds"] = result.std_folds
    result.model.info["outlier_regions"] = [
        {**reg, "rows": [int(row_numbers[i]) for i in reg["rows"]]} for reg in result.outlier_regions
    ]


def fold_spread_std(
    result: CalibrationResult, problem: Problem, folds: list[np.ndarray], evaluated: tuple | None = None
) -> dict[str, float]:
    """Jackknife over spatial folds: how much each free parameter moves when a block of the volume is
    left out. Unlike the least-squares covariance it sees model errors that depend on where one
    measures, so it is closer to what another campaign gives; reports use the larger of the two."""
    names = result.model.param_names
    free = np.array([n in set(result.free) for n in names])
    r, J = evaluated or problem.evaluate(result.model)
    Js, norms = scale_columns(flatten_jacobian(J)[:, free])
    rv = r.reshape(-1)
    N, g = Js.T @ Js, Js.T @ rv
    est = np.array(
        [
            np.linalg.lstsq(N - Js[t].T @ Js[t], g - Js[t].T @ rv[t], rcond=None)[0] / norms
            for t in ((3 * f[:, None] + np.arange(3)).ravel() for f in folds)
        ]
    )
    kf = len(folds)
    spread = np.sqrt((kf - 1) / kf * np.sum((est - est.mean(axis=0)) ** 2, axis=0))
    free_names = [n for n, m in zip(names, free, strict=True) if m]
    return {n: float(v) for n, v in zip(free_names, spread, strict=True)}


def confounded_pairs(
    result: CalibrationResult, problem: Problem, limit: float = 0.95, evaluated: tuple | None = None
) -> list[tuple]:
    """Pairs of free geometric parameters whose estimates correlate beyond `limit` (|corr|)."""
    names = result.model.param_names
    free = np.array([n in set(result.free) for n in names])
    _, J = evaluated or problem.evaluate(result.model)
    Js, _ = scale_columns(flatten_jacobian(J)[:, free])
    cov = np.linalg.pinv(Js.T @ Js)
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(sd, sd)
    fn = [n for n, m in zip(names, free, strict=True) if m]
    geo = set(result.model.nominal.param_names)
    out = []
    for i in range(len(fn)):
        for j in range(i + 1, len(fn)):
            if (fn[i] in geo or fn[j] in geo) and abs(corr[i, j]) > limit:
                out.append((fn[i], fn[j], float(corr[i, j])))
    return out


def outlier_regions(points: np.ndarray, outliers: np.ndarray, min_count: int = 4) -> list[dict]:
    """Flagged points that cluster in one part of the volume (each within two location spacings of
    another flagged point): a region the model does not fit, not independent blunders."""
    idx = np.flatnonzero(outliers)
    if len(idx) < min_count:
        return []
    radius = 2.0 * location_spacing(points)
    pairs = cKDTree(points[idx]).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    n_comp, label = connected_components(graph, directed=False)
    regions = []
    for c in range(n_comp):
        members = idx[label == c]
        if len(members) >= min_count:
            centre = points[members].mean(axis=0)
            regions.append(
                {
                    "count": int(len(members)),
                    "rows": members.tolist(),  # positions in the frame (0-based); reports print data rows
                    "centre_mm": (centre * 1000).tolist(),
                    "radius_mm": float(np.max(np.linalg.norm(points[members] - centre, axis=1)) * 1000),
                }
            )
    return regions


# Beyond these, a change is no manufacturing error: wrong robot model, units or a confounded parameter.
TOLERANCE_LENGTH_M = 5e-3
TOLERANCE_ANGLE_RAD = np.deg2rad(1.0)


def implausible_changes(result: CalibrationResult) -> list[str]:
    """One message per geometric parameter that moved further than a manufacturing tolerance."""
    out = []
    for row in result.parameter_table():
        if row["delta"] is None or row["name"] not in result.model.nominal.param_names:
            continue
        if row["unit"] == "m" and abs(row["delta"]) > TOLERANCE_LENGTH_M:
            size = f"{row['delta'] * 1000:+.1f} mm (tolerance ~{TOLERANCE_LENGTH_M * 1000:g} mm)"
        elif row["unit"] == "rad" and abs(row["delta"]) > TOLERANCE_ANGLE_RAD:
            size = f"{np.rad2deg(row['delta']):+.2f} deg (tolerance ~{np.rad2deg(TOLERANCE_ANGLE_RAD):g} deg)"
        else:
            continue
        out.append(
            f"implausible: {row['name']} moved {size} from the {result.model.robot} nominal; is the robot "
            "model right (data of another robot?), are the joints in radians and the positions in mm?"
        )
    return out


def check_joint_limits(df: pd.DataFrame, nominal: KinematicModel, source: str = "dataset") -> None:
    """Joints beyond the robot's limits (0.05 rad margin): degrees, or data of another robot."""
    q = joints_rad(df, nominal.n_joints)
    lim = np.asarray(nominal.joint_limits, float)
    bad = (q < lim[:, 0] - 0.05) | (q > lim[:, 1] + 0.05)
    if bad.any():
        r, j = np.argwhere(bad)[0]
        raise ValueError(
            f"{source}: joint {j + 1} in data row {data_rows(df)[r]} is {q[r, j]:.3f} rad, beyond the "
            f"{nominal.name} limits [{lim[j, 0]:.3f}, {lim[j, 1]:.3f}]; degrees (name the columns q1_deg..) "
            "or data of another robot?"
        )


def reregister(model: CalibratedModel, df: pd.DataFrame, tool: bool = False) -> CalibratedModel:
    """The model with its base frame (and, if `tool`, its tool points) fitted to another campaign.

    For a campaign from another tracker placement: the robot is the same, the tracker <- base transform
    is not. A rigid fit first (the placements may differ by metres), then a robust refinement.
    """
    ctx, _ = model.context(df)
    p_base = replace(model, T_tracker_base=np.eye(4)).predict_ctx(ctx)
    T, _ = fit_rigid(p_base, points_m(df))
    moved = replace(model, T_tracker_base=T)
    free = np.array([n.startswith("base_") or (tool and n.startswith("tool")) for n in moved.param_names])
    return solve_ridge_igg3(moved, Problem.from_frame(moved, df), free, max_iter=10).model
