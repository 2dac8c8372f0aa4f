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
  An effect with a physical prior (`Effect.prior`: the links' material expansion) adds its Gaussian prior
  to the cost, (sigma (x - mean) / std)^2 with sigma the tracker's a-priori noise per axis at the data's
  distances: the data then outweigh the prior exactly when they measure the coefficient better than std.
- ``lm``: scipy ``least_squares`` (trust-region, Levenberg-Marquardt-like) with a robust loss (soft L1,
  scale 1.5 sigma, sigma from a first least-squares pass by the median absolute deviation: the positions'
  for position coordinates, a probe's rotations' for rotation coordinates, as IGG3 judges them).

Both report parameter standard errors (sigma0^2 times the inverse of the normal matrix) and flag a point
as an outlier when its standardised residual exceeds k1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hil.analysis.calibration.blas_threads import one_blas_thread
from hil.analysis.calibration.folds import campaign_folds, kfold
from hil.analysis.calibration.identifiability import IdentifiabilityReport, analyse, scale_columns
from hil.analysis.calibration.noise_floor import TRACKER_MPE_M, TRACKER_MPE_SIGMAS, tracker_sigma_m
from hil.data.dataset import (
    ORIENTATION_COLUMNS,
    data_rows,
    joints_rad,
    orientations,
    points_m,
    pose_ids,
    repeated_orientation_counts,
    smr_ids,
)
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.se3 import fit_rigid, rotation_log
from hil.model.calibrated_model import CalibratedModel, initial_model, with_initial_probes
from hil.model.effects import EffectContext
from hil.model.grid_frame import location_spacing

K0, K1 = 1.5, 2.5  # IGG3 thresholds of the grid paper
# Beyond this many rows the solvers converge on a fixed random subset of them, then finish on every row
# (IGG3 iterations linearised at the subset's solution until converged, at most FINISH_ITERS, or LM
# from that start).
CONVERGE_ROWS = 4000  # a 12 000-pose campaign: the same model to 0.1 um in half the time
FINISH_ITERS = 30


# Default 1-sigma noise of a 6-DoF probe's orientation reading (T-Mac class: about 0.01 deg per axis).
PROBE_ANGLE_NOISE_RAD = float(np.deg2rad(0.01))


def position_noise_m(
    points: np.ndarray, mpe_m: tuple[float, float] = TRACKER_MPE_M, sigmas: float = TRACKER_MPE_SIGMAS
) -> float:
    """1-sigma tracker noise per axis at the median distance of the points (hil.analysis.calibration.noise_floor's model)."""
    return float(tracker_sigma_m(float(np.median(np.linalg.norm(points, axis=1))), mpe_m, sigmas))


@dataclass
class Problem:
    """A dataset prepared for fitting: context, nest ids, measured points, which pose each row is and,
    from a 6-DoF probe, measured orientations.

    Each row is one observation: its position residual (3, m) and, with orientations, its rotation
    residual log(R_measured R_predicted^T) (the SO(3) log vector in the tracker frame, rad: the same angle as
    log(R_measured^T R_predicted)) times `rot_scale` = position sigma / angle sigma (m/rad), so that the
    unweighted least squares over the (N, 6) residual is the maximum-likelihood fit. A reading copied onto
    n rows of one pose (a single-probe export repeats it on every SMR row) is one measurement: each copy's
    rotation equations get weight 1/sqrt(n) (`rot_weight`), so together they count once.
    """

    ctx: EffectContext
    smr: np.ndarray
    measured: np.ndarray  # (N, 3) m
    pose: np.ndarray | None = None  # (N,) pose id of each row (rows of one pose share a fold)
    R_measured: np.ndarray | None = None  # (N, 3, 3) probe orientation in the tracker frame
    rot_scale: float = 0.0  # m per rad: weight of the rotation residual against the position one
    rot_weight: np.ndarray | None = None  # (N,) 1/sqrt(copies of the row's orientation reading in its pose)

    @classmethod
    def from_frame(
        cls,
        model: CalibratedModel,
        df: pd.DataFrame,
        orientation: bool = False,
        angle_noise_rad: float = PROBE_ANGLE_NOISE_RAD,
        position_noise: float | None = None,
    ) -> Problem:
        """`orientation`: add the probe's rotation equations when the frame has rx/ry/rz_deg, weighted by
        `position_noise` (m, default the tracker's at these distances) over `angle_noise_rad`."""
        ctx, _ = model.context(df)
        measured = points_m(df)
        R = orientations(df) if orientation else None
        scale = 0.0
        pose = pose_ids(df)
        weight = None
        if R is not None:
            weight = 1.0 / np.sqrt(repeated_orientation_counts(df, pose))
            if angle_noise_rad <= 0:
                raise ValueError(f"probe angle noise must be > 0 rad, got {angle_noise_rad}")
            sigma_p = position_noise_m(measured) if position_noise is None else position_noise
            if sigma_p <= 0:
                raise ValueError(f"position noise must be > 0 m, got {sigma_p}")
            scale = sigma_p / angle_noise_rad
        return cls(ctx, smr_ids(df), measured, pose, R, scale, weight)

    @property
    def _copy_weight_rows(self) -> np.ndarray:
        """(N,) weight of each row's rotation equations: 1/sqrt(copies of its reading), 1 by default."""
        return np.ones(len(self.measured)) if self.rot_weight is None else self.rot_weight

    @property
    def rot_factor(self) -> np.ndarray:
        """(N, 1) factor from a rotation log vector (rad) to its weighted residual (m)."""
        return (self.rot_scale * self._copy_weight_rows)[:, None]

    @property
    def copy_weight(self) -> np.ndarray:
        """(N, 3|6) weight of each residual coordinate for copied readings (1, or a rotation's 1/sqrt(n)):
        a residual over it is on the scale of one reading, so robust scales and outlier tests use that."""
        if self.R_measured is None:
            return np.ones((len(self.measured), 3))
        w = self._copy_weight_rows
        return np.concatenate([np.ones((len(w), 3)), np.repeat(w[:, None], 3, axis=1)], axis=1)

    @property
    def n_rotation_readings(self) -> float:
        """Independent orientation readings (copies within a pose counted once), 0 without orientation."""
        if self.R_measured is None:
            return 0.0
        return float(np.sum(self._copy_weight_rows**2))

    @property
    def n_obs(self) -> int:
        """Coordinates per row: 3 (position) or 6 (position and scaled rotation)."""
        return 3 if self.R_measured is None else 6

    def subset(self, rows: np.ndarray) -> Problem:
        return Problem(
            self.ctx.subset(rows),
            self.smr[rows],
            self.measured[rows],
            None if self.pose is None else self.pose[rows],
            None if self.R_measured is None else self.R_measured[rows],
            self.rot_scale,
            None if self.rot_weight is None else self.rot_weight[rows],
        )

    def evaluate(self, model: CalibratedModel) -> tuple[np.ndarray, np.ndarray]:
        """Residuals measured - predicted (N, 3|6) and the Jacobian (N, 3|6, P) at `model`."""
        self.ctx.p_flange_tool = model._row_tools(self.smr)
        p, J = model.jacobian_ctx(self.ctx, self.smr)
        r = self.measured - p
        if self.R_measured is None:
            return r, J
        R_pred, J_rot = model.rotation_jacobian_ctx(self.ctx, self.smr)
        f = self.rot_factor
        return (
            np.concatenate([r, self._weighted_rotation_residual(R_pred)], axis=1),
            np.concatenate([J, f[:, :, None] * J_rot], axis=1),
        )

    def residuals(self, model: CalibratedModel) -> np.ndarray:
        """Residuals measured - predicted (N, 3|6), as `evaluate` without the Jacobian."""
        self.ctx.p_flange_tool = model._row_tools(self.smr)
        r = self.measured - model.predict_ctx(self.ctx)
        if self.R_measured is None:
            return r
        R_pred = model.predict_rotation_ctx(self.ctx, self.smr)
        return np.concatenate([r, self._weighted_rotation_residual(R_pred)], axis=1)

    def _weighted_rotation_residual(self, R_pred: np.ndarray) -> np.ndarray:
        """log(R_measured R_pred^T) (N, 3) rad, scaled and weighted into metres like the position residual."""
        assert self.R_measured is not None
        return self.rot_factor * rotation_log(self.R_measured @ np.swapaxes(R_pred, 1, 2))

    def spatial_folds(self, k: int, seed: int) -> list[np.ndarray]:
        """k folds that are blocks of the measured volume, every row of one pose in the same fold (its
        SMRs share the robot's error: split, a held-out row would be predicted from its own pose); the poses
        of a single-joint sweep are dealt to the folds in turn (hil.analysis.calibration.folds.campaign_folds)."""
        pose = np.arange(len(self.measured)) if self.pose is None else self.pose
        return campaign_folds(self.measured, pose, self.ctx.q, k, seed)

    @property
    def n_poses(self) -> int:
        """Distinct robot poses among the rows (spatial folds are made of whole poses)."""
        return self._compact_poses()[1]

    def _compact_poses(self) -> tuple[np.ndarray, int]:
        """Pose ids renumbered 0..n-1 over this problem's rows (a subset keeps the full set's ids)."""
        if self.pose is None:
            return np.arange(len(self.measured)), len(self.measured)
        ids, pose = np.unique(self.pose, return_inverse=True)
        return pose.ravel(), len(ids)

    def random_folds(self, k: int, seed: int) -> list[np.ndarray]:
        """k random folds of whole poses (interpolation)."""
        pose, n_pose = self._compact_poses()
        if n_pose == len(pose):
            return kfold(len(pose), k, seed)
        return [np.flatnonzero(np.isin(pose, f)) for f in kfold(n_pose, k, seed)]


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
    residual_rot_rad: np.ndarray | None = None  # (N, 3) log(R_measured R_predicted^T), 6-DoF probe rows
    # the pairs of parameters the fit confounds (`confounded_pairs`: names and correlation); each has a note
    # (`confounded_note`)
    confounded: list[tuple[str, str, float]] = field(default_factory=list)

    @property
    def orientation_rms_deg(self) -> float | None:
        """RMS of the inliers' rotation residual angles (deg), None without orientation data."""
        if self.residual_rot_rad is None:
            return None
        ok = ~self.outliers
        return float(np.rad2deg(np.sqrt(np.mean(np.sum(self.residual_rot_rad[ok] ** 2, axis=1)))))

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
            "orientation_rms_deg": self.orientation_rms_deg,
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


# SI unit of a geometric parameter or an effect coefficient -> (the unit the user reads, its factor): mm,
# degrees, ppm. One table for the calibration's parameter table and the diagnosis' effect coefficients.
USER_UNITS = {
    "m": ("mm", 1e3),
    "rad": ("deg", float(np.rad2deg(1.0))),
    "coef": ("coef", 1.0),
    "rad/m": ("deg/m", float(np.rad2deg(1.0))),
    "rad/rad": ("1", 1.0),
    "1/K": ("ppm/K", 1e6),
    "1/s": ("ppm/s", 1e6),
    "m/K": ("mm/K", 1e3),
    "m/s": ("mm/s", 1e3),
}


def in_user_units(value: float | None, unit: str) -> float | None:
    """A parameter value or change from SI (m, rad, ...) into the units the reports use (mm, deg, ppm)."""
    return None if value is None else value * USER_UNITS[unit][1]


def unit_of(name: str) -> str:
    kind = name.rstrip("0123456789")
    if (
        kind in ("theta", "alpha", "beta")
        or name in ("base_rx", "base_ry", "base_rz")
        or name.startswith("probe")
    ):
        return "rad"
    if kind in ("a", "d") or name.startswith(("base_t", "tool")):
        return "m"
    return "coef"


def full_values(model: CalibratedModel) -> np.ndarray:
    """Current values in the full parameter order (base: translation and rotation vector of T; a probe:
    the rotation vector of R_flange_probe)."""
    vals = list(model.kinematic.params)
    vals += list(model.T_tracker_base[:3, 3]) + list(
        Rotation.from_matrix(model.T_tracker_base[:3, :3]).as_rotvec()
    )
    for smr in sorted(model.tools):
        vals += list(model.tools[smr])
    for smr in sorted(model.probes):
        vals += list(Rotation.from_matrix(model.probes[smr]).as_rotvec())
    for eff in model.effects:
        vals += list(eff.params)
    return np.asarray(vals, float)


def flatten_jacobian(J: np.ndarray) -> np.ndarray:
    """(N, d, P) point Jacobian -> (dN, P) rows in the order of the flattened (N, d) residual."""
    return J.reshape(-1, J.shape[-1])


def identify(model: CalibratedModel, problem: Problem, tol: float = 1e-3) -> IdentifiabilityReport:
    """Identifiability analysis of all parameters of `model` on `problem`."""
    _, J = problem.evaluate(model)
    return analyse(flatten_jacobian(J), model.param_names, tol=tol)


def prior_terms(model: CalibratedModel, free: np.ndarray, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per free parameter: the weight (sigma_m / std)^2 of its Gaussian prior (`Effect.prior`; 0 without one)
    and how far its value in `model` lies from the prior's mean, in the parameter's unit."""
    weight, offset = np.zeros(len(model.param_names)), np.zeros(len(model.param_names))
    for eff, sl in zip(model.effects, model.effect_slices(), strict=True):
        prior = eff.prior()
        if prior is not None:
            mean, std = prior
            weight[sl] = (sigma_m / std) ** 2
            offset[sl] = eff.params - mean
    return weight[free], offset[free]


def _redundancy(Js: np.ndarray, Ninv: np.ndarray) -> np.ndarray:
    """Unit-weight redundancy numbers 1 - a_i N^-1 a_i^T of each row (clipped below at 0.05)."""
    h = np.sum((Js @ Ninv) * Js, axis=1)  # one BLAS product: a three-operand einsum loops in C, ~10x slower
    return np.clip(1.0 - h, 0.05, None)


def igg3_weight(t: np.ndarray, k0: float = K0, k1: float = K1) -> np.ndarray:
    """IGG3 weight factor of standardised residuals t."""
    t = np.abs(t)
    w = np.ones_like(t)
    mid = (t > k0) & (t <= k1)
    w[mid] = (k0 / t[mid]) * ((k1 - t[mid]) / (k1 - k0)) ** 2
    w[t > k1] = 0.0
    return w


def _linearised(problem: Problem, model: CalibratedModel, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual vector and Jacobian of the free columns at `model`, flattened: what a solver with a frozen
    Jacobian iterates on (the full Jacobian is dropped at once, it can be large)."""
    r0, J0 = problem.evaluate(model)
    return r0.reshape(-1), flatten_jacobian(J0)[:, free]


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
    fit = _RidgeFit(model, problem, np.asarray(free, bool), ridge, frozen_jacobian)
    start = model
    w_pts = np.ones(fit.n_points)
    dev = np.zeros(int(fit.free.sum()))  # accumulated change of the free parameters since the start
    warm = 0
    it = 0
    sigma_robust: np.ndarray | None = None
    for it in range(1, max_iter + 1):  # noqa: B007
        r, Jf = fit.linearise(model, dev)
        Js, norms = scale_columns(Jf)
        rv = r.reshape(-1)
        w_rows = np.repeat(w_pts, fit.d)
        M, mu = fit.normal_matrix(Js, w_rows, norms)
        prior = fit.prior
        rhs = (
            Js.T @ (w_rows * rv)
            - mu * prior.mask * (dev * norms)
            - prior.weight * (prior.offset + dev) / norms
        )
        step_s = np.linalg.solve(M + 1e-14 * np.trace(M) / len(M) * np.eye(len(M)), rhs)
        cost0 = prior.cost(float(np.sum(w_rows * rv**2)), mu, dev, norms)
        model, r_new, step, step_s, cost = fit.backtrack(model, w_rows, mu, dev, norms, step_s, cost0)
        dev += step
        small = np.max(np.abs(step_s)) < 1e-8 or cost >= cost0 * (1 - 1e-10)  # converged
        if not robust:
            if small:
                break
            continue
        warm += 1
        if warm < 15 and not small and np.all(w_pts == 1):
            continue  # plain Gauss-Newton to convergence before judging points (IGG3 is not convex)
        # Robust scale, fixed once from the least-squares solution (1.4826 x median absolute residual of
        # all coordinates; positions and a probe's rotations each their own): a weighted sigma0 re-estimated
        # each step shrinks as points are rejected and lets the re-weighting reject ever more points.
        if sigma_robust is None:
            cw = problem.copy_weight
            sigma_robust = (
                robust_scales(r_new.reshape(fit.n_points, fit.d) / cw, centred=False) * cw
            ).reshape(-1)
        w_new = fit.igg3_weights(Js, M, r_new, sigma_robust, k0, k1)
        changed = np.max(np.abs(w_new - w_pts)) > 1e-6
        w_pts = w_new
        if small and not changed:
            break
    if frozen_jacobian:
        dx = np.zeros(len(fit.names))
        dx[fit.free] = dev
        model = start.apply_increment(dx)
    return fit.result(model, w_pts, it, "ridge-igg3" if robust else "ridge")


@dataclass(frozen=True)
class _Prior:
    """What `solve_ridge_igg3` adds to the least-squares cost: the ridge on the robot's parameters (`mask`:
    not the set-up's base frame, tool points and probes) and the prior's weights and offsets (`prior_terms`)."""

    mask: np.ndarray  # (p,) bool over the free parameters
    weight: np.ndarray  # (p,)
    offset: np.ndarray  # (p,)

    def matrix(self, Nm: np.ndarray, mu: float, norms: np.ndarray) -> np.ndarray:
        """The penalised normal matrix of the scaled columns."""
        return Nm + mu * np.diag(self.mask.astype(float)) + np.diag(self.weight / norms**2)

    def cost(
        self, data_cost: float, mu: float, dev: np.ndarray, norms: np.ndarray, step: np.ndarray | None = None
    ) -> float:
        """The penalised weighted cost at the parameters moved by `dev` (and `step`, when given) from the
        start; `data_cost` is the weighted sum of squared residuals there."""
        if step is None:
            return float(
                data_cost
                + mu * np.sum(self.mask * (dev * norms) ** 2)
                + np.sum(self.weight * (self.offset + dev) ** 2)
            )
        return float(
            data_cost
            + mu * np.sum(self.mask * ((dev + step) * norms) ** 2)
            + np.sum(self.weight * (self.offset + dev + step) ** 2)
        )


class _RidgeFit:
    """One `solve_ridge_igg3` fit: the problem's residuals and Jacobian of the free columns (at each model,
    or frozen at the start), the ridge and prior penalties, the step's backtracking, the IGG3 weights and
    the final statistics."""

    def __init__(
        self, model: CalibratedModel, problem: Problem, free: np.ndarray, ridge: float, frozen_jacobian: bool
    ) -> None:
        self.problem, self.free, self.ridge = problem, free, ridge
        self.names = model.param_names
        self.frozen = _linearised(problem, model, free) if frozen_jacobian else None
        # The prior holds the robot's geometry and effects, not the set-up (base frame, tool points, probes).
        prior_mask = np.array([not n.startswith(("base_", "tool", "probe")) for n in self.names])[free]
        w_prior, off_prior = prior_terms(model, free, position_noise_m(problem.measured))
        self.prior = _Prior(prior_mask, w_prior, off_prior)
        self.n_points = problem.measured.shape[0]
        self.d = problem.n_obs  # coordinates per point: position, and a probe's scaled rotation

    def linearise(self, model: CalibratedModel, dev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (N, d) and the free columns of the flattened Jacobian at `model` (`dev` from the start)."""
        if self.frozen is not None:
            r0v, J0f = self.frozen
            return (r0v - J0f @ dev).reshape(self.n_points, self.d), J0f
        r, J = self.problem.evaluate(model)
        return r, flatten_jacobian(J)[:, self.free]

    def normal_matrix(
        self, Js: np.ndarray, w_rows: np.ndarray, norms: np.ndarray
    ) -> tuple[np.ndarray, float]:
        """The penalised normal matrix of the scaled columns `Js` under the row weights, and the ridge mu
        (`ridge` times the largest eigenvalue of the unpenalised one)."""
        Nm = (Js * w_rows[:, None]).T @ Js
        mu = self.ridge * np.linalg.eigvalsh(Nm)[-1]
        return self.prior.matrix(Nm, mu, norms), mu

    def backtrack(
        self,
        model: CalibratedModel,
        w_rows: np.ndarray,
        mu: float,
        dev: np.ndarray,
        norms: np.ndarray,
        step_s: np.ndarray,
        cost0: float,
    ) -> tuple[CalibratedModel, np.ndarray, np.ndarray, np.ndarray, float]:
        """The scaled step halved until it does not raise the penalised weighted cost (guards weak
        directions), at most 12 times: the model there, its residual vector, the step (unscaled and
        scaled) and its cost."""
        step = step_s / norms
        for _ in range(12):
            dx = np.zeros(len(self.names))
            dx[self.free] = step
            if self.frozen is not None:
                trial, r_new = model, self.frozen[0] - self.frozen[1] @ (dev + step)
            else:
                trial = model.apply_increment(dx)
                r_new = self.problem.residuals(trial).reshape(-1)
            cost = self.prior.cost(float(np.sum(w_rows * r_new**2)), mu, dev, norms, step)
            if cost <= cost0 * (1 + 1e-12):
                break
            step, step_s = step / 2, step_s / 2
        return trial, r_new, step, step_s, cost

    def igg3_weights(
        self, Js: np.ndarray, M: np.ndarray, r: np.ndarray, sigma_robust: np.ndarray, k0: float, k1: float
    ) -> np.ndarray:
        """Each point's IGG3 weight from its residual standardised by the robust scale and its redundancy."""
        red = _redundancy(Js, np.linalg.pinv(M))
        t_rows = r / (sigma_robust * np.sqrt(red))
        t_pts = np.sqrt(np.mean(t_rows.reshape(self.n_points, self.d) ** 2, axis=1))
        return igg3_weight(t_pts, k0, k1)

    def result(
        self, model: CalibratedModel, w_pts: np.ndarray, iterations: int, solver: str
    ) -> CalibrationResult:
        """The fit at `model`: sigma0 from the weighted residuals, the parameters' standard deviations from
        the penalised normal matrix, the outliers (weight 0)."""
        r, J = self.problem.evaluate(model)
        Jf = flatten_jacobian(J)[:, self.free]
        Js, norms = scale_columns(Jf)
        w_rows = np.repeat(w_pts, self.d)
        M, _ = self.normal_matrix(Js, w_rows, norms)
        dof = max(int(np.count_nonzero(w_rows)) - int(self.free.sum()), 1)
        sigma0 = float(np.sqrt(np.sum(w_rows * r.reshape(-1) ** 2) / dof))
        cov_s = np.linalg.inv(M + 1e-14 * np.eye(len(M)))
        std = sigma0 * np.sqrt(np.diag(cov_s)) / norms
        free_names = [n for n, f in zip(self.names, self.free, strict=True) if f]
        return CalibrationResult(
            model=model,
            solver=solver,
            free=free_names,
            std=dict(zip(free_names, map(float, std), strict=True)),
            sigma0_m=sigma0,
            weights=w_pts,
            outliers=w_pts == 0,
            residual_m=r[:, :3],
            iterations=iterations,
            residual_rot_rad=_rotation_part(self.problem, r),
        )


def robust_scales(r: np.ndarray, centred: bool) -> np.ndarray:
    """Robust sigma (1.4826 x median absolute deviation, about the median if `centred`, else about 0) per
    column of a (N, 3|6) residual, pooled over the position columns and over the rotation columns: a
    probe's rotations and the positions carry different model errors, so each is judged by its own."""
    out = np.empty(r.shape[1])
    for cols in (slice(0, 3), slice(3, r.shape[1])):
        x = r[:, cols].ravel()
        if x.size:
            # the centre as a float of its own: inside the expression, mypy's overload search over numpy's
            # median and abs took 9 s on this one line
            centre = float(np.median(x)) if centred else 0.0
            out[cols] = max(1.4826 * float(np.median(np.abs(x - centre))), 1e-12)
    return out


def _rotation_part(problem: Problem, r: np.ndarray) -> np.ndarray | None:
    """The rotation residual (N, 3) rad out of a (N, 6) residual, None for position-only problems."""
    return r[:, 3:] / problem.rot_factor if problem.R_measured is not None else None


def _scaled_loss(loss: str, scale: np.ndarray) -> str | Callable[[np.ndarray], np.ndarray]:
    """`loss` ("soft_l1" or "linear") with a scale per residual coordinate, as a scipy least_squares
    callable (f_scale 1): rho_i(z) = c_i^2 rho(z / c_i^2), quadratic where |f_i| << c_i."""
    if loss == "linear":
        return "linear"
    if loss != "soft_l1":
        raise ValueError(f"unknown robust loss '{loss}'; choose 'soft_l1' or 'linear'")
    c2 = scale**2

    def soft_l1(z: np.ndarray) -> np.ndarray:
        u = 1.0 + z / c2
        return np.stack([2.0 * c2 * (np.sqrt(u) - 1.0), u**-0.5, -0.5 * u**-1.5 / c2])

    return soft_l1


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
        r0v, J0f = _linearised(problem, model, free)

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
    cw = problem.copy_weight
    sigmas = np.maximum(robust_scales(first.fun.reshape(cw.shape) / cw, centred=True), 1e-9) * cw  # (N, d)
    # Each coordinate leaves the quadratic part of the loss at K0 times its own robust scale (positions,
    # and a probe's rotations, as IGG3 judges them): one scale for all would treat every rotation as an
    # outlier (or none) whenever the angle noise setting is off.
    sol = least_squares(
        fun,
        first.x,
        jac=jac,
        x_scale="jac",
        method="trf",
        loss=_scaled_loss(loss, K0 * sigmas.reshape(-1)),
        max_nfev=60,
        xtol=1e-12,
    )
    fitted = at(sol.x)
    r, J = problem.evaluate(fitted)
    Jf = flatten_jacobian(J)[:, free]
    t_pts = np.sqrt(np.mean((r / sigmas) ** 2, axis=1))
    outliers = t_pts > k1
    w_rows = np.repeat((~outliers).astype(float), problem.n_obs)
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
        residual_m=r[:, :3],
        iterations=int(first.nfev + sol.nfev),
        residual_rot_rad=_rotation_part(problem, r),
    )


def calibrate(
    df: pd.DataFrame,
    robot: str | KinematicModel | CalibratedModel,
    solver: str = "ridge",
    tol: float = 1e-3,
    tool_guess_m: np.ndarray | None = None,
    ridge: float = 1e-7,
    probe_angle_noise_rad: float | None = None,
    position_noise: float | None = None,
) -> CalibrationResult:
    """Full calibration of a dataset: initial registration, identifiability, robust solve.

    `robot` is a catalogue name, a nominal KinematicModel, or a CalibratedModel to start from (its
    effects are refitted together with the geometry). `solver` is "ridge" (IGG3) or "lm".
    Rows with a 6-DoF probe's orientation (rx_deg, ry_deg, rz_deg) add three rotation equations each and
    a probe orientation per nest, weighted by `position_noise` (m, default: the tracker's MPE model at the
    data's distances) over `probe_angle_noise_rad` (default 0.01 deg); None takes them from
    `df.attrs["probe_angle_noise_rad"]` / `df.attrs["position_noise_m"]` when set (how `hil diagnose`
    passes its options through).
    """
    angle = probe_angle_noise_rad
    if angle is None:
        angle = df.attrs.get("probe_angle_noise_rad", PROBE_ANGLE_NOISE_RAD)
    pos = position_noise if position_noise is not None else df.attrs.get("position_noise_m")
    with one_blas_thread():  # small dense problems: BLAS threads only contend
        return _calibrate(df, robot, solver, tol, tool_guess_m, ridge, float(angle), pos)


def _calibrate(
    df: pd.DataFrame,
    robot: str | KinematicModel | CalibratedModel,
    solver: str,
    tol: float,
    tool_guess_m: np.ndarray | None,
    ridge: float,
    angle_noise_rad: float = PROBE_ANGLE_NOISE_RAD,
    position_noise: float | None = None,
) -> CalibrationResult:
    model = robot if isinstance(robot, CalibratedModel) else initial_model(robot, df, tool_guess_m)
    model = with_initial_probes(model, df)
    check_joint_limits(df, model.nominal)
    full = Problem.from_frame(
        model, df, orientation=True, angle_noise_rad=angle_noise_rad, position_noise=position_noise
    )
    check_orientation_readings(model, df, full)
    # A big campaign converges on a fixed random subset first, then finishes on every row (below).
    big = len(df) > CONVERGE_ROWS
    problem = (
        full.subset(np.sort(np.random.default_rng(0).permutation(len(df))[:CONVERGE_ROWS])) if big else full
    )
    # Tool points first (the registration assumed a guess), so the identifiability sees a sane model.
    pre_free = np.array([n.startswith(("base_", "tool", "probe")) for n in model.param_names])
    model = solve_ridge_igg3(model, problem, pre_free, robust=False, max_iter=10).model
    report = identify(model, problem, tol)
    n_free = int(report.keep_mask.sum())
    n_eq = 3 * len(df) + int(round(3 * full.n_rotation_readings))
    need = 2 * n_free + 10
    if n_eq < need:
        n_pose = full.n_poses
        raise ValueError(
            f"{len(df)} rows at {n_pose} distinct poses give {n_eq} equations for {n_free} identifiable "
            f"parameters (at least {need} needed); measure at least {int(np.ceil(need * n_pose / n_eq))} "
            "well-spread poses (a 100-200 mm grid gives hundreds)"
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
    if full.R_measured is not None:
        result.model.info["orientation"] = {
            "rms_deg": result.orientation_rms_deg,
            "angle_noise_deg": float(np.rad2deg(angle_noise_rad)),
            "position_noise_mm": full.rot_scale * angle_noise_rad * 1000,
        }
    result.notes += implausible_changes(result) + orientation_notes(result, angle_noise_rad)
    _honest_numbers(result, problem)
    return result


def confounded_note(a: str, b: str, correlation: float) -> str:
    """The note on parameters `a` and `b` that the fit confounds (their estimates correlate `correlation`)."""
    return (
        f"confounded: {a} and {b} correlate {correlation:+.3f} on these poses; each alone is unreliable (their "
        "combination is); poses that move them differently separate them"
    )


def _honest_numbers(result: CalibrationResult, problem: Problem, k: int = 5) -> None:
    """Spatial-fold spread of the parameters, confounded pairs and outlier regions, into the result."""
    rows = np.flatnonzero(~result.outliers)
    inliers = problem.subset(rows)
    evaluated = inliers.evaluate(result.model)  # one Jacobian for both figures
    if inliers.n_poses >= 2 * k:  # distinct poses: the rows of one pose share a fold
        folds = inliers.spatial_folds(k, 0)
        result.std_folds = fold_spread_std(result, inliers, folds, evaluated)
    result.confounded = confounded_pairs(result, inliers, evaluated=evaluated)
    result.notes += [confounded_note(a, b, c) for a, b, c in result.confounded]
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
            for t in ((r.shape[1] * f[:, None] + np.arange(r.shape[1])).ravel() for f in folds)
        ]
    )
    kf = len(folds)
    spread = np.sqrt((kf - 1) / kf * np.sum((est - est.mean(axis=0)) ** 2, axis=0))
    free_names = [n for n, m in zip(names, free, strict=True) if m]
    return {n: float(v) for n, v in zip(free_names, spread, strict=True)}


def parameter_correlations(result: CalibrationResult, J: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Correlations of the free parameters' estimates from the Jacobian `J` (as Problem.evaluate gives it):
    their names and the matrix.

    A free parameter no equation moves (a 6-DoF probe's orientation in the flange when the rotations are set
    aside) has no estimate here and correlates with nothing: its zero column is left out. Kept in, its
    variance is zero up to rounding (of either sign), and dividing by it gave correlations like 1e141 on
    series A. Every column left is unit-norm and non-zero, so each variance is bounded away from zero
    (about 1 / P^2 at least) and the correlations are well defined."""
    names = result.model.param_names
    Jf = flatten_jacobian(J)
    free = np.array([n in set(result.free) for n in names]) & np.any(Jf != 0.0, axis=0)
    Js, _ = scale_columns(Jf[:, free])
    cov = np.linalg.pinv(Js.T @ Js)
    sd = np.sqrt(np.diag(cov))
    return [n for n, m in zip(names, free, strict=True) if m], cov / np.outer(sd, sd)


def confounded_pairs(
    result: CalibrationResult, problem: Problem, limit: float = 0.95, evaluated: tuple | None = None
) -> list[tuple]:
    """Pairs of free geometric parameters whose estimates correlate beyond `limit` (|corr|)."""
    fn, corr = parameter_correlations(result, (evaluated or problem.evaluate(result.model))[1])
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


def implausible_changes(result: CalibrationResult | CalibratedModel) -> list[str]:
    """One message per geometric parameter that moved further than a manufacturing tolerance (a length
    beyond TOLERANCE_LENGTH_M or an angle beyond TOLERANCE_ANGLE_RAD): the commands refuse such a model.
    Takes a calibration result or a model (a diagnosis's final model)."""
    model = result.model if isinstance(result, CalibrationResult) else result
    names, values = model.param_names, full_values(model)
    out = []
    for name, nominal in zip(model.nominal.param_names, model.nominal.params, strict=True):
        delta = float(values[names.index(name)]) - float(nominal)
        unit = unit_of(name)
        if unit == "m" and abs(delta) > TOLERANCE_LENGTH_M:
            size = f"{delta * 1000:+.1f} mm (tolerance ~{TOLERANCE_LENGTH_M * 1000:g} mm)"
        elif unit == "rad" and abs(delta) > TOLERANCE_ANGLE_RAD:
            size = f"{np.rad2deg(delta):+.2f} deg (tolerance ~{np.rad2deg(TOLERANCE_ANGLE_RAD):g} deg)"
        else:
            continue
        out.append(
            f"implausible: {name} moved {size} from the {model.robot} nominal; is the robot "
            "model right (data of another robot?), are the joints in radians and the positions in mm?"
        )
    return out


# A probe reading right, in the right convention and units, agrees with the nominal arm, registered on the
# positions, within about a degree (median 0.5 deg on a simulated UR10); the wrong Euler convention gives
# tens of degrees, radians in the _deg columns some 45.
ORIENTATION_PLAUSIBLE_DEG = 5.0
# After the fit, an orientation RMS beyond this many times the probe's stated noise gets a note.
ORIENTATION_NOISE_FACTOR = 3.0


def check_orientation_readings(model: CalibratedModel, df: pd.DataFrame, problem: Problem) -> None:
    """Refuse orientation readings that the nominal model misses by more than ORIENTATION_PLAUSIBLE_DEG in the
    median row: a wrong convention or unit would otherwise drag the position calibration off by millimetres.
    The nominal model is first registered on the positions with its tool points fitted too (a probe 110 mm
    off the flange, with the tool guessed at the flange, left the base 75 mm off and good readings 5 deg off)."""
    if problem.R_measured is None:
        return
    registered = _registered_on_positions(model, df)
    check = replace(problem, ctx=registered.context(df)[0])
    rot = _rotation_part(check, check.residuals(registered))
    assert rot is not None
    median = float(np.rad2deg(np.median(np.linalg.norm(rot, axis=1))))
    if median > ORIENTATION_PLAUSIBLE_DEG:
        raise ValueError(
            f"the probe orientation columns {', '.join(ORIENTATION_COLUMNS)} disagree with the nominal "
            f"{model.nominal.name} by {median:.1f} deg in the median row (readings that fit agree within "
            f"about {ORIENTATION_PLAUSIBLE_DEG:g} deg): are they in the convention given with "
            "--orientation-convention (xyz-extrinsic or xyz-intrinsic) and in degrees, not radians? "
            "Drop the three columns to calibrate on positions only"
        )


REGISTRATION_ROUNDS = 5  # base and tool points fitted in turn; each round a rigid fit and a linear one


def _registered_on_positions(model: CalibratedModel, df: pd.DataFrame) -> CalibratedModel:
    """The model's geometry with its base frame and each nest's tool point fitted to the measured positions
    (in turn: the base by a rigid fit, then each tool point by linear least squares, REGISTRATION_ROUNDS
    times) and its probes estimated afresh on that placement."""
    measured, smr = points_m(df), smr_ids(df)
    ctx, _ = model.context(df)
    T_BF = forward_kinematics(model.kinematic, ctx.q + model.joint_offsets(ctx))
    tools = dict(model.tools)
    T = model.T_tracker_base
    for _ in range(REGISTRATION_ROUNDS):
        p_base = (
            np.einsum("nij,nj->ni", T_BF[:, :3, :3], np.array([tools[int(s)] for s in smr])) + T_BF[:, :3, 3]
        )
        T, _ = fit_rigid(p_base, measured)
        in_base = (measured - T[:3, 3]) @ T[:3, :3]  # the measured points in the base frame
        for s in np.unique(smr):
            rows = smr == s
            A = T_BF[rows, :3, :3].reshape(-1, 3)
            b = (in_base[rows] - T_BF[rows, :3, 3]).reshape(-1)
            tools[int(s)] = np.linalg.lstsq(A, b, rcond=None)[0]
    return with_initial_probes(replace(model, T_tracker_base=T, tools=tools, probes={}), df)


def orientation_notes(result: CalibrationResult, angle_noise_rad: float) -> list[str]:
    """A note when the fitted orientation residual is far above the probe's stated noise."""
    rms = result.orientation_rms_deg
    expected = float(np.rad2deg(np.sqrt(3) * angle_noise_rad))  # 3-D RMS of the per-axis noise
    if rms is None or rms <= ORIENTATION_NOISE_FACTOR * expected:
        return []
    return [
        f"orientation: the probe's rotation residual RMS is {rms:.3g} deg, {rms / expected:.0f}x what its "
        f"stated noise ({np.rad2deg(angle_noise_rad):.3g} deg per axis) gives: the rotation equations weigh "
        "too much; check the angle noise (--probe-angle-noise-deg), the probe's mounting, and the "
        "orientation convention"
    ]


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
