"""A diagnosis in words for the terminal: its conclusion, cautions, physics terms and open questions. The
diagnosis returns its verdict as data; the wording is here (and the HTML page and JSON file reuse it)."""

from __future__ import annotations

from hil.analysis.diagnosis.cautions import (
    AmbiguousEffects,
    CalibrationNote,
    Caution,
    FirstChoiceSetAside,
    PreviousEffectsKept,
    StageWorseThanPrevious,
    ThermalPriorContradicted,
    TrackerAirStuck,
    ValidationJointsOutside,
    ValidationTemperaturesOutside,
    ValidationUnrepresented,
    ValidationWorseThanGeometric,
)
from hil.analysis.diagnosis.pipeline import DiagnosisReport, tracker_air_caution
from hil.analysis.diagnosis.questions import AmbiguousEffects as AmbiguousQuestion
from hil.analysis.diagnosis.questions import (
    ConfoundedParameters,
    ConfoundedWithGeometry,
    DriftUnmonitored,
    Marginal,
    OneApproachDirection,
    PeriodNotCovered,
    Question,
    TemperatureNotSpanned,
    ThermalRivals,
    as_question,
)
from hil.analysis.diagnosis.screening import effect_label
from hil.model.effects import REFRACTION_PER_K
from hil.model.residual_maps import MAP_MODES


def _effect(e: dict) -> str:
    return effect_label(e["name"], e["joint"])


def caution_text(c: Caution) -> str:
    """One caution of the verdict (hil.analysis.diagnosis.cautions) in words."""
    match c:
        case CalibrationNote():
            return c.text
        case FirstChoiceSetAside():
            return (
                f"a first choice of {_effect(c.effect)} led to a worse final model ({c.heldout_rms_mm:.4f} vs "
                f"{c.heldout_rms_without_mm:.4f} mm held-out); it was set aside"
            )
        case PreviousEffectsKept():
            return (
                f"a selection that started from the earlier diagnosis' effects ({', '.join(_effect(e) for e in c.effects)}) "
                f"predicted held-out points better ({c.heldout_rms_kept_mm:.4f} mm, p = {c.p_value:.2g}) than one that "
                f"dropped {', '.join(_effect(e) for e in c.dropped)} ({c.heldout_rms_mm:.4f} mm); it was kept"
            )
        case StageWorseThanPrevious():
            return f"stage '{c.stage}' predicts held-out points worse than the stage before it ({c.rms_mm:.4f} mm)"
        case AmbiguousEffects():
            return (
                f"on this data {_effect(c.chosen)} and {_effect(c.confounded_with)} explain the same residual; "
                "the choice between them is not reliable (measure poses or approach directions that separate them, "
                "e.g. a random visiting order)."
            )
        case ValidationUnrepresented():
            v, h = c.validate_rms_mm, c.heldout_rms_mm
            return (
                f"the validation campaign's RMS ({v:.4f} mm) is {v / h:.1f}x the held-out one: the training campaign "
                "does not represent it (poses, visiting order, time, tracker placement), so an effect may be hidden "
                "in the training data by another one; measure a campaign in a random order"
                + ("" if c.reregistered else ", or re-register the base on it")
            )
        case ValidationWorseThanGeometric():
            return (
                f"on the validation campaign the final model ({c.final_rms_mm:.4f} mm) predicts worse than the "
                f"geometric one ({c.geometric_rms_mm:.4f} mm): use the geometric model there"
            )
        case ValidationTemperaturesOutside():
            (vlo, vhi), (lo, hi) = c.validate_c, c.training_c
            return (
                f"validation temperatures {vlo:.1f}..{vhi:.1f} C lie outside the training's {lo:.1f}..{hi:.1f} C: "
                "the model extrapolates thermal effects (measure the training over the working temperatures)"
            )
        case ThermalPriorContradicted():
            follows = (
                "holds no growth (the recorded temperature follows something else: the air rather than the arm, a "
                "drift in time)"
                if c.standing == "rejected"
                else "follows the data"
            )
            return (
                f"the data make the links' thermal growth {c.data_per_k * 1e6:.1f} ppm/K, against the material's "
                f"{c.material_per_k * 1e6:.1f} ppm/K in the robot file: the model {follows}; if the arm is of "
                "another material, give its expansion_per_k in the robot file"
            )
        case TrackerAirStuck():
            return _tracker_air_words(c)
        case ValidationJointsOutside():
            return (
                f"validation joint(s) {', '.join(map(str, c.joints))} leave the training's range by more than "
                f"{c.margin_deg:g} deg: the model extrapolates there"
            )
    raise ValueError(f"no wording for the caution kind '{c.kind}'")


