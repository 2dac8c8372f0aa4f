"""A calibrated model's prediction intervals for the rows of a dataset (the method: hil.model.intervals)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from hil.data.dataset import has_orientation, smr_ids
from hil.model.calibrated_model import FORMAT, CalibratedModel
from hil.model.effects import EffectContext
from hil.model.intervals import (
    ORIENTATION_UNKNOWN,
    Extrapolation,
    IntervalError,
    Intervals,
    PredictionSpread,
    extrapolation_of,
    parameter_variance,
    spread_variance,
)


def spread_of(model: CalibratedModel) -> PredictionSpread:
    """The model's spread, or a refusal that says why there is none and what to do."""
    if model.spread is None:
        if model.format_version < 2:
            raise IntervalError(
                f"the model file is of format {model.file_format!r}, which carries no prediction spread, so "
                "it gives no interval (without --interval it still predicts); run 'hil diagnose' again to "
                f"write a model of format {FORMAT!r} that carries what --interval needs"
            )
        raise IntervalError(
            "the model carries no prediction spread (it was not diagnosed with held-out data), so it gives "
            "no interval; run 'hil diagnose' to write a model that carries what --interval needs"
        )
    return model.spread


def with_effects_free(model: CalibratedModel) -> CalibratedModel:
    """The model with no effect held: its Jacobian then has every effect's columns (a held coefficient is
    uncertain too)."""
    return replace(
        model,
        effects=[
            type(e)(joint=e.joint, params=e.params, state={k: v for k, v in e.state.items() if k != "held"})
            for e in model.effects
        ],
    )


def parameter_variance_rows(
    model: CalibratedModel, spread: PredictionSpread, ctx: EffectContext, smr: np.ndarray
) -> np.ndarray:
    """v_par of every row (m^2 per axis), from the point's derivative by the spread's parameters; an effect
    held at an assumed value takes part (its coefficient is uncertain too, by its prior's width)."""
    unheld = with_effects_free(model)
    _, J = unheld.jacobian_ctx(ctx, smr)
    names = unheld.param_names
    cols = [names.index(n) for n in spread.parameter_names]
    return parameter_variance(J[:, :3, cols], spread.parameter_covariance)


def rotation_parameter_variance_rows(
    model: CalibratedModel, spread: PredictionSpread, ctx: EffectContext, smr: np.ndarray
) -> np.ndarray:
    """v_par of every row's orientation (rad^2 per axis), as `parameter_variance_rows` through the
    orientation's derivative by the parameters."""
    unheld = with_effects_free(model)
    _, J = unheld.rotation_jacobian_ctx(ctx, smr)
    names = unheld.param_names
    cols = [names.index(n) for n in spread.parameter_names]
    return parameter_variance(J[:, :, cols], spread.parameter_covariance)


def orientation_intervals(
    model: CalibratedModel,
    spread: PredictionSpread,
    df: pd.DataFrame,
    ex: Extrapolation,
    probability: float,
) -> tuple[np.ndarray | None, list[str]]:
    """The angle (rad) about each row's predicted orientation that holds its measured one with
    `probability`, for rows with a 6-DoF probe's orientation (None without), and notes on why none is given.
    A model file from before the orientation's spread is refused: its positions' spread says nothing of
    angles."""
    if not has_orientation(df):
        return None, []
    if spread.orientation is None:
        if spread.orientation_reason == ORIENTATION_UNKNOWN and model.probes:
            raise IntervalError(
                "the rows carry a 6-DoF probe's orientation (rx_deg, ry_deg, rz_deg), and the model file was "
                "written before hil gave orientation intervals, so it carries no orientation spread; run "
                "'hil diagnose' again to write a model that does (or drop those columns for interval_mm alone)"
            )
        why = (
            "the model does not know the probe's mounting" if not model.probes else spread.orientation_reason
        )
        return None, [f"no interval_deg for the rows' orientations: {why}"]
    angles = spread.orientation
    ctx, _ = model.context(df)
    v_par = rotation_parameter_variance_rows(model, spread, ctx, smr_ids(df))
    return angles.factor(probability) * np.sqrt(angles.variance(ex, v_par)), []


def prediction_intervals(model: CalibratedModel, df: pd.DataFrame, probability: float = 0.95) -> Intervals:
    """The radius (m) about each row's predicted point that holds its measured point with `probability`;
    with a 6-DoF probe's orientation in the rows, also the angle (rad) about the predicted orientation."""
    spread = spread_of(model)
    k = spread.factor(probability)
    ctx, _ = model.context(df)
    ex, notes = extrapolation_of(spread, df, ctx.q)
    angle, angle_notes = orientation_intervals(model, spread, df, ex, probability)
    notes += angle_notes
    v_par = parameter_variance_rows(model, spread, ctx, smr_ids(df))
    radius = k * np.sqrt(spread_variance(spread, ex, v_par))
    beyond = int(np.sum(ex.joint_distance_m > spread.tested_distance_m))
    if beyond:
        notes.append(
            f"{beyond} of {len(radius)} rows lie farther from the training poses than its held-out blocks did "
            f"({spread.tested_distance_m * 1000:.0f} mm lever-weighted): their intervals extend the growth the "
            "campaign measured nearer; measure a few of them to check"
        )
    if spread.assumed_effects:
        notes.append(
            "assumed, not found, by the data: "
            + ", ".join(spread.assumed_effects)
            + " (their prior's width is in the intervals)"
        )
    return Intervals(probability=probability, radius_m=radius, extrapolation=ex, notes=notes, angle_rad=angle)
