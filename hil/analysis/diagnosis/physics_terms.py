"""The physics terms of a diagnosed model: where the geometric fit starts (the links' thermal growth when the
robot file names their material, the joints' gravity yield when it names the link masses) and what the fit
made of them against their priors (fitted beside prior, standard error, the data's share of what is known).
The selection never adds or removes these terms; hil.analysis.diagnosis.pipeline reports them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
from scipy import stats

from hil.analysis.calibration.solve import CalibrationResult, Problem, position_noise_m
from hil.geometry.kinematics import KinematicModel
from hil.model.calibrated_model import CalibratedModel, initial_model
from hil.model.effects import (
    GravityCompliance,
    gravity_physics,
    gravity_physics_term,
    hold_rigid,
    material_expansion,
    material_growth,
)


def held_rigid_start(
    start: str | KinematicModel | CalibratedModel, joints: dict
) -> str | KinematicModel | CalibratedModel:
    """`start` with the gravity physics terms of `joints` ({joint: negative compliance}) held rigid."""
    if not joints or not isinstance(start, CalibratedModel):
        return start
    effects = [
        hold_rigid(e, joints[e.joint]) if gravity_physics_term(e) and e.joint in joints else e
        for e in start.effects
    ]
    return replace(start, effects=effects)


def physics_start(
    robot: str | KinematicModel, df: pd.DataFrame, tool_guess_m: np.ndarray | None
) -> str | KinematicModel | CalibratedModel:
    """Where the geometric fit starts: the registered nominal model with the physics the robot file allows
    (the links' thermal growth when it names their material and every row records a temperature, the joints'
    gravity yield when it names the link masses), else `robot` itself."""
    model = initial_model(robot, df, tool_guess_m)
    ctx = model.context(df)[0]
    growth = material_expansion(ctx, model.nominal)
    effects = ([] if growth is None else [growth]) + list(gravity_physics(ctx, model.nominal))
    for eff in effects:
        model = model.with_effect(eff)
    return model if effects else robot


# A physics term (the material's growth, a joint's gravity yield) counts as measured when the data carry at
# least this share of the information on its coefficient (1 - posterior variance / prior variance), else the prior holds it.
DATA_LED_SHARE = 0.5


def thermal_summary(result: CalibrationResult, prob: Problem) -> dict | None:
    """The material's thermal growth in the fitted model: the coefficient fitted beside the material's, its
    standard error, the temperature the rows span and the data's share of what is known of it (0: the prior
    alone, the campaign spanned too little temperature; 1: the data alone). None without such a term."""
    eff = next((e for e in result.model.effects if material_growth(e)), None)
    if eff is None:
        return None
    prior_std = float(eff.state["prior_std_per_k"])
    std, share = data_share(result, prob, eff.param_names[0], prior_std)
    temps = prob.ctx.temperature_c
    held = {"held_conflicting_per_k": eff.state["conflicting_per_k"]} if eff.held else {}
    return {
        **held,
        "material_per_k": float(eff.state["material_per_k"]),
        "fitted_per_k": float(eff.params[0]),
        "std_per_k": std,
        "prior_std_per_k": prior_std,
        "span_k": float(np.ptp(temps)) if temps is not None and len(temps) else 0.0,
        "reference_c": float(eff.state["reference"]),
        "data_share": share,
        "data_led": share >= DATA_LED_SHARE,
    }


def data_share(result: CalibrationResult, prob: Problem, name: str, prior_std: float) -> tuple[float, float]:
    """(standard error, data's share of what is known) of a coefficient fitted with a Gaussian prior of
    `prior_std`: 1 - posterior variance / prior variance (0: the prior alone, 1: the data alone)."""
    std = result.std.get(name)
    if std is None or result.sigma0_m <= 0:
        return prior_std, 0.0
    std_apriori = std * position_noise_m(prob.measured) / result.sigma0_m  # std is scaled by sigma0
    return float(std), float(np.clip(1.0 - (std_apriori / prior_std) ** 2, 0.0, 1.0))


def gravity_summary(result: CalibrationResult, prob: Problem, alpha: float) -> list[dict]:
    """Each joint's yield under the link masses' gravity in the fitted model (one per physics term): the
    compliance and its standard error, the stiffness it means (kN m/rad), the torque the rows span, the data's
    share of what is known of it (as `thermal_summary`) and whether the data found the yield: data-led and a
    compliance above zero by more than the two-sided `alpha` quantile of its standard error. A term held rigid
    (the data made it negative: `hold_rigid`) says what the data had made of it."""
    out = []
    z = float(stats.norm.isf(alpha / 2))
    for eff in result.model.effects:
        if not isinstance(eff, GravityCompliance) or not gravity_physics_term(eff):
            continue
        prior_std = float(eff.state["prior_std"])
        std, share = data_share(result, prob, eff.param_names[0], prior_std)
        c = float(eff.params[0])
        torque = eff.torque(prob.ctx, result.model.nominal)
        stiffness = 1e-3 / c if c > 0 else None
        # d(1/c) = dc / c^2: the stiffness' standard error where the compliance is well above its own
        stiffness_std = 1e-3 * std / c**2 if c > 0 else None
        out.append(
            {
                "joint": eff.joint,
                "compliance_rad_per_nm": c,
                "std_rad_per_nm": std,
                "prior_std_rad_per_nm": prior_std,
                "stiffness_knm_per_rad": stiffness,
                "stiffness_std_knm_per_rad": stiffness_std,
                "torque_min_nm": float(torque.min()),
                "torque_max_nm": float(torque.max()),
                "data_share": share,
                "data_led": share >= DATA_LED_SHARE,
                "found": share >= DATA_LED_SHARE and c > z * std,
                **({"held_negative_compliance": eff.state["negative_compliance"]} if eff.held else {}),
            }
        )
    return out