def _ppm(value: float) -> str:
    return f"{value * 1e6:.2f}"


def _tracker_air_words(c: TrackerAirStuck) -> str:
    """A stuck air reading in the user's terms: what was read, what it means, what the model holds and why,
    and the remedy."""
    rose = "rose" if c.end_c >= c.start_c else "fell"
    data = (
        "the data alone carry nothing of it"
        if c.data_per_k is None
        else f"the data alone make it {_ppm(c.data_per_k)} ppm/K"
        if c.data_std_per_k is None
        else f"the data alone: {_ppm(c.data_per_k)} +- {_ppm(c.data_std_per_k)} ppm/K"
    )
    prior = f"{_ppm(c.prior_per_k)} +- {_ppm(c.prior_std_per_k)} ppm/K"
    if c.standing == "found":
        held = (
            f"the data show it: the model scales the tracker's distances by {_ppm(c.fitted_per_k)} +- "
            f"{_ppm(c.std_per_k)} ppm per K of the recorded temperature (prior {prior}; {data})"
        )
    elif c.standing == "rejected":
        held = f"the data find no such scale ({data}, no different from zero; prior {prior}): the model holds none"
    else:
        held = (
            f"the data cannot tell how much the air warmed, so the model assumes the scale at "
            f"{_ppm(c.fitted_per_k)} +- {_ppm(c.std_per_k)} ppm per K of the recorded temperature (prior "
            f"{prior}; {data}); it is the tracker's scale, not the arm's growth"
        )
    return (
        f"the tracker's air temperature read {c.air_c:.2f} degC at every point while the recorded temperature "
        f"{rose} {abs(c.end_c - c.start_c):.1f} K ({c.start_c:.2f} to {c.end_c:.2f} degC): if the air was entered "
        f"by hand or the weather station is stuck, the tracker's distances scale by about "
        f"{_ppm(abs(REFRACTION_PER_K))} ppm per K the air warmed; {held}. Let the tracker read its weather "
        "station, or record the hall's air; revisits of a few poses spread over several K resolve the scale"
    )


def tracker_air_text(tracker_air: dict | None) -> str | None:
    """The tracker's scale from a stuck air reading in words (the caution's; None without such a term)."""
    if not tracker_air:
        return None
    return (
        "Tracker scale from a stuck air reading: "
        + _tracker_air_words(tracker_air_caution(tracker_air))
        + "."
    )


def conclusion(report: DiagnosisReport) -> str:
    """The verdict in words: what was added, what is left, then one caution a line."""
    return conclusion_text(report.verdict, report.effects_added)


def conclusion_text(v: dict, effects_added: list[dict]) -> str:
    """`conclusion` from the verdict data and the effects ({name, joint}) the final model holds."""
    added = ", ".join(_effect(e) for e in effects_added) or "nothing"
    if v["residual"] == "structured":
        text = (
            f"Added: {added}. Structured residual remains that no candidate effect explains (residual sigma "
            f"{v['ratio']:.2f}x the noise floor; a {v['map']} residual map predicts it on held-out points), so a "
            f"residual map is used as the fallback ({MAP_MODES.get(v['map'], v['map'])})."
        )
    elif v["residual"] == "local":
        text = (
            f"Added: {added}. Structured residual remains that no candidate effect explains (residual sigma "
            f"{v['ratio']:.2f}x the noise floor), but only locally: a {v['map']} residual map predicts it between "
            "measured points, not in blocks of the volume held out, so no map is added (it would extrapolate "
            "worse than the model alone). Measure densely where the model is to be used to map it there."
        )
    elif v["residual"] == "excess":
        text = (
            f"Added: {added}. The residual is {v['ratio']:.2f}x the noise floor but shows no structure a residual "
            "map can predict: the noise floor is probably underestimated (robot repeatability?)."
        )
    else:
        text = f"Added: {added}. The residual is at the noise floor ({v['ratio']:.2f}x)."
    return "\n".join([text, *(f"Caution: {caution_text(c)}" for c in v["cautions"])])


def final_orientation_text(report: DiagnosisReport) -> str | None:
    """The final model's orientation residual in words, when a 6-DoF probe was fitted and effects were added
    (without effects the geometric fits' figures say it)."""
    final = report.model.info.get("orientation")
    if not final or not report.model.effects:
        return None
    return f"6-DoF probe, final model (effects included): orientation RMS {final['rms_deg']:.4f} deg"


