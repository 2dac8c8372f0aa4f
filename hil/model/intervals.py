"""Prediction intervals: how far the measured SMR may lie from a model's predicted point.

The interval of a row is the radius of a sphere about the predicted point that holds the measured point
with probability P. It is `k(P) * s(x)`: a per-axis spread s(x) that grows where the model extrapolates,
times a factor k(P) read off the held-out rows of the model's own campaign (split-conformal: the P-quantile
of |held-out residual| / s over those rows, so no distribution is assumed).

The spread (per axis, squared, m^2) is

    s^2(x) = s0^2 + a_joint d + a_temp dT + a_time dt + max(0, v_par(x) - v_par_train)

- d: the distance from x to the nearest training pose in joint space, each joint's angle weighted by its
  lever arm to the SMR (m); dT, dt: how far x lies outside
  the temperatures and times the campaign spans (0 inside, and 0 for a row without that column: treated as
  anywhere in the span). s0 and the joint rate are a non-negative least-squares fit of the spatial folds'
  held-out squared residuals (blocks of the volume); the temperature and time rates are what the warmest
  and coldest (earliest and latest) 30 % of the rows, held out, show beyond that, per unit outside the
  span: the campaign's own measure of how a prediction degrades with distance
  (hil.analysis.diagnosis.intervals). Every growth is linear in the variance (a linear variogram, as of a
  random walk): a rate read over the short distances a campaign's held-out rows lie from the rest is
  extrapolated to a far pose or a warmer day, and a quadratic law would turn its noise into intervals many
  times the error. A row farther from the training poses than the held-out blocks were (`tested_distance_m`,
  their 95th percentile) is named in the notes: its interval rests on that extension.
- v_par(x): the variance the fitted parameters' covariance puts on the point, trace(J C J^T) / 3 (the
  linearised least-squares covariance with each physics term's prior; a term held at an assumed value counts
  with its prior's width). It grows where the geometry or an effect is extrapolated: far from the measured
  poses, outside the temperatures a thermal term was fitted on, and fastest for a term the physics assumes
  rather than the data found. Its mean over the training rows is already in s0 (the held-out residuals
  carry it), so only the excess is added.

With a 6-DoF probe the orientation gets its own interval, the same way (`AngleSpread`): the angle about the
predicted orientation that holds the measured one with probability P is `k_rot(P) * s_rot(x)`, with s_rot^2
(per axis, rad^2) the same law over the same distances, its constant and rates read off the held-out rows'
rotation errors |log(R_measured R_predicted^T)|, its v_par from the parameters' covariance through the
orientation's derivative, its factor the quantile of those rows' scores. A position's spread says nothing of
an angle's (a wrist joint's error turns the probe and hardly moves the SMR), so neither borrows from the other.

All of it travels in the model file (`PredictionSpread`, model format 2); a model without it has no interval.
A format-2 file written before the orientation's spread existed has no `orientation_reason`: it is refused an
interval for orientation rows (`ORIENTATION_UNKNOWN`), never given one from the positions' spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

# At most this many training poses travel in the model file for the distance to the nearest one (an
# evenly spaced subset of a larger campaign; the distance is then a little longer than to the full set,
# which errs on the wide side).
MAX_STORED_POSES = 4000
# At most this many normalised held-out scores travel in the file (quantiles of the full set beyond).
MAX_STORED_SCORES = 2001


# The orientation reason of a model file written before the orientation's spread existed.
ORIENTATION_UNKNOWN = "unknown"


class IntervalError(ValueError):
    """An interval the model cannot give (no spread in its file, P outside what its held-out rows support)."""


def conformal_factor(scores: np.ndarray, n_heldout: int, probability: float) -> float:
    """k(P): the split-conformal quantile of sorted held-out scores, with the finite-sample correction
    ceil((n + 1) P) / n; a P the held-out rows cannot support is refused, not guessed."""
    if not 0.0 < probability < 1.0:
        raise IntervalError(f"interval probability {probability}: give a value between 0 and 1")
    n = n_heldout
    level = math.ceil((n + 1) * probability) / n
    if level > 1.0:
        raise IntervalError(
            f"interval probability {probability}: {n} held-out rows support at most "
            f"{n / (n + 1):.3f}; measure more poses or ask for a lower probability"
        )
    return float(np.quantile(scores, level, method="higher"))


@dataclass(frozen=True)
class Span:
    """A driver's range over the training rows (temperature in degC, time in s)."""

    low: float
    high: float

    def outside(self, values: np.ndarray) -> np.ndarray:
        """How far each value lies outside the span (0 inside)."""
        return np.maximum(self.low - values, 0.0) + np.maximum(values - self.high, 0.0)


