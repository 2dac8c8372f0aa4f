"""The physics terms of a diagnosed model: where the geometric fit starts (the links' thermal growth when the
robot file names their material, the joints' gravity yield when it names the link masses, the tracker's scale
when its air reading stays put while the recorded temperature rises) and what the fit made of them against
their priors (fitted beside prior, standard error, the data's share of what is known).
The selection never adds or removes these terms; hil.analysis.diagnosis.pipeline reports them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy import stats

from hil.analysis.calibration.solve import CalibrationResult, Problem, position_noise_m
from hil.geometry.kinematics import KinematicModel
from hil.geometry.robots import EXPANSION_RANGE_PER_K
from hil.model.calibrated_model import CalibratedModel, initial_model
from hil.model.effects import (
    PRIOR_CONFLICT_SIGMAS,
    Effect,
    GravityCompliance,
    gravity_physics,
    gravity_physics_term,
    hold_absent,
    hold_rigid,
    material_expansion,
    material_growth,
    stuck_air_scale,
    stuck_air_tracker_scale,
    without_prior,
)

# A weather station that reads the hall's air moves with it: its readings change by a few hundredths of a K
# within minutes (a hall is never still to that level; stations report 0.01 K steps, the coarser ones 0.1 K),
# and an arm that warms by a kelvin warms the air round it by some part of that. A hand-entered air or a stuck
# station repeats one value exactly. An air reading that changes by less than half a station's finest step
# over the whole campaign (room for a file's rounding, none for a live station's one-step flicker) was
# entered by hand, or the station is stuck, or not read at all.
STUCK_AIR_TOLERANCE_K = 0.005
# ... and counts as stuck only where the recorded temperature spans at least this: 100x the tolerance, so a
# working station in air that warmed by even a tenth of the recorded temperature's rise would have moved ten
# times past it (and the same span below which the diagnosis calls the temperature not spanned:
# hil.analysis.diagnosis.questions.MIN_TEMPERATURE_SPAN_K).
STUCK_AIR_MIN_SPAN_K = 1.0


@dataclass(frozen=True)
class StuckAir:
    """A campaign whose tracker's air reading stayed at `air_c` while the recorded temperature spanned
    `span_k` (from `start_c` to `end_c`, its first and last rows' readings)."""

    air_c: float
    span_k: float
    start_c: float
    end_c: float


def stuck_air(df: pd.DataFrame) -> StuckAir | None:
    """The tracker's air reading stuck (`STUCK_AIR_TOLERANCE_K`) while the recorded temperature spans at least
    STUCK_AIR_MIN_SPAN_K, on a campaign whose every row records both (`air_temperature_c`, `temperature_c`);
    None otherwise (a campaign that does not record the air says nothing of it)."""
    if not {"air_temperature_c", "temperature_c"} <= set(df.columns) or len(df) == 0:
        return None
    air = df["air_temperature_c"].to_numpy(float)
    temps = df["temperature_c"].to_numpy(float)
    if not (np.all(np.isfinite(air)) and np.all(np.isfinite(temps))):
        return None
    span = float(np.ptp(temps))
    if float(np.ptp(air)) > STUCK_AIR_TOLERANCE_K or span < STUCK_AIR_MIN_SPAN_K:
        return None
    return StuckAir(float(np.median(air)), span, float(temps[0]), float(temps[-1]))


def held_rigid_start(
    start: str | KinematicModel | CalibratedModel, joints: dict
) -> str | KinematicModel | CalibratedModel:
    """`start` with the gravity physics terms of `joints` ({joint: the compliance a fit made of it}) held rigid:
    a negative one as yielding against gravity (`hold_rigid`), another as rejected (`hold_absent`)."""
    if not joints or not isinstance(start, CalibratedModel):
        return start
    effects = [
        (hold_rigid if joints[e.joint] < 0 else hold_absent)(e, joints[e.joint])
        if gravity_physics_term(e) and e.joint in joints
        else e
        for e in start.effects
    ]
    return replace(start, effects=effects)


def physics_start(
    robot: str | KinematicModel, df: pd.DataFrame, tool_guess_m: np.ndarray | None
) -> str | KinematicModel | CalibratedModel:
    """Where the geometric fit starts: the registered nominal model with the physics the robot file allows
    (the links' thermal growth when it names their material and every row records a temperature, the joints'
    gravity yield when it names the link masses) and the campaign shows (the tracker's scale when its air
    reading stayed put while the recorded temperature rose: `stuck_air`), else `robot` itself."""
    model = initial_model(robot, df, tool_guess_m)
    ctx = model.context(df)[0]
    growth = material_expansion(ctx, model.nominal)
    effects: list[Effect] = [] if growth is None else [growth]
    effects += gravity_physics(ctx, model.nominal)
    air = stuck_air(df)
    scale = None if air is None else stuck_air_tracker_scale(ctx, air.air_c)
    if scale is not None:
        effects.append(scale)
    for eff in effects:
        model = model.with_effect(eff)
    return model if effects else robot


# A physics term (the material's growth, a joint's gravity yield) counts as measured when the data carry at
# least this share of the information on its coefficient (1 - posterior variance / prior variance), else the
# prior carries it (the term is assumed).
DATA_LED_SHARE = 0.5

# What the report says of a physics term: the data show it (found), the prior carries it (assumed), or the
# data tested it and it is not there (rejected: held at zero, the geometric model's assumption).
FOUND, ASSUMED, REJECTED = "found", "assumed", "rejected"


@dataclass(frozen=True)
class Coefficient:
    """A physics term's coefficient after a fit with its Gaussian prior, and what the data alone make of it."""

    fitted: float  # the posterior mean (the fit with its prior; the data alone once the prior is dropped)
    std: float  # the posterior standard error (scaled by the fit's sigma0)
    prior_mean: float
    prior_std: float
    data_share: float  # 1 - posterior variance / prior variance (a-priori noise)
    data_alone: float | None  # the value the data alone give (None: they carry nothing of it)
    data_alone_std: float | None

    def contradicts_prior(self) -> bool:
        """The data alone lie more than PRIOR_CONFLICT_SIGMAS from the prior (and carry most of what is known:
        a campaign that hardly sees the term cannot contradict it)."""
        if self.data_alone is None or self.data_alone_std is None or self.data_share < DATA_LED_SHARE:
            return False
        spread = float(np.hypot(self.data_alone_std, self.prior_std))
        return abs(self.data_alone - self.prior_mean) > PRIOR_CONFLICT_SIGMAS * spread

    def away_from_zero(self, z: float, positive: bool = False) -> bool:
        """The fitted value is clearly not zero: beyond `z` standard errors (above zero with `positive`)."""
        value = self.fitted if positive else abs(self.fitted)
        return value > z * self.std

    def data_show_it(self, z: float) -> bool:
        """The data alone put the coefficient clearly away from zero: their own value beyond `z` of their own
        standard errors. The posterior's distance from zero is no such evidence: a prior away from zero
        lends it part of that distance (a material's 23 +- 6.9 ppm/K is 3.3 sigma from zero on its own)."""
        if self.data_alone is None or self.data_alone_std is None:
            return False
        return abs(self.data_alone) > z * self.data_alone_std


def coefficient(result: CalibrationResult, prob: Problem, eff: Effect) -> Coefficient:
    """`eff`'s (a physics term's, one coefficient) fitted value, standard error and the data's own value:
    a Gaussian posterior is the precision-weighted mean of prior and data, so the data's value follows from
    the posterior and the prior (var_data = 1 / (1 / var_post - 1 / var_prior))."""
    prior = eff.prior()
    if prior is None:  # the prior dropped: the fit is the data's
        prior_mean = float(eff.state.get("material_per_k", eff.state.get("prior_mean_per_k", 0.0)))
        prior_std = float(eff.state.get("prior_std_per_k", eff.state.get("prior_std", 0.0)))
    else:
        prior_mean, prior_std = float(prior[0][0]), float(prior[1][0])
    std, share, std_apriori = _posterior(result, prob, eff.param_names[0], prior_std)
    fitted = float(eff.params[0])
    if eff.held:
        return Coefficient(fitted, std, prior_mean, prior_std, 0.0, None, None)
    if prior is None:
        return Coefficient(fitted, std, prior_mean, prior_std, 1.0, fitted, std)
    if share <= 0.0:
        return Coefficient(fitted, std, prior_mean, prior_std, share, None, None)
    var_post, var_prior = std_apriori**2, prior_std**2
    var_data = 1.0 / (1.0 / var_post - 1.0 / var_prior)
    alone = var_data * (fitted / var_post - prior_mean / var_prior)
    # the data's standard error in the fit's own scale (sigma0), as the posterior's
    scale = std / std_apriori if std_apriori > 0 else 1.0
    return Coefficient(
        fitted, std, prior_mean, prior_std, share, float(alone), float(np.sqrt(var_data) * scale)
    )


def _posterior(
    result: CalibrationResult, prob: Problem, name: str, prior_std: float
) -> tuple[float, float, float]:
    """(standard error scaled by sigma0, data's share of what is known, standard error at the a-priori noise)
    of a coefficient fitted with a Gaussian prior of `prior_std`: the share is 1 - posterior variance / prior
    variance (0: the prior alone, 1: the data alone)."""
    std = result.std.get(name)
    if std is None or result.sigma0_m <= 0:
        return prior_std, 0.0, prior_std
    std_apriori = std * position_noise_m(prob.measured) / result.sigma0_m  # std is scaled by sigma0
    return float(std), float(np.clip(1.0 - (std_apriori / prior_std) ** 2, 0.0, 1.0)), float(std_apriori)


def data_share(result: CalibrationResult, prob: Problem, name: str, prior_std: float) -> tuple[float, float]:
    """(standard error, data's share of what is known) of a coefficient fitted with a Gaussian prior of
    `prior_std` (`_posterior`)."""
    std, share, _ = _posterior(result, prob, name, prior_std)
    return std, share


def material_decision(result: CalibrationResult, prob: Problem, alpha: float) -> Effect | None:
    """What the data make of the links' material growth in a fitted model, as the term to fit instead (None:
    the fit stands). Data that contradict the material (`Coefficient.contradicts_prior`) drop its prior
    (`without_prior`); data that carry most of what is known and whose own value is not clearly away from zero
    (the two-sided `alpha` level, `Coefficient.data_show_it`: the posterior's distance from zero is partly the
    prior's, so it is no finding; the data's own value where they contradict the prior) hold it at zero
    (`hold_absent`), as do data whose own value is no growth of any material (EXPANSION_RANGE_PER_K: a
    temperature that follows a drift in time or the air). An arm whose links do not grow while the hall warms (the recorded temperature follows
    the air, not the arm) is so found out rather than given the material's growth."""

    def contradicted(eff: Effect, c: Coefficient, z: float) -> Effect:
        assert c.data_alone is not None and c.data_alone_std is not None
        lo, hi = EXPANSION_RANGE_PER_K
        if abs(c.data_alone) > z * c.data_alone_std and lo <= c.data_alone <= hi:
            return without_prior(eff, c.fitted)
        # no growth, or none of any material (the temperature's term follows a drift, the air): the links
        # are held at no growth and the selection tests what the temperature follows
        return hold_absent(eff, c.data_alone)

    return _prior_decision(result, prob, alpha, material_growth, contradicted)


def tracker_air_decision(result: CalibrationResult, prob: Problem, alpha: float) -> Effect | None:
    """What the data make of the tracker's scale from a stuck air reading (`stuck_air_scale`), as the term to
    fit instead (None: the fit stands): data that carry most of what is known of it and whose own value is not
    clearly away from zero (the two-sided `alpha` level, `Coefficient.data_show_it`) hold it at zero
    (`hold_absent`: the air did not warm, or the station was right); data that contradict the prior drop it
    (`without_prior`) where their own value is clearly a scale, else hold it at zero. Where the prior carries
    it, it stays assumed."""

    def contradicted(eff: Effect, c: Coefficient, z: float) -> Effect:
        return without_prior(eff, c.fitted) if c.data_show_it(z) else hold_absent(eff, c.fitted)

    return _prior_decision(result, prob, alpha, stuck_air_scale, contradicted)


def _prior_decision(
    result: CalibrationResult,
    prob: Problem,
    alpha: float,
    chosen: Callable[[Effect], bool],
    contradicted: Callable[[Effect, Coefficient, float], Effect],
) -> Effect | None:
    """The rule both physics terms with a Gaussian prior follow (the `chosen` one of the fitted model), as
    the term to fit instead (None: the fit stands): the prior carries it (assumed), or its prior was dropped
    and the data leave it at zero (held there), or the data contradict the prior (`contradicted` says what
    then), or the data alone put it clearly away from zero (found), else the data reject it (held at zero)."""
    eff = next((e for e in result.model.effects if chosen(e)), None)
    if eff is None or eff.held:
        return None
    c = coefficient(result, prob, eff)
    z = float(stats.norm.isf(alpha / 2))
    if c.data_share < DATA_LED_SHARE:
        return None  # assumed: the prior carries it
    if eff.state.get("prior_dropped"):
        return None if c.away_from_zero(z) else hold_absent(eff, c.fitted)
    if c.contradicts_prior():
        return contradicted(eff, c, z)
    if c.data_show_it(z):
        return None
    return hold_absent(eff, c.fitted if c.data_alone is None else c.data_alone)


def _standing(eff: Effect, c: Coefficient, z: float) -> str:
    """A physics term with a Gaussian prior as the report says it: rejected (held at zero), assumed (the prior
    carries it), else found where the data alone put it beyond `z` of their standard errors, rejected where
    they do not."""
    if eff.held:
        return REJECTED
    if c.data_share < DATA_LED_SHARE:
        return ASSUMED
    return FOUND if c.data_show_it(z) else REJECTED


def term_shift_mm(model: CalibratedModel, prob: Problem, eff: Effect) -> float:
    """How much a term moves the prediction on the rows of `prob`: the RMS (mm) of the model's positions with
    it minus without it."""
    without = replace(model, effects=[e for e in model.effects if e is not eff])
    prob.ctx.p_flange_tool = model._row_tools(prob.smr)
    d = model.predict_ctx(prob.ctx) - without.predict_ctx(prob.ctx)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))) * 1000.0)


