"""Fit a model's prediction spread (hil.model.intervals) from held-out rows of its own campaign, and check
its intervals' coverage.

Three kinds of held-out rows measure how a prediction degrades as it leaves what the model was fitted on:
the spatial folds (blocks of the volume: distance to the nearest training pose), the warmest and the coldest
rows (temperature outside the span the rest covers) and the earliest and latest (time outside it). Each is
predicted by the model refitted without it (the diagnosis' linearised refit, `cv_positions`). The spread's
constant and rates are the non-negative least-squares fit of the held-out squared residuals on those
distances; the factor k(P) is the quantile of the held-out rows' |residual| / s. With a 6-DoF probe's
orientations in the fit, the same held-out refits give each row's rotation error, and the orientation's
spread is fitted from those alone, the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy.optimize import nnls

from hil.analysis.calibration.identifiability import scale_columns
from hil.analysis.calibration.solve import (
    CalibrationResult,
    Problem,
    flatten_jacobian,
    position_noise_m,
    prior_terms,
)
from hil.analysis.diagnosis.screening import cv_residuals
from hil.data.dataset import orientations, points_m
from hil.geometry.kinematics import chain_axes
from hil.geometry.se3 import rotation_log
from hil.model.calibrated_model import CalibratedModel
from hil.model.intervals import (
    MAX_STORED_POSES,
    MAX_STORED_SCORES,
    AngleSpread,
    Extrapolation,
    PredictionSpread,
    Span,
    driver_outside,
    nearest_distance,
)
from hil.model.prediction_intervals import (
    parameter_variance_rows,
    prediction_intervals,
    rotation_parameter_variance_rows,
    with_effects_free,
)

# Share of the rows held out at each end of the temperature and of the time span.
EXTREME_SHARE = 0.3


@dataclass(frozen=True)
class HeldOut:
    """Held-out residuals (m) of some rows and how far each lay from the rows it was predicted from."""

    kind: str  # "spatial", "temperature" or "time": what the held-out rows lie outside of
    rows: np.ndarray
    residual_m: np.ndarray  # (n, 3)
    extrapolation: Extrapolation
    rotation_rad: np.ndarray | None = (
        None  # (n, 3) log(R_measured R_predicted^T), with a probe's orientations
    )

    @property
    def per_axis_m2(self) -> np.ndarray:
        return np.sum(self.residual_m**2, axis=1) / 3.0

    @property
    def per_axis_rad2(self) -> np.ndarray:
        assert self.rotation_rad is not None
        return np.sum(self.rotation_rad**2, axis=1) / 3.0


def _span(values: np.ndarray | None) -> Span | None:
    if values is None or len(values) == 0 or not np.all(np.isfinite(values)):
        return None
    return Span(float(np.min(values)), float(np.max(values)))


def joint_levers(model: CalibratedModel, prob: Problem) -> np.ndarray:
    """Each joint's mean lever arm (m) to the SMR over the rows: |z_j x (p - o_j)|."""
    T, Z, O = chain_axes(model.kinematic, prob.ctx.q)
    tools = model._row_tools(prob.smr)
    p = np.einsum("nij,nj->ni", T[:, :3, :3], tools) + T[:, :3, 3]  # (N, 3)
    arms = p.T[None] - O[:-1]  # (n, 3, N)
    return np.linalg.norm(np.cross(Z, arms, axis=1), axis=1).mean(axis=1)


def _extrapolation(prob: Problem, test: np.ndarray, levers_m: np.ndarray) -> Extrapolation:
    train = np.setdiff1d(np.arange(len(prob.measured)), test)
    q, temp, time = prob.ctx.q, prob.ctx.temperature_c, prob.ctx.t_s
    return Extrapolation(
        joint_distance_m=nearest_distance(np.unique(q[train], axis=0), q[test], levers_m),
        temperature_outside_k=driver_outside(
            _span(None if temp is None else temp[train]), None if temp is None else temp[test], len(test)
        ),
        time_outside_s=driver_outside(
            _span(None if time is None else time[train]), None if time is None else time[test], len(test)
        ),
    )


def _ends(values: np.ndarray | None) -> list[np.ndarray]:
    """The rows at each end of a driver's span (EXTREME_SHARE each), when it varies."""
    if values is None or not np.all(np.isfinite(values)) or np.ptp(values) <= 0:
        return []
    lo, hi = np.quantile(values, [EXTREME_SHARE, 1.0 - EXTREME_SHARE])
    return [
        rows
        for rows in (np.flatnonzero(values <= lo), np.flatnonzero(values >= hi))
        if 0 < len(rows) < len(values)
    ]