def thermal_text(thermal: dict | None) -> str | None:
    """The links' thermal growth in words: the fitted coefficient beside the material's, and whether the
    campaign's temperature span or the material's prior set it (None without a material term)."""
    if not thermal:
        return None
    share = thermal["data_share"]
    material = thermal["material_per_k"] * 1e6
    if thermal["standing"] == "rejected":
        data = thermal.get("data_per_k", thermal["fitted_per_k"]) * 1e6
        return (
            f"Thermal growth of the links: rejected, the data find none (they make it {data:.1f} ppm/K, no "
            f"different from zero; material {material:.1f} ppm/K; temperature span {thermal['span_k']:.2f} K): "
            "the model holds no growth."
        )
    if thermal["standing"] == "found":
        who = "found by this campaign"
        if thermal["prior_contradicted"]:
            who += (
                f"; the model follows the data, not the material (with the material's prior the fit made "
                f"{thermal['with_prior_per_k'] * 1e6:.1f} ppm/K of it)"
            )
    else:
        who = (
            f"assumed: the campaign spans too little temperature to measure it, so the material's value carries "
            f"it; it moves the prediction by {thermal['shift_mm']:.4f} mm RMS on these rows, more where the "
            "temperature leaves their span"
        )
    return (
        f"Thermal growth of the links: {thermal['fitted_per_k'] * 1e6:.1f} +- {thermal['std_per_k'] * 1e6:.1f} "
        f"ppm/K fitted, material {material:.1f} ppm/K (temperature span "
        f"{thermal['span_k']:.2f} K, the data carry {100 * share:.0f} % of what is known of it; {who})."
    )


def gravity_text(gravity: list[dict]) -> str | None:
    """The joints' yield under the link masses' gravity in words: each joint's stiffness with its standard
    error, and whether the data found it or the prior (a rigid joint) holds it (None without such terms)."""
    if not gravity:
        return None
    parts = []
    for g in gravity:
        k, dk = g["stiffness_knm_per_rad"], g["stiffness_std_knm_per_rad"]
        if "held_negative_compliance" in g:
            what = (
                f"held rigid: the data made its compliance negative "
                f"({g['held_negative_compliance'] * 1e6:.2g} urad/(N m), the joint yielding against gravity), so "
                "the term stood in for something else"
            )
        elif "rejected_compliance" in g:
            what = (
                f"rejected, held rigid: the data find no yield (compliance {g['rejected_compliance'] * 1e6:.2g} "
                "urad/(N m), no different from zero) and a rigid joint predicts held-out points as well"
            )
        elif g["found"]:
            size = f"{k:.0f} +- {dk:.0f} kN m/rad" if dk is not None and dk < k else f"{k:.0f} kN m/rad"
            what = f"{size}, found by the data"
        elif g["data_led"]:
            what = (
                f"assumed: no yield clearly seen (compliance {g['compliance_rad_per_nm'] * 1e6:.2g} +- "
                f"{g['std_rad_per_nm'] * 1e6:.2g} urad/(N m)) but it predicts held-out points better than a "
                f"rigid joint; it moves the prediction by {g['shift_mm']:.4f} mm RMS"
            )
        else:
            what = (
                f"assumed: the prior holds it (the data carry {100 * g['data_share']:.0f} %); it moves the "
                f"prediction by {g['shift_mm']:.4f} mm RMS"
            )
        parts.append(f"joint {g['joint']}: {what}")
    return "Gravity yield from the link masses (joint stiffness): " + "; ".join(parts) + "."


def z_text(z: float, decisive: float) -> str:
    """An evidence z to two figures, or three where two would read as the threshold it has not reached (4.56
    against 4.6) or reached (4.6 against 4.6 for 4.62)."""
    short = f"{z:.2g}"
    return f"{z:.3g}" if short == f"{decisive:.2g}" and z != decisive else short