def thermal_summary(result: CalibrationResult, prob: Problem, alpha: float = 1e-3) -> dict | None:
    """The material's thermal growth in the fitted model: the coefficient fitted beside the material's, its
    standard error, the temperature the rows span, the data's share of what is known of it (0: the prior
    alone, the campaign spanned too little temperature; 1: the data alone), what the data alone make of it
    and its `standing`: found, assumed (with `shift_mm`, how much it moves the prediction on the rows) or
    rejected. None without such a term."""
    eff = next((e for e in result.model.effects if material_growth(e)), None)
    if eff is None:
        return None
    c = coefficient(result, prob, eff)
    z = float(stats.norm.isf(alpha / 2))
    temps = prob.ctx.temperature_c
    standing = _standing(eff, c, z)
    extra: dict = {}
    if eff.state.get("rejected"):
        extra["data_per_k"] = float(eff.state["data_value"])
    if eff.state.get("prior_dropped"):
        extra["with_prior_per_k"] = float(eff.state["with_prior"])
    # the data's own value beyond PRIOR_CONFLICT_SIGMAS prior sigmas from the material's
    off = abs(extra.get("data_per_k", c.fitted) - float(eff.state["material_per_k"]))
    contradicted = bool(eff.state.get("prior_dropped")) or (
        "data_per_k" in extra and off > PRIOR_CONFLICT_SIGMAS * c.prior_std
    )
    return {
        **extra,
        "material_per_k": float(eff.state["material_per_k"]),
        "fitted_per_k": c.fitted,
        "std_per_k": c.std,
        "prior_std_per_k": float(eff.state["prior_std_per_k"]),
        "span_k": float(np.ptp(temps)) if temps is not None and len(temps) else 0.0,
        "reference_c": float(eff.state["reference"]),
        "data_share": 1.0 if eff.state.get("rejected") else c.data_share,
        "data_led": standing != ASSUMED,
        "prior_contradicted": contradicted,
        "standing": standing,
        "shift_mm": term_shift_mm(result.model, prob, eff),
    }