def held_out(
    model: CalibratedModel,
    free: np.ndarray,
    prob: Problem,
    folds: list[np.ndarray],
    cv_spatial: np.ndarray | None,
    levers_m: np.ndarray,
) -> list[HeldOut]:
    """The held-out rows of every kind: the spatial folds (their position residuals `cv_spatial` when given
    and the fit has no orientations), each end of the temperature span, each end of the time span; distances
    weighted by the joints' `levers_m`; with orientations in the fit, each row's rotation error too."""
    with_rotation = prob.R_measured is not None

    def part(kind: str, rows: np.ndarray, cv: np.ndarray) -> HeldOut:
        rotation = cv[rows, 3:6] / prob.rot_factor[rows] if with_rotation else None
        return HeldOut(kind, rows, cv[rows, :3], _extrapolation(prob, rows, levers_m), rotation)

    cv = (
        cv_spatial if cv_spatial is not None and not with_rotation else cv_residuals(model, free, prob, folds)
    )
    out = [part("spatial", f, cv) for f in folds]
    for kind, values in (("temperature", prob.ctx.temperature_c), ("time", prob.ctx.t_s)):
        for rows in _ends(values):
            out.append(part(kind, rows, cv_residuals(model, free, prob, [rows])))
    return out


def parameter_covariance(
    result: CalibrationResult, free: np.ndarray, prob: Problem
) -> tuple[list[str], np.ndarray]:
    """The fitted parameters' covariance (SI), sigma0^2 (J^T J + P)^-1 on the problem's rows (the final
    model's inliers) with P each physics term's prior weight (as the fit weighs them, hil.analysis.calibration.solve); an effect held
    at an assumed value, or left out of the fit as not identifiable, joins with its prior's variance
    (uncorrelated: no fit moved it); one without a prior left out of the fit counts as exact."""
    model = result.model
    names = model.param_names
    free = free.copy()
    for eff, sl in zip(model.effects, model.effect_slices(), strict=True):
        free[sl] |= eff.held  # a held term's columns: what the data say of it beside its prior
    _, J = prob.evaluate(with_effects_free(model))
    Js, norms = scale_columns(flatten_jacobian(J)[:, free])
    w_prior, _ = prior_terms(model, free, position_noise_m(prob.measured))
    M = Js.T @ Js + np.diag(w_prior / norms**2)
    M += 1e-12 * float(np.linalg.eigvalsh(M)[-1]) * np.eye(len(M))
    cov = result.sigma0_m**2 * np.linalg.inv(M) / np.outer(norms, norms)
    chosen = [n for n, f in zip(names, free, strict=True) if f]
    held_names, held_var = [], []
    for eff, sl in zip(model.effects, model.effect_slices(), strict=True):
        prior = eff.prior()
        if prior is None:
            continue
        for name, std in zip(names[sl], np.asarray(prior[1], float), strict=True):
            if name not in chosen:  # not identifiable on these rows: the prior is all there is
                held_names.append(name)
                held_var.append(float(std) ** 2)
    full = np.zeros((len(chosen) + len(held_names),) * 2)
    full[: len(chosen), : len(chosen)] = cov
    full[len(chosen) :, len(chosen) :] = np.diag(held_var)
    return chosen + held_names, full


@dataclass(frozen=True)
class GrowthLaw:
    """One quantity's spread law (per axis, squared units): s^2 = s0 + joint_rate d + temperature_rate dT +
    time_rate dt + max(0, v_par - v_train), and the held-out rows' sorted scores |error| / s."""

    s0: float
    joint_rate: float
    temperature_rate: float
    time_rate: float
    v_train: float
    scores: np.ndarray
    n_heldout: int

    def variance(self, ex: Extrapolation, v_par: np.ndarray) -> np.ndarray:
        return (
            self.s0
            + self.joint_rate * ex.joint_distance_m
            + self.temperature_rate * ex.temperature_outside_k
            + self.time_rate * ex.time_outside_s
            + np.maximum(v_par - self.v_train, 0.0)
        )