@dataclass(frozen=True)
class AngleSpread:
    """The orientation's spread (rad^2 per axis, rates per the same distances as the position's) and its
    held-out scores |rotation error| / s_rot."""

    s0_rad2: float
    joint_rate_rad2_per_m: float
    temperature_rate_rad2_per_k: float
    time_rate_rad2_per_s: float
    parameter_variance_train_rad2: float  # mean v_par of the orientation over the training rows
    scores: np.ndarray  # sorted, at most MAX_STORED_SCORES
    n_heldout: int

    def factor(self, probability: float) -> float:
        """k_rot(P), as `PredictionSpread.factor`."""
        return conformal_factor(self.scores, self.n_heldout, probability)

    def variance(self, ex: Extrapolation, parameter_variance_rad2: np.ndarray | float) -> np.ndarray:
        """s_rot^2(x) per row (rad^2, per axis)."""
        return (
            self.s0_rad2
            + self.joint_rate_rad2_per_m * ex.joint_distance_m
            + self.temperature_rate_rad2_per_k * ex.temperature_outside_k
            + self.time_rate_rad2_per_s * ex.time_outside_s
            + np.maximum(parameter_variance_rad2 - self.parameter_variance_train_rad2, 0.0)
        )

    def to_dict(self) -> dict:
        return {
            "s0_rad2": self.s0_rad2,
            "joint_rate_rad2_per_m": self.joint_rate_rad2_per_m,
            "temperature_rate_rad2_per_k": self.temperature_rate_rad2_per_k,
            "time_rate_rad2_per_s": self.time_rate_rad2_per_s,
            "parameter_variance_train_rad2": self.parameter_variance_train_rad2,
            "scores": np.asarray(self.scores).tolist(),
            "n_heldout": self.n_heldout,
        }

    @classmethod
    def from_dict(cls, d: dict) -> AngleSpread:
        return cls(
            s0_rad2=float(d["s0_rad2"]),
            joint_rate_rad2_per_m=float(d["joint_rate_rad2_per_m"]),
            temperature_rate_rad2_per_k=float(d["temperature_rate_rad2_per_k"]),
            time_rate_rad2_per_s=float(d["time_rate_rad2_per_s"]),
            parameter_variance_train_rad2=float(d["parameter_variance_train_rad2"]),
            scores=np.asarray(d["scores"], float),
            n_heldout=int(d["n_heldout"]),
        )