def question_text(q: Question | dict) -> str:
    """One open question of the diagnosis (hil.analysis.diagnosis.questions) in words: what is undecided and why
    (a question read from a campaign's records, a dict, is read back first)."""
    q = as_question(q)
    match q:
        case PeriodNotCovered():
            return (
                f"a once-per-turn error of joint {q.effect['joint']}: its sampled range covers {q.range_deg:.0f} deg, "
                f"a test needs {q.needs_deg:.0f} (over a shorter arc it looks like geometry)"
            )
        case OneApproachDirection():
            return (
                f"backlash of joint {q.effect['joint']}: {q.rows_up} rows approached it from below, {q.rows_down} "
                f"from above; a test needs {q.needs_rows} each way"
            )
        case DriftUnmonitored():
            return (
                f"drift of the cell over time: {q.revisited_poses} poses were measured again late in the campaign, "
                f"{q.needs_poses} are needed"
            )
        case TemperatureNotSpanned():
            if not q.recorded:
                return "thermal growth: the campaign records no temperature; poses cannot decide it"
            return (
                f"thermal growth: the temperature spans {q.span_k:.2f} K (needs {q.needs_k:.0f} K); poses cannot "
                "decide it, a run at another temperature can"
            )
    z, decisive = q.evidence_z, q.decisive_z
    ev = (
        ""
        if z is None or decisive is None
        else f" (evidence z {z_text(z, decisive)}, decided at {decisive:.2g})"
    )
    match q:
        case Marginal():
            return f"{_effect(q.effect)}: marginal, held-out p = {q.p_cv:.2g}{ev}"
        case ConfoundedWithGeometry():
            return f"{_effect(q.effect)}: the geometry imitates it on these poses{ev}"
        case AmbiguousQuestion():
            return f"{_effect(q.effect)} or {_effect(q.rival)}: both explain the same residual{ev}"
        case ThermalRivals():
            return (
                f"the tracker's scale or the links' growth: over {q.span_k:.2g} K the growth may have taken the "
                f"tracker's stretch (about the tracker, not the base){ev}"
            )
        case ConfoundedParameters():
            a, b = q.parameters
            return f"{a} and {b} correlate {q.correlation:+.3f}: each alone is unreliable{ev}"
    return q.kind.value


def undecided_text(report: DiagnosisReport) -> str:
    """The open questions in words, one a line (or a line that says nothing is undecided)."""
    if not report.undecided:
        return "undecided: nothing; the campaign decides every question the diagnosis asks"
    lines = ["undecided:"]
    lines += [f"  - {question_text(q)}" for q in report.undecided]
    return "\n".join(lines)


def group_text(group: dict) -> str:
    """What one group of a plan's rows should decide."""
    q = as_question(group["question"])
    what = question_text(q).split(":")[0]
    if isinstance(q, PeriodNotCovered):
        extra = f", joint range {group['range_after_deg']:.0f} deg after" + (
            " (and back down: backlash)" if group.get("also") else ""
        )
    elif "evidence_z_after" in group:
        before, after, decisive = group["evidence_z_before"], group["evidence_z_after"], group["decisive_z"]
        extra = f", evidence z {z_text(before, decisive)} -> {z_text(after, decisive)} (decided at {decisive:.2g})"
    else:
        extra = ""
    return f"  {group['purpose']:<28} {group['rows']:>3} rows: decides {what}{extra}"


def plan_text(plan: dict) -> str:
    """The plan's groups in words (terminal and HTML); a line that says so when nothing is to be measured."""
    if plan["rows"] == 0:
        lines = ["plan: nothing undecided that poses can decide; the plan holds the header only"]
    else:
        lines = [f"plan: {plan['rows']} poses, in this order:"]
        lines += [group_text(g) for g in plan["groups"]]
    for skipped in plan["not_planned"]:
        lines.append(f"  not planned: {question_text(skipped['question']).split(':')[0]}: {skipped['why']}")
    return "\n".join(lines)


def intervals_text(intervals: list[dict]) -> str | None:
    """The prediction intervals' coverage in words: on the held-out rows their factor was read from (at least
    P by construction) and on the validation rows (the honest check)."""
    if not intervals:
        return None
    parts = []
    for c in intervals:
        if c["on"] == "heldout":
            parts.append(f"{100 * c['covered']:.1f} % of {c['rows']} held-out rows (their factor's own rows)")
        elif c.get("quantity") == "orientation":
            parts.append(
                f"the probe's measured orientation on {100 * c['covered']:.1f} % of {c['rows']} validation rows, "
                f"median interval {c['median_interval_deg']:.4f} deg against an RMS error of {c['rms_deg']:.4f} deg"
            )
        else:
            parts.append(
                f"{100 * c['covered']:.1f} % of {c['rows']} validation rows, median interval "
                f"{c['median_interval_mm']:.4f} mm against an RMS error of {c['rms_mm']:.4f} mm"
            )
    p = intervals[0]["probability"]
    return (
        f"Prediction intervals ({100 * p:.0f} %, hil predict --interval) hold the measured point on "
        + "; ".join(parts)
        + "."
    )