def fit_growth(parts: list[HeldOut], per_axis: str, v_par: np.ndarray, floor: float) -> GrowthLaw:
    """The spread law of one quantity from the held-out rows' per-axis squared errors (`per_axis`: the
    HeldOut property that gives them) and every training row's v_par: s0 and the joint rate a non-negative
    least-squares fit of the spatial folds' errors (s0 at least `floor`, what the instrument measures), then
    the temperature's and the time's rates from what the rows beyond each end show beyond that."""
    v_train = float(np.mean(v_par))

    def gather(kinds: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, Extrapolation]:
        """Rows, their per-axis squared error less the parameters' excess variance, their extrapolation."""
        chosen = [p for p in parts if p.kind in kinds]
        rows = np.concatenate([p.rows for p in chosen])
        r2 = np.concatenate([getattr(p, per_axis) for p in chosen])
        fields = Extrapolation.__dataclass_fields__
        ex = Extrapolation(*(np.concatenate([getattr(p.extrapolation, f) for p in chosen]) for f in fields))
        return rows, r2 - np.maximum(v_par[rows] - v_train, 0.0), ex

    _, r2, ex = gather(("spatial",))
    X = np.column_stack([np.ones_like(r2), ex.joint_distance_m])
    scale = np.maximum(np.abs(X).max(axis=0), 1e-300)
    s0, joint_rate = nnls(X / scale, np.maximum(r2, 0.0))[0] / scale
    law = GrowthLaw(max(float(s0), floor), float(joint_rate), 0.0, 0.0, v_train, np.zeros(1), 1)
    if any(p.kind == "temperature" for p in parts):
        _, r2, ex = gather(("temperature",))
        excess = r2 - law.variance(ex, np.full(len(r2), v_train))
        law = replace(law, temperature_rate=_rate(excess, ex.temperature_outside_k))
    if any(p.kind == "time" for p in parts):  # beyond what the temperature's rate already gives them
        _, r2, ex = gather(("time",))
        excess = r2 - law.variance(ex, np.full(len(r2), v_train))
        law = replace(law, time_rate=_rate(excess, ex.time_outside_s))
    rows, r2, ex = gather(("spatial", "temperature", "time"))
    r2_raw = r2 + np.maximum(v_par[rows] - v_train, 0.0)
    scores = np.sort(np.sqrt(3.0 * np.maximum(r2_raw, 0.0) / law.variance(ex, v_par[rows])))
    if len(scores) > MAX_STORED_SCORES:  # its quantiles, end points kept
        scores = np.quantile(scores, np.linspace(0.0, 1.0, MAX_STORED_SCORES), method="higher")
    return replace(law, scores=scores, n_heldout=len(r2))


def fit_spread(
    result: CalibrationResult,
    free: np.ndarray,
    prob: Problem,
    folds: list[np.ndarray],
    noise_m2: float,
    cv_spatial: np.ndarray | None = None,
) -> PredictionSpread:
    """The spread of the fitted model `result.model` on `prob`'s rows (hil.model.intervals); `noise_m2` (per
    axis, m^2) is the least s0^2 can be: no prediction is closer than the tracker measures. With a 6-DoF
    probe's orientations in `prob`, the orientation's spread too (from its held-out rows alone)."""
    model = result.model
    names, covariance = parameter_covariance(result, free, prob)
    levers_m = joint_levers(model, prob)
    parts = held_out(model, free, prob, folds, cv_spatial, levers_m)
    base = PredictionSpread(
        s0_m2=0.0,
        joint_rate_m=0.0,
        joint_levers_m=levers_m,
        tested_distance_m=1.0,
        temperature_rate_m2_per_k=0.0,
        time_rate_m2_per_s=0.0,
        training_joints_rad=_stored_poses(prob.ctx.q),
        temperature_span_c=_span(prob.ctx.temperature_c),
        time_span_s=_span(prob.ctx.t_s),
        parameter_names=names,
        parameter_covariance=covariance,
        parameter_variance_train_m2=0.0,
        scores=np.zeros(1),
        n_heldout=1,
    )
    law = fit_growth(parts, "per_axis_m2", parameter_variance_rows(model, base, prob.ctx, prob.smr), noise_m2)
    spatial = np.concatenate([p.extrapolation.joint_distance_m for p in parts if p.kind == "spatial"])
    fitted = replace(
        base,
        s0_m2=law.s0,
        joint_rate_m=law.joint_rate,
        tested_distance_m=max(float(np.quantile(spatial, 0.95)), 1e-3),
        temperature_rate_m2_per_k=law.temperature_rate,
        time_rate_m2_per_s=law.time_rate,
        parameter_variance_train_m2=law.v_train,
        scores=law.scores,
        n_heldout=law.n_heldout,
    )
    if prob.R_measured is None:
        return fitted
    v_rot = rotation_parameter_variance_rows(model, base, prob.ctx, prob.smr)
    rot = fit_growth(parts, "per_axis_rad2", v_rot, 0.0)
    angles = AngleSpread(
        s0_rad2=rot.s0,
        joint_rate_rad2_per_m=rot.joint_rate,
        temperature_rate_rad2_per_k=rot.temperature_rate,
        time_rate_rad2_per_s=rot.time_rate,
        parameter_variance_train_rad2=rot.v_train,
        scores=rot.scores,
        n_heldout=rot.n_heldout,
    )
    return replace(fitted, orientation=angles, orientation_reason="")