def gravity_summary(result: CalibrationResult, prob: Problem, alpha: float) -> list[dict]:
    """Each joint's yield under the link masses' gravity in the fitted model (one per physics term): the
    compliance and its standard error, the stiffness it means (kN m/rad), the torque the rows span, the data's
    share of what is known of it (as `thermal_summary`), whether the data found the yield (data-led and a
    compliance above zero by more than the two-sided `alpha` quantile of its standard error) and its
    `standing` (found, assumed with `shift_mm`, rejected). A term held rigid says what the data had made of
    it: negative (the joint yielding against gravity: `hold_rigid`) or no better than a rigid joint on held-out
    points (`hold_absent`)."""
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
        found = not eff.held and share >= DATA_LED_SHARE and c > z * std
        standing = REJECTED if eff.held else FOUND if found else ASSUMED
        held: dict = {}
        if "negative_compliance" in eff.state:
            held["held_negative_compliance"] = eff.state["negative_compliance"]
        if eff.state.get("rejected"):
            held["rejected_compliance"] = eff.state["data_value"]
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
                "found": found,
                "standing": standing,
                "shift_mm": term_shift_mm(result.model, prob, eff),
                **held,
            }
        )
    return out


def tracker_air_summary(
    result: CalibrationResult, prob: Problem, air: StuckAir | None, alpha: float = 1e-3
) -> dict | None:
    """The tracker's scale from its stuck air reading (`stuck_air`) in the fitted model: the air it read, the
    recorded temperature's span, the coefficient fitted beside its prior (per K of the recorded temperature),
    what the data alone make of it, the data's share of what is known, and its `standing`: found (the data
    alone put it clearly away from zero), assumed (the prior carries it; `shift_mm`: how much it moves the
    prediction on the rows) or rejected (the data carry it and find no scale: held at zero). None without
    such a term."""
    eff = next((e for e in result.model.effects if stuck_air_scale(e)), None)
    if eff is None or air is None:
        return None
    c = coefficient(result, prob, eff)
    z = float(stats.norm.isf(alpha / 2))
    standing = _standing(eff, c, z)
    data_alone = float(eff.state["data_value"]) if eff.state.get("rejected") else c.data_alone
    data_alone_std = None if eff.state.get("rejected") else c.data_alone_std
    return {
        "air_c": air.air_c,
        "span_k": air.span_k,
        "temperature_start_c": air.start_c,
        "temperature_end_c": air.end_c,
        "prior_per_k": float(eff.state["prior_mean_per_k"]),
        "prior_std_per_k": float(eff.state["prior_std_per_k"]),
        "fitted_per_k": c.fitted,
        "std_per_k": c.std,
        "data_per_k": data_alone,
        "data_std_per_k": data_alone_std,
        "data_share": 1.0 if eff.state.get("rejected") else c.data_share,
        "data_led": standing != ASSUMED,
        "prior_dropped": bool(eff.state.get("prior_dropped")),
        "standing": standing,
        "shift_mm": term_shift_mm(result.model, prob, eff),
    }