@dataclass(frozen=True)
class PredictionSpread:
    """What a model needs to give intervals: the fitted spread model and the held-out scores."""

    s0_m2: float  # per-axis variance inside the campaign, m^2
    joint_rate_m: float  # variance (m^2) per lever-weighted joint distance (m)
    tested_distance_m: float  # the farthest the held-out blocks lay from their training poses (95th pct)
    joint_levers_m: np.ndarray  # (n,) each joint's mean lever arm to the SMR over the training poses
    temperature_rate_m2_per_k: float
    time_rate_m2_per_s: float
    training_joints_rad: np.ndarray  # (M, n) poses for the nearest-pose distance
    temperature_span_c: Span | None
    time_span_s: Span | None
    parameter_names: list[str]  # the parameters the covariance is of (the model's names)
    parameter_covariance: np.ndarray  # (k, k), SI units
    parameter_variance_train_m2: float  # mean v_par over the training rows
    scores: np.ndarray  # sorted |held-out residual| / s over the held-out rows (at most MAX_STORED_SCORES)
    n_heldout: int  # how many held-out rows the scores came from
    assumed_effects: list[str] = field(default_factory=list)  # effects carried by their prior, not found
    orientation: AngleSpread | None = None  # a 6-DoF probe's orientation spread
    # why there is no orientation spread ("" when there is one; ORIENTATION_UNKNOWN: a file from before it)
    orientation_reason: str = "the model was diagnosed without a 6-DoF probe's orientations"

    def factor(self, probability: float) -> float:
        """k(P): the split-conformal quantile of the held-out scores (`conformal_factor`)."""
        return conformal_factor(self.scores, self.n_heldout, probability)

    def to_dict(self) -> dict:
        def span(s: Span | None) -> list[float] | None:
            return None if s is None else [s.low, s.high]

        return {
            "s0_m2": self.s0_m2,
            "joint_rate_m": self.joint_rate_m,
            "tested_distance_m": self.tested_distance_m,
            "joint_levers_m": np.asarray(self.joint_levers_m).tolist(),
            "temperature_rate_m2_per_k": self.temperature_rate_m2_per_k,
            "time_rate_m2_per_s": self.time_rate_m2_per_s,
            "training_joints_rad": np.asarray(self.training_joints_rad).tolist(),
            "temperature_span_c": span(self.temperature_span_c),
            "time_span_s": span(self.time_span_s),
            "parameter_names": self.parameter_names,
            "parameter_covariance": np.asarray(self.parameter_covariance).tolist(),
            "parameter_variance_train_m2": self.parameter_variance_train_m2,
            "scores": np.asarray(self.scores).tolist(),
            "n_heldout": self.n_heldout,
            "assumed_effects": self.assumed_effects,
            "orientation": None if self.orientation is None else self.orientation.to_dict(),
            "orientation_reason": self.orientation_reason,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PredictionSpread:
        def span(v: list[float] | None) -> Span | None:
            return None if v is None else Span(float(v[0]), float(v[1]))

        return cls(
            s0_m2=float(d["s0_m2"]),
            joint_rate_m=float(d["joint_rate_m"]),
            tested_distance_m=float(d["tested_distance_m"]),
            joint_levers_m=np.asarray(d["joint_levers_m"], float),
            temperature_rate_m2_per_k=float(d["temperature_rate_m2_per_k"]),
            time_rate_m2_per_s=float(d["time_rate_m2_per_s"]),
            training_joints_rad=np.asarray(d["training_joints_rad"], float),
            temperature_span_c=span(d["temperature_span_c"]),
            time_span_s=span(d["time_span_s"]),
            parameter_names=[str(v) for v in d["parameter_names"]],
            parameter_covariance=np.asarray(d["parameter_covariance"], float),
            parameter_variance_train_m2=float(d["parameter_variance_train_m2"]),
            scores=np.asarray(d["scores"], float),
            n_heldout=int(d["n_heldout"]),
            assumed_effects=[str(v) for v in d.get("assumed_effects", [])],
            orientation=None if d.get("orientation") is None else AngleSpread.from_dict(d["orientation"]),
            orientation_reason=str(d.get("orientation_reason", ORIENTATION_UNKNOWN)),
        )


@dataclass(frozen=True)
class Extrapolation:
    """Per row, how far it lies from what the model was trained on."""

    joint_distance_m: np.ndarray  # (N,) lever-weighted joint distance to the nearest training pose
    temperature_outside_k: np.ndarray  # (N,) outside the training's temperatures (0 inside or unknown)
    time_outside_s: np.ndarray  # (N,) outside the training's times (0 inside or unknown)


def driver_outside(span: Span | None, values: np.ndarray | None, n: int) -> np.ndarray:
    """How far each row's driver lies outside the span; 0 where either is unknown."""
    if span is None or values is None:
        return np.zeros(n)
    out = span.outside(np.asarray(values, float))
    return np.where(np.isfinite(out), out, 0.0)


def nearest_distance(reference: np.ndarray, q: np.ndarray, levers_m: np.ndarray) -> np.ndarray:
    """Lever-weighted joint distance (m) from each row of q to its nearest reference pose:
    sqrt(sum_j (L_j dq_j)^2), each joint's angle difference times its lever arm to the SMR, so a turn of the
    wrist counts for the little it moves the point and a turn of the base for the much it does."""
    return cKDTree(reference * levers_m).query(q * levers_m, k=1)[0]


def spread_variance(
    spread: PredictionSpread, ex: Extrapolation, parameter_variance_m2: np.ndarray | float
) -> np.ndarray:
    """s^2(x) per row (m^2, per axis)."""
    return (
        spread.s0_m2
        + spread.joint_rate_m * ex.joint_distance_m
        + spread.temperature_rate_m2_per_k * ex.temperature_outside_k
        + spread.time_rate_m2_per_s * ex.time_outside_s
        + np.maximum(parameter_variance_m2 - spread.parameter_variance_train_m2, 0.0)
    )


def parameter_variance(J: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """v_par per row (m^2, per axis): trace(J C J^T) / 3 for J (N, 3, k) the point's derivative by the
    parameters and C (k, k) their covariance."""
    return np.einsum("nai,ij,naj->n", J, covariance, J) / 3.0


@dataclass(frozen=True)
class Intervals:
    """A prediction's intervals, row for row, and what the caller should be told about them."""

    probability: float
    radius_m: np.ndarray  # (N,)
    extrapolation: Extrapolation
    notes: list[str]
    angle_rad: np.ndarray | None = None  # (N,) about the predicted orientation, for a 6-DoF probe's rows

    @property
    def radius_mm(self) -> np.ndarray:
        return self.radius_m * 1000.0

    @property
    def angle_deg(self) -> np.ndarray | None:
        return None if self.angle_rad is None else np.rad2deg(self.angle_rad)


def frame_drivers(df: pd.DataFrame) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The temperature and time columns of a frame (None where absent)."""
    temp = df["temperature_c"].to_numpy(float) if "temperature_c" in df.columns else None
    time = df["t_s"].to_numpy(float) if "t_s" in df.columns else None
    return temp, time


def extrapolation_of(
    spread: PredictionSpread, df: pd.DataFrame, q: np.ndarray
) -> tuple[Extrapolation, list[str]]:
    """How far each row lies outside the training; notes for drivers the rows lack (treated as in span)."""
    temp, time = frame_drivers(df)
    notes = []
    for span, values, column, what in (
        (spread.temperature_span_c, temp, "temperature_c", "temperatures"),
        (spread.time_span_s, time, "t_s", "times"),
    ):
        if span is not None and (values is None or not np.all(np.isfinite(values))):
            notes.append(
                f"rows without {column}: their intervals treat them as anywhere within the {what} the model "
                f"was trained on ({span.low:.6g}..{span.high:.6g}); outside it they would be wider"
            )
    ex = Extrapolation(
        joint_distance_m=nearest_distance(spread.training_joints_rad, q, spread.joint_levers_m),
        temperature_outside_k=driver_outside(spread.temperature_span_c, temp, len(q)),
        time_outside_s=driver_outside(spread.time_span_s, time, len(q)),
    )
    return ex, notes