def _rate(excess_m2: np.ndarray, outside: np.ndarray) -> float:
    """Variance per unit outside the span that the held-out rows beyond an end add to what the spatial model
    predicts for them (their mean excess over their mean distance outside; 0 when they show none)."""
    if len(excess_m2) == 0 or not np.any(outside > 0):
        return 0.0
    return float(max(np.mean(excess_m2), 0.0) / np.mean(outside))


def _stored_poses(q: np.ndarray) -> np.ndarray:
    """The distinct training poses, an evenly spaced subset of at most MAX_STORED_POSES of them."""
    poses = np.unique(q, axis=0)
    if len(poses) <= MAX_STORED_POSES:
        return poses
    return poses[np.linspace(0, len(poses) - 1, MAX_STORED_POSES).round().astype(int)]


@dataclass(frozen=True)
class Coverage:
    """How often a model's intervals held the measured point, on some rows."""

    on: str  # "heldout" (the rows the factor was read from: P by construction) or "validate"
    probability: float
    rows: int
    covered: float  # share of rows whose measured point lies inside the interval
    median_interval_mm: float | None  # (None on the held-out rows: their radii are not kept)
    rms_mm: float | None  # RMS error of the same predictions on the same rows

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class OrientationCoverage:
    """How often a 6-DoF probe's orientation intervals (`interval_deg`) held the measured orientation on rows
    never used for fitting: the angle between the measured and the predicted orientation against the interval."""

    on: str  # "validate"
    probability: float
    rows: int
    covered: float  # share of rows whose measured orientation lies inside the interval
    median_interval_deg: float
    rms_deg: float  # RMS angle between the measured and the predicted orientation on the same rows
    quantity: str = "orientation"

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def validation_orientation_coverage(
    model: CalibratedModel, df: pd.DataFrame, probability: float
) -> OrientationCoverage | None:
    """The orientation intervals on validation rows that carry a 6-DoF probe's orientation; None where the rows
    carry none or the model gives no orientation interval (its notes say why, in `hil predict`)."""
    R_measured = orientations(df)
    if R_measured is None:
        return None
    iv = prediction_intervals(model, df, probability)
    if iv.angle_rad is None:
        return None
    R_predicted = model.predict_rotation(df)
    err_rad = np.linalg.norm(rotation_log(R_measured @ np.swapaxes(R_predicted, 1, 2)), axis=1)
    return OrientationCoverage(
        "validate",
        probability,
        len(err_rad),
        float(np.mean(err_rad <= iv.angle_rad)),
        float(np.rad2deg(np.median(iv.angle_rad))),
        float(np.rad2deg(np.sqrt(np.mean(err_rad**2)))),
    )


def heldout_coverage(spread: PredictionSpread, probability: float) -> Coverage:
    """The intervals on the held-out rows their factor was read from (conformal: >= P by construction; shown
    so the reader sees the factor and the sample it rests on)."""
    k = spread.factor(probability)
    return Coverage("heldout", probability, spread.n_heldout, float(np.mean(spread.scores <= k)), None, None)


def validation_coverage(model: CalibratedModel, df: pd.DataFrame, probability: float) -> Coverage:
    """The intervals on rows never used for fitting: the share whose measured point they hold."""
    iv = prediction_intervals(model, df, probability)
    err = np.linalg.norm(model.predict(df) - points_m(df), axis=1)
    return Coverage(
        "validate",
        probability,
        len(err),
        float(np.mean(err <= iv.radius_m)),
        float(np.median(iv.radius_mm)),
        float(np.sqrt(np.mean(err**2)) * 1000.0),
    )
