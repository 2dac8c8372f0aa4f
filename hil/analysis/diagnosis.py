"""Close the loop: calibrate, look at the residual, test candidate effects, add the one that helps, repeat.

Every fit and test uses every equation the data has: each SMR's position and, from a 6-DoF probe, its
orientation, each weighted by its noise (the tracker's MPE, the probe's stated angle noise; see
hil.analysis.calibration.Problem); the held-out figures (mm) are of positions. A probe whose rotation residual
after the geometric fit is beyond its stated noise (ORIENTATION_SELECTION_FACTOR) refutes that weight: the
effects are then tested on positions only, and a caution says so. Several SMRs at one pose are
one sample of the pose's error (they share its fold and count once in the tests).

Selection rule for each round (every candidate from `hil.analysis.effects` the data could reveal):
1. add the candidate to the current model and re-run the identifiability analysis on the joint
   (geometry + effects) Jacobian, so coefficients the data cannot separate from the geometry are merged;
2. k-fold cross-validation on blocks of the workspace (default 5 folds, the same for every candidate;
   CV_REPEATS partitions, each point's held-out squared error averaged over them; the poses of a
   single-joint sweep dealt to the folds in turn, hil.analysis.folds.campaign_folds): each fold refits all
   free parameters on the other folds and predicts the held-out points;
3. the candidate must (a) lower the held-out squared error per point, tested pairwise against the current
   model (one-sided t-test, p < alpha), and (b) explain more than measurement noise on the full fit:
   (SSE_before - SSE_after) / sigma^2 ~ chi2(k) with sigma the larger of the noise-floor sigma and the
   residual sigma after, p < alpha / number of candidates;
4. the passing candidate with the largest held-out gain is added (near-ties and temperature: `pick_winner`)
   and the whole model refitted robustly; an earlier effect that no longer earns its place is removed.
   The screening's rows are the current model's inliers; a candidate the full-fit test finds but the held-out
   one does not is judged again on the rows that the current model or its own robust fit accepts (rival
   models are judged on the rows either fits, a row both reject is a blunder: `reclaimed`).
The loop stops when nothing passes. The links' thermal growth is physics, not a candidate, when the robot
names its material and the campaign records a temperature: it is in the model from the geometric fit on,
fitted with the material's coefficient as its prior (hil.analysis.effects.material_expansion), never removed,
and the report gives the fitted coefficient beside the material's (`thermal_summary`). So is the joints' yield
under gravity when the robot file gives the links' masses: one compliance per joint that carries a gravity
torque, the torque computed from the masses, fitted with a prior centred on a rigid joint
(hil.analysis.effects.gravity_physics); the report gives each joint's stiffness and whether the data found
its yield (`gravity_summary`). The residual left is
then tested against the noise floor; if it is larger and a residual map predicts it on held-out blocks of the
volume (the spatial folds: better than no map, p < alpha), the report says structure remains that no
candidate explains and adds the map as a fallback stage. A map that only interpolates (wins on random folds,
not on spatial ones) is not added: the verdict calls the structure local.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats
from threadpoolctl import threadpool_limits

from hil.analysis.calibrated_model import CalibratedModel
from hil.analysis.calibration import (
    CONFOUNDED_NOTE,
    CalibrationResult,
    Problem,
    calibrate,
    confounded_pairs,
    flatten_jacobian,
    parameter_correlations,
)
from hil.analysis.calibration import reregister as reregister_model
from hil.analysis.diagnosis_baseline import (
    Baseline,
    Progress,
    baseline_fit,
    fit_plain,
    free_mask,
    quiet,
    registration,
)
from hil.analysis.drift_monitor import reference_drift
from hil.analysis.effects import (
    Effect,
    candidate_effects,
    make_effect,
    material_conflict,
    material_growth,
    physical,
    tool_points_rows,
    yields_against_gravity,
)
from hil.analysis.identifiability import IdentifiabilityReport
from hil.analysis.noise_floor import TRACKER_MPE_M, NoiseFloor
from hil.analysis.physics_terms import gravity_summary, thermal_summary
from hil.analysis.reclaim import reclaimed
from hil.analysis.residual_maps import MAP_KINDS, MAP_MODES, kfold_map_errors, make_map, map_from_dict
from hil.analysis.rivals import compare_with_rivals, rivals_in_round
from hil.analysis.screening import (
    EXTRAPOLATING_FAMILIES,
    Candidate,
    Screen,
    cv_residuals,
    effect_label,
    group_key,
    held_out_gain,
    linear_fit_heldout,
    pick_winner,
    predicts_along_joint,
    weakest_effect,
)
from hil.data.dataset import drop_duplicate_rows, joints_rad
from hil.geometry.kinematics import KinematicModel


def error_stats(err_m: np.ndarray) -> dict[str, float]:
    """mean / RMS / max / 95th percentile of 3-D error norms, mm, from (N, 3) errors in metres."""
    e = np.linalg.norm(np.atleast_2d(err_m), axis=1) * 1000.0
    return {
        "mean_mm": float(np.mean(e)),
        "rms_mm": float(np.sqrt(np.mean(e**2))),
        "max_mm": float(np.max(e)),
        "p95_mm": float(np.percentile(e, 95)),
    }


@dataclass
class Step:
    effect: dict  # {name, joint}
    parameters: list[dict]  # {name, value, std}
    heldout_before: dict
    heldout_after: dict
    candidates: list[Candidate]
    merged: list[dict]  # identifiability notes for the effect's coefficients
    correlations: list[dict]  # strongest correlation of each effect coefficient with a geometric parameter
    plot: dict = field(default_factory=dict)  # driver label/values, residual along the effect before/after
    action: str = (
        "added"  # "removed" (a later effect made it redundant), "replaced" (a rival the data prefers)
    )
    summary: dict = field(default_factory=dict)  # physical figures: deflection, amplitude, gap, ppm/K
    replaces: dict | None = None  # the effect a "replaced" step took out ({name, joint})
    rival_tests: list[dict] = field(default_factory=list)  # hil.analysis.rivals' comparisons behind it

    def title(self) -> str:
        """'gravity_compliance joint 2', 'removed backlash joint 4', 'cyclic joint 2 (replaces cyclic joint 3)'."""
        named = self.effect["name"] + (f" joint {self.effect['joint']}" if self.effect["joint"] else "")
        if self.action == "removed":
            return "removed " + named
        if self.action == "replaced" and self.replaces:
            gone = self.replaces["name"] + (
                f" joint {self.replaces['joint']}" if self.replaces["joint"] else ""
            )
            return f"{named} (replaces {gone})"
        return named

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["candidates"] = [c.to_dict() for c in self.candidates]
        return d


@dataclass
class DiagnosisReport:
    model: CalibratedModel
    calibration: dict  # both solvers' summaries
    noise: NoiseFloor
    stages: list[dict]
    steps: list[Step]
    unexplained_structure: bool
    verdict: (
        dict  # residual ("floor" | "excess" | "local" | "structured"), ratio, map, cautions: report words it
    )
    residual_map: dict | None = None
    histograms: dict = field(default_factory=dict)  # stage -> held-out error norms (mm)
    final_round: list[Candidate] = field(default_factory=list)
    ambiguities: list[dict] = field(default_factory=list)  # effects this data could not tell apart
    undecided: list[dict] = field(default_factory=list)  # open questions (hil.analysis.undecided)
    plan: dict | None = None  # the proposed measurements' groups (hil.analysis.discrimination.Plan.to_dict)
    run: dict = field(default_factory=dict)  # robot, input files (hash, rows), date, software version
    thermal: dict | None = None  # the material's thermal growth, fitted against its prior (`thermal_summary`)
    # the joints' yield from the link masses (`gravity_summary`)
    gravity: list[dict] = field(default_factory=list)
    drift: dict | None = None  # reference poses re-measured (hil.analysis.drift_monitor.reference_drift)

    @property
    def effects_added(self) -> list[dict]:
        """The effects the final model holds, in the order they were added; the material's thermal growth
        only where the data, not its prior, set its coefficient (else it is held at the material's value and
        reported under `thermal`), a joint's gravity yield from the link masses only where the data found it
        (`gravity_summary`'s `found`; else it is reported under `gravity` only)."""
        led = bool(self.thermal and self.thermal["data_led"])
        found = {g["joint"] for g in self.gravity if g["found"]}

        def named(e: Effect) -> bool:
            if not physical(e):
                return True
            return led if material_growth(e) else e.joint in found

        return [{"name": e.family, "joint": e.joint} for e in self.model.effects if named(e)]

    @property
    def noise_floor_mm(self) -> float:
        return self.noise.floor_mm

    def to_dict(self) -> dict:
        return {
            "effects_added": self.effects_added,
            "stages": self.stages,
            "unexplained_structure": self.unexplained_structure,
            "noise_floor_mm": self.noise.floor_mm,
            "noise_floor_method": self.noise.method,
            "verdict": self.verdict,
            "steps": [s.to_dict() for s in self.steps],
            "final_round_candidates": [c.to_dict() for c in self.final_round],
            "ambiguities": self.ambiguities,
            "undecided": self.undecided,
            "plan": self.plan,
            "thermal": self.thermal,
            "gravity": self.gravity,
            "drift": self.drift,
            "calibration": self.calibration,
            "residual_map": self.residual_map,
            "run": self.run,
        }

    def table(self) -> str:
        """Plain-text before/after table."""
        lines = [f"{'stage':<34} {'on':<9} {'mean':>8} {'RMS':>8} {'max':>8} {'p95':>8}   (mm)"]
        for s in self.stages:
            lines.append(
                f"{s['stage']:<34} {s['on']:<9} {s['mean_mm']:8.4f} {s['rms_mm']:8.4f} {s['max_mm']:8.4f} "
                f"{s['p95_mm']:8.4f}"
            )
        lines.append(
            f"noise floor (RMS of a perfect model): {self.noise.floor_mm:.4f} mm  [{self.noise.method}]"
        )
        return "\n".join(lines)


def _stage(name: str, on: str, err: np.ndarray) -> dict:
    return {"stage": name, "on": on, **error_stats(err)}


def _effect_params(result: CalibrationResult, eff_index: int) -> list[dict]:
    model = result.model
    eff = model.effects[eff_index]
    out = []
    for nm, v in zip(eff.param_names, eff.params, strict=True):
        out.append(
            {
                "name": nm,
                "value": float(v),
                "std": result.honest_std(nm),
                "unit": eff.coefficient_unit(),
                "free": nm in result.std,
            }
        )
    return out


def _correlations(result: CalibrationResult, problem: Problem, eff: Effect) -> list[dict]:
    """For each free coefficient of `eff`, its strongest correlation with a geometric parameter."""
    fnames, corr = parameter_correlations(result, problem.evaluate(result.model)[1])
    out = []
    for nm in eff.param_names:
        if nm not in fnames:
            continue
        i = fnames.index(nm)
        geo = [k for k, n in enumerate(fnames) if "." not in n]
        k = max(geo, key=lambda k: abs(corr[i, k]))
        out.append({"coefficient": nm, "parameter": fnames[k], "correlation": float(corr[i, k])})
    return out


def _effect_displacement(model: CalibratedModel, problem: Problem, index: int) -> np.ndarray:
    """Tracker-frame displacement (N, 3) that effect `index` contributes (model with minus without)."""
    without = replace(model, effects=[e for i, e in enumerate(model.effects) if i != index])
    problem.ctx.p_flange_tool = model._row_tools(problem.smr)
    return model.predict_ctx(problem.ctx) - without.predict_ctx(problem.ctx)


def run_diagnosis(
    df: pd.DataFrame,
    robot: str | KinematicModel,
    df_validate: pd.DataFrame | None = None,
    folds: int = 5,
    alpha: float = 1e-3,
    seed: int = 0,
    families: tuple[str, ...] | None = None,
    max_effects: int = 15,
    repeatability_mm: float = 0.0,
    tool_guess_m: np.ndarray | None = None,
    tracker_mpe_m: tuple[float, float] = TRACKER_MPE_M,
    compare_maps: bool = False,
    reregister_validation: str = "none",
    progress: Progress | None = None,
    screening: str = "batched",
    previous_effects: list[dict] | None = None,
) -> DiagnosisReport:
    """The whole loop on a training dataset (and an optional validation dataset never used for fitting).

    Named steps: baseline fit, forward selection (candidate screening each round), stage evaluation,
    verdict. `compare_maps` runs the k-fold residual-map comparison (IDW / SVR / GP) even when the
    residual is at the noise floor. `reregister_validation` ("none", "base", "base+tool") refits the
    base frame (and tool) of every stage on the validation campaign first, for a campaign taken from
    another tracker placement; the report then shows both. `progress(phase, done, total)` is called as
    the work advances (the CLI draws it with an ETA). `screening` "batched" judges a round's candidates
    from one shared factorisation (hil.analysis.screening); "refit" fits each candidate on its own (the
    slow reference the batched path reproduces). `previous_effects` ({name, joint}, the effects the
    diagnosis of an earlier part of this campaign named, as an active loop's round has): when the selection
    here drops any of them, a selection that starts from them is run too and the one whose model predicts
    held-out points better is kept (`_keep_previous`): a round's measurements must not make the model worse.

    Held-out figures of every stage are computed at the end on the same rows and spatial folds: all
    points except those the final model rejects as outliers.
    """
    if screening not in ("batched", "refit"):
        raise ValueError(f"screening '{screening}': use batched or refit")
    if reregister_validation not in ("none", "base", "base+tool"):
        raise ValueError(f"reregister_validation '{reregister_validation}': use none, base or base+tool")
    df = drop_duplicate_rows(df, "training data")  # copies would count twice in every test
    with threadpool_limits(1):  # small dense problems: threads only contend
        fit_args = (df, robot, folds, seed, repeatability_mm, tool_guess_m, tracker_mpe_m, progress)
        base = baseline_fit(*fit_args)
        base.screening = screening
        path = _select(base, df, alpha, families, max_effects)
        material = next((e for e in path.current.model.effects if material_growth(e)), None)
        conflict = material is not None and material_conflict(material)
        against = {
            e.joint: float(e.params[0]) for e in path.current.model.effects if yields_against_gravity(e)
        }
        if conflict or against:
            # The temperature's term took something that is no growth of the links (a drift in time, the
            # air's temperature rather than the arm's), or a joint's gravity term yields against gravity once
            # the selected effects are in: select again with the growth held at the material's and those
            # joints held rigid.
            hold = float(material.params[0]) if conflict and material is not None else None
            base = baseline_fit(*fit_args, hold_material=hold, hold_gravity={**base.held_gravity, **against})
            base.screening = screening
            path = _select(base, df, alpha, families, max_effects)
        _settle_rivals(base, df, path, alpha)
        if previous_effects:
            path = _keep_previous(base, df, path, previous_effects, alpha, families, max_effects)
        stages, hist, steps = _evaluate_stages(path, base.progress)
        report = _verdict(base, path, stages, hist, steps, alpha, compare_maps)
        report.thermal = thermal_summary(path.current, path.prob)
        report.gravity = gravity_summary(path.current, path.prob, alpha)
        if report.thermal and "held_conflicting_per_k" in report.thermal:
            report.verdict["cautions"].append(
                caution(
                    "thermal_growth_held",
                    fitted_per_k=report.thermal["held_conflicting_per_k"],
                    material_per_k=report.thermal["material_per_k"],
                )
            )
        report.drift = reference_drift(df)
        if df_validate is not None:
            _validate(report, path, df, df_validate, reregister_validation)
        report.run = run_record(base.nominal.nominal, {"training": df, "validation": df_validate})
        report.undecided = undecided_questions(df, path, alpha, float(np.sqrt(base.sigma2)))
        report.verdict["cautions"] = without_decided_pairs(report.verdict["cautions"], report.undecided)
        return report


def _select(
    base: Baseline, df: pd.DataFrame, alpha: float, families: tuple[str, ...] | None, max_effects: int
) -> _Path:
    """Forward selection, tried again without its first choice while it stays above the noise floor."""
    path = _forward_selection(base, df, alpha, families, max_effects, banned=set())
    for _ in range(2):  # greedy got stuck above the floor? Try again without its first choice.
        if not path.effects or _excess_ratio(path.current.model, base, path) <= 1.1:
            break
        first = path.effects[0]
        other = _forward_selection(base, df, alpha, families, max_effects, banned={*path.banned, first})
        # Judged on the rows either path's model accepts: a path whose model rejects more rows would
        # otherwise look better on its own inliers.
        errors, _ = _shared_heldout_errors(base, path, other)
        rms_mm = [float(np.sqrt(np.mean(e))) * 1000.0 for e in errors]
        if rms_mm[1] < 0.95 * rms_mm[0]:
            other.cautions.append(
                caution(
                    "first_choice_set_aside",
                    effect={"name": first[0], "joint": first[1]},
                    heldout_rms_mm=rms_mm[0],
                    heldout_rms_without_mm=rms_mm[1],
                )
            )
            path = other
        else:
            break
    return path


def undecided_questions(df: pd.DataFrame, path: _Path, alpha: float, sigma_m: float) -> list[dict]:
    """What the campaign leaves undecided (hil.analysis.undecided); a statistical question whose evidence
    already passes hil.analysis.discrimination's threshold is decided and left out."""
    from hil.analysis.discrimination import evidence
    from hil.analysis.undecided import open_questions

    pairs = confounded_pairs(path.current, path.prob)
    found = open_questions(df, path.final_round, path.ambiguities, pairs, alpha, path.current.model.effects)
    decided = set()
    for ev in evidence(df, path.current.model, found, sigma_m):
        ev["question"]["evidence_z"] = ev["evidence_z"]
        ev["question"]["decisive_z"] = ev["decisive_z"]
        if ev["evidence_z"] is not None and ev["evidence_z"] >= ev["decisive_z"]:
            decided.add(id(ev["question"]))
    return [q for q in found if id(q) not in decided]


def without_decided_pairs(cautions: list[dict], undecided: list[dict]) -> list[dict]:
    """The cautions less the geometric calibration's notes on confounded pairs that the final diagnosis does
    not leave open (its evidence separates them, or the final model no longer confounds them): the report
    must not call a pair unreliable that the open questions call decided."""
    open_pairs = {frozenset(q["parameters"]) for q in undecided if q["kind"] == "confounded_parameters"}

    def decided(c: dict) -> bool:
        if c["kind"] != "calibration_note" or not c["text"].startswith(CONFOUNDED_NOTE):
            return False
        words = c["text"].split()
        return frozenset((words[1], words[3])) not in open_pairs

    return [c for c in cautions if not decided(c)]


@dataclass
class _Path:
    """Step 2's outcome: the stages one forward selection went through."""

    current: CalibrationResult
    prob: Problem
    partitions: list[list[np.ndarray]]  # spatial folds, several draws (see CV_REPEATS)
    free: np.ndarray
    stage_models: list[tuple[str, CalibratedModel]]
    pending: list[dict]
    ambiguities: list[dict]
    final_round: list[Candidate]
    banned: set
    cautions: list[dict] = field(default_factory=list)  # see `caution`
    cv_final: np.ndarray | None = None  # held-out residuals of the last stage (step 3)

    @property
    def first_step(self) -> int:
        """Index in `stage_models` of the stage the selection started from (the one before its first step)."""
        return len(self.stage_models) - 1 - len(self.pending)

    @property
    def folds(self) -> list[np.ndarray]:
        """The spatial folds of the held-out figures (the first partition)."""
        return self.partitions[0]

    @property
    def effects(self) -> list[tuple[str, int | None]]:
        """The effects the selection added (not the physics terms: the material's growth, the gravity yield
        from the link masses)."""
        return [(e.family, e.joint) for e in self.current.model.effects if not physical(e)]

    @property
    def cv_rms_mm(self) -> float:
        return error_stats(_cv_positions(self.current.model, self.free, self.prob, self.folds))["rms_mm"]


# The stage that adds the joints' gravity yield computed from the link masses (physics) to the geometric fit.
GRAVITY_STAGE = "+ gravity yield (link masses)"


def _cv_positions(
    model: CalibratedModel, free: np.ndarray, prob: Problem, folds: list[np.ndarray]
) -> np.ndarray:
    """Held-out position residuals (N, 3): a 6-DoF probe's rotations take part in every fit, while the
    figures (mm) are of positions."""
    return cv_residuals(model, free, prob, folds)[:, :3]


def _excess_ratio(model: CalibratedModel, base: Baseline, path: _Path) -> float:
    """Residual sigma over the noise sigma on the path's rows."""
    r = path.prob.residuals(model)
    return float(np.sqrt(np.sum(r**2) / max(r.size - int(path.free.sum()), 1) / base.sigma2))


def _screen_round(
    base: Baseline,
    path: _Path,
    alpha: float,
    families: tuple[str, ...] | None,
    banned: set,
    df: pd.DataFrame | None = None,
) -> list[tuple[Candidate, CalibratedModel | None]]:
    """Candidate screening: every effect the data could show, tested linearly against the current model
    (with `df`, a candidate the full-fit test finds is judged again on rows the current model rejects:
    `reclaimed`)."""
    cands = candidate_effects(base.full.ctx, path.current.model.nominal, path.current.model.effects, families)
    cands = [c for c in cands if (c.family, c.joint) not in banned]
    base_fit = fit_plain(path.current.model, path.prob, path.free, iters=3)
    # Screening is linear: one Gauss-Newton step from the current fit, for the current model and for
    # every candidate alike (the problem is nearly linear there); the winner is refitted in full.
    screen = Screen(base_fit, path.prob, path.free, path.partitions, base.sigma2, alpha, len(cands))
    phase = f"effect {len(path.current.model.effects) + 1}: screening candidates"
    test = screen.test if base.screening == "batched" else screen.test_refit
    out = []
    for i, eff in enumerate(cands):
        base.progress(phase, i, len(cands))
        out.append(test(eff))
    base.progress(phase, len(cands), len(cands))
    if df is not None:
        out = reclaimed(base, path.current, path.free, alpha, out, len(cands))
    return [_along_joint(base_fit, path, base.sigma2, alpha, c, m) for c, m in out]


def _along_joint(
    base_fit: CalibratedModel,
    path: _Path,
    sigma2: float,
    alpha: float,
    cand: Candidate,
    model: CalibratedModel | None,
) -> tuple[Candidate, CalibratedModel | None]:
    """A passing candidate whose claim reaches beyond the sampled arc of its joint (a scale) fails unless it
    also predicts each half of the joint's range from the other (hil.analysis.screening.predicts_along_joint)."""
    if not cand.passed or cand.name not in EXTRAPOLATING_FAMILIES:
        return cand, model
    eff = make_effect(cand.name, cand.joint)
    eff.prepare(path.prob.ctx, base_fit.nominal)
    why = predicts_along_joint(base_fit, path.prob, path.free, eff, sigma2, alpha)
    if why is None:
        return cand, model
    return replace(cand, passed=False, note="; ".join(x for x in (why, cand.note) if x)), None


def _forward_selection(
    base: Baseline,
    df: pd.DataFrame,
    alpha: float,
    families: tuple[str, ...] | None,
    max_effects: int,
    banned: set,
    start: tuple[tuple[str, int | None], ...] = (),
) -> _Path:
    """Step 2: add the best passing candidate, refit, drop effects a later one made redundant; repeat.
    `start`: effects (family, joint) put into the model first, one stage each, without a test."""
    current = base.ridge
    prob, partitions = base.rows_and_folds(current)
    path = _Path(
        current=current,
        prob=prob,
        partitions=partitions,
        free=free_mask(current.model, prob)[0],
        stage_models=[("uncompensated (nominal)", base.nominal)]
        + (
            [("kinematic", current.model)]
            if base.geometric is None
            else [("kinematic", base.geometric.model), (GRAVITY_STAGE, current.model)]
        ),
        pending=[],
        ambiguities=[],
        final_round=[],
        banned=set(banned),
    )

    def refit(result: CalibrationResult) -> IdentifiabilityReport:
        return _refit(base, path, result)

    for name, joint in start:
        if (name, joint) in {(e.family, e.joint) for e in path.current.model.effects}:
            continue  # the physics holds it already
        carried = make_effect(name, joint)
        if not carried.prepare(base.full.ctx, path.current.model.nominal):
            continue  # this campaign does not offer it (hil.analysis.effects' conditions)
        rep = refit(calibrate(df, path.current.model.with_effect(carried), "ridge"))
        note = "carried over from the earlier diagnosis"
        cand = Candidate(name, joint, len(carried.params), float("nan"), 0.0, 1.0, 1.0, True, note)
        _record_added(path, cand, [], rep)
    for _ in range(max_effects):
        results = _screen_round(base, path, alpha, families, banned, df)
        winners = [(c, m) for c, m in results if c.passed and m is not None]
        if not winners:
            pair = _pair_lookahead(base, path, results, alpha)
            if pair is None:
                path.final_round = [c for c, _ in results]
                break
            first, (second, pair_model) = pair
            alone = make_effect(first.name, first.joint)
            alone.prepare(base.full.ctx, path.current.model.nominal)
            first.note = (first.note + "; " if first.note else "") + (
                f"added with {effect_label(second.name, second.joint)}: neither passes alone, together they do"
            )
            rep = refit(calibrate(df, path.current.model.with_effect(alone), "ridge"))
            _record_added(path, first, [c for c, _ in results], rep)
            winners = [(second, pair_model)]
        best, best_model = pick_winner(winners)
        close = [c for c, _ in winners if c is not best and c.gain_mm2 >= 0.8 * best.gain_mm2]
        if close:  # say so when the data hardly tells two candidates apart
            best.note = (
                (best.note + "; " if best.note else "")
                + "nearly as good: "
                + ", ".join(c.name + (f" j{c.joint}" if c.joint else "") for c in close)
            )
        phase = f"effect {len(best_model.effects)}: full refit with {effect_label(best.name, best.joint)}"
        base.progress(phase, 0, 1)
        rep = refit(calibrate(df, best_model, "ridge"))
        base.progress(phase, 1, 1)
        if close:
            path.ambiguities += _confounded(base, path, best, close, alpha)
        _record_added(path, best, [c for c, _ in results], rep)
        # Backward check: does every earlier effect still earn its place beside the new one?
        while len(path.effects) > 1:
            weakest = weakest_effect(path.current.model, path.prob, path.partitions, base.sigma2, alpha)
            if weakest is None:
                break
            idx, cand = weakest
            gone = path.current.model.effects[idx]
            reduced = replace(
                path.current.model, effects=[e for k, e in enumerate(path.current.model.effects) if k != idx]
            )
            refit(calibrate(df, reduced, "ridge"))
            label = "- " + effect_label(gone.family, gone.joint) + " (no longer needed)"
            path.stage_models.append((label, path.current.model))
            path.pending.append(
                {
                    "action": "removed",
                    "effect": {"name": gone.family, "joint": gone.joint},
                    "parameters": [],
                    "candidates": [cand],
                    "merged": [],
                    "correlations": [],
                    "summary": {},
                }
            )
    return path


def _keep_previous(
    base: Baseline,
    df: pd.DataFrame,
    path: _Path,
    previous: list[dict],
    alpha: float,
    families: tuple[str, ...] | None,
    max_effects: int,
) -> _Path:
    """The selection's path, or one that starts from the `previous` diagnosis' effects when that predicts
    held-out points better: more measurements must not leave a worse model than a refit of what was named
    before (a held-out test on new rows can be too weak to re-admit a true effect that the earlier
    diagnosis had, while dropping it leaves the geometry to absorb it). Both paths are judged on the rows
    inlier to either (a row both reject is a blunder for both; one only the other accepts is part of the
    evidence between them) and the same spatial partitions (the mean held-out squared error)."""
    physics = {(e.family, e.joint) for e in path.current.model.effects if physical(e)}  # in every path
    keys = tuple(k for k in map(_named, previous) if k not in physics)
    if set(keys) <= set(path.effects):
        return path
    other = _forward_selection(base, df, alpha, families, max_effects, banned=set(), start=keys)
    _settle_rivals(base, df, other, alpha)
    errors, prob = _shared_heldout_errors(base, path, other)
    gain, p_value = held_out_gain(errors[0] - errors[1], prob.pose)
    if gain <= 0 or set(other.effects) == set(path.effects):
        return path
    other.cautions.append(
        caution(
            "previous_effects_kept",
            effects=[{"name": n, "joint": j} for n, j in keys],
            dropped=[{"name": n, "joint": j} for n, j in keys if (n, j) not in path.effects],
            heldout_rms_mm=float(np.sqrt(np.mean(errors[0]))) * 1000.0,
            heldout_rms_kept_mm=float(np.sqrt(np.mean(errors[1]))) * 1000.0,
            p_value=p_value,
        )
    )
    return other


def _shared_heldout_errors(base: Baseline, a: _Path, b: _Path) -> tuple[list[np.ndarray], Problem]:
    """Each path's held-out squared errors per point on the rows inlier to either (a row both reject is a
    blunder for both; one only the other accepts is evidence between them) and the same spatial partitions:
    two paths whose models reject different rows are compared on the same points."""
    prob, partitions = base.rows_and_folds(a.current, a.current.outliers & b.current.outliers)
    errors = []
    for candidate in (a, b):
        model = candidate.current.model
        r, J = prob.evaluate(model)
        free = free_mask(model, prob)[0]
        errors.append(linear_fit_heldout(flatten_jacobian(J)[:, free], r, partitions)[1])
    return errors, prob


def _refit(base: Baseline, path: _Path, result: CalibrationResult) -> IdentifiabilityReport:
    """Make `result` the path's current model: its rows, folds and identifiable parameters follow it."""
    path.current = result
    path.prob, path.partitions = base.rows_and_folds(result)
    path.free, rep = free_mask(result.model, path.prob)
    return rep


def _record_added(
    path: _Path,
    added: Candidate,
    candidates: list[Candidate],
    rep: IdentifiabilityReport,
    label: str | None = None,
    **extra: Any,
) -> None:
    """The stage (`label`, by default '+ effect') and step of the effect just added, the last of the current
    model; `extra` goes into the step (a replacement's `action`, `replaces`, `rival_tests`)."""
    path.stage_models.append((label or "+ " + effect_label(added.name, added.joint), path.current.model))
    eff_index = len(path.current.model.effects) - 1
    eff = path.current.model.effects[eff_index]
    path.pending.append(
        {
            **extra,
            "effect": {"name": added.name, "joint": added.joint},
            "parameters": _effect_params(path.current, eff_index),
            "candidates": candidates,
            "merged": [d for d in rep.dropped if d["name"] in eff.param_names],
            "correlations": _correlations(path.current, path.prob, eff),
            "summary": eff.summary(path.prob.ctx, path.current.model.nominal),
        }
    )


# When no single candidate passes, the PAIR_POOL candidates most significant on the full fit are tried in
# pairs: two effects of one joint (gravity sag and backlash of joint 2, say) can each be half-imitated by the
# geometry and the other, so neither shows alone, while together they leave the noise floor.
PAIR_POOL = 4


def _pair_lookahead(
    base: Baseline, path: _Path, results: list[tuple[Candidate, CalibratedModel | None]], alpha: float
) -> tuple[Candidate, tuple[Candidate, CalibratedModel]] | None:
    """The best pair of this round's candidates that passes the screening's tests together (each test at a
    level shared with every pair tried), as (first, (second, linearised model with both)); None if none does."""
    pool = sorted(
        (c for c, _ in results if c.gain_mm2 > 0 and not c.note and c.p_chi2 < 1.0),
        key=lambda c: c.p_chi2,
    )[:PAIR_POOL]
    pairs = [(a, b) for i, a in enumerate(pool) for b in pool[i + 1 :]]
    if not pairs:
        return None
    base_fit = fit_plain(path.current.model, path.prob, path.free, iters=3)
    level = len(results) + len(pairs)
    screen = Screen(base_fit, path.prob, path.free, path.partitions, base.sigma2, alpha, level)
    singles = {}
    for c in pool:
        eff = make_effect(c.name, c.joint)
        if eff.prepare(base.full.ctx, base_fit.nominal):
            screen.test(eff)
            singles[(c.name, c.joint)] = screen.heldout_errors.get((c.name, c.joint))
    best = None
    for a, b in pairs:
        e_a, e_b = singles.get((a.name, a.joint)), singles.get((b.name, b.joint))
        if e_a is None or e_b is None:
            continue
        effects = [make_effect(c.name, c.joint) for c in (a, b)]
        if not all(e.prepare(base.full.ctx, base_fit.nominal) for e in effects):
            continue
        cand, model = screen.test(effects[1], effects[0])
        if not cand.passed or model is None:
            continue
        e_pair = screen.heldout_errors[group_key(*effects)]
        # each member must earn its place in the pair: the pair beats either alone on held-out points
        if any(held_out_gain(e_one - e_pair, path.prob.pose)[1] >= alpha / level for e_one in (e_a, e_b)):
            continue
        if best is None or cand.gain_mm2 > best[1][0].gain_mm2:
            best = (a, (cand, model))
    return best


def _settle_rivals(base: Baseline, df: pd.DataFrame, path: _Path, alpha: float) -> None:
    """Each added effect against the rivals of its round, in the final model (hil.analysis.rivals): a rival
    the data prefers replaces it (a step of its own); one the data does not separate from it is an open
    question. Every replacement re-checks from the start, at most once per effect."""
    for _ in range(len(path.current.model.effects) + 1):
        replaced = False
        for index, eff in enumerate(path.current.model.effects):
            key = (eff.family, eff.joint)
            round_of = next(
                (
                    i
                    for i in reversed(path.pending)
                    if i.get("action", "added") != "removed" and _named(i) == key
                ),
                None,
            )
            if round_of is None:
                continue
            tests, models = compare_with_rivals(
                path.current.model,
                index,
                rivals_in_round(round_of["candidates"], key),
                path.prob,
                base.full.ctx,
                path.partitions,
                base.sigma2,
                alpha,
            )
            better = [t for t in tests if t.verdict == "replace" and _named(t.rival) in models]
            if better:
                best = min(better, key=lambda t: t.p_rival_better)
                rival = _named(best.rival)
                rep = _refit(base, path, calibrate(df, models[rival], "ridge"))
                _record_added(
                    path,
                    next(c for c in round_of["candidates"] if (c.name, c.joint) == rival),
                    round_of["candidates"],
                    rep,
                    label=f"+ {effect_label(*rival)} for {effect_label(*key)}",
                    action="replaced",
                    replaces=best.chosen,
                    rival_tests=[t.to_dict() for t in tests],
                )
                path.ambiguities = [a for a in path.ambiguities if _named(a["chosen"]) != key]
                replaced = True
                break
            for t in tests:
                if t.verdict != "undecided":
                    continue
                pair = (_named(t.chosen), _named(t.rival))
                if any((_named(a["chosen"]), _named(a["confounded_with"])) == pair for a in path.ambiguities):
                    continue
                path.ambiguities.append(
                    {
                        "chosen": t.chosen,
                        "confounded_with": t.rival,
                        "chosen_gain_mm2": t.chosen_gain_mm2,
                        "p_chosen_better": t.p_chosen_better,
                        "refitted": True,
                    }
                )
        if not replaced:
            return


def _named(item: dict) -> tuple[str, int | None]:
    """(name, joint) of an effect given as {name, joint} or of a step entry holding one under 'effect'."""
    effect = item.get("effect", item)
    return effect["name"], effect["joint"]


def _confounded(base: Baseline, path: _Path, best: Candidate, close: list[Candidate], alpha: float) -> list:
    """Did the winner take the near runners-up's gain? Then the data cannot tell them apart."""
    after = Screen(path.current.model, path.prob, path.free, path.partitions, base.sigma2, alpha, 1)
    out = []
    for c in close:
        eff_c = make_effect(c.name, c.joint)
        eff_c.prepare(base.full.ctx, path.current.model.nominal)
        left = (after.test if base.screening == "batched" else after.test_refit)(eff_c)[0].gain_mm2
        if left < 0.25 * c.gain_mm2:
            out.append(
                {
                    "chosen": {"name": best.name, "joint": best.joint},
                    "confounded_with": {"name": c.name, "joint": c.joint},
                    "gain_before_mm2": c.gain_mm2,
                    "gain_left_mm2": left,
                }
            )
    return out


def _evaluate_stages(path: _Path, tell: Progress = quiet) -> tuple[list[dict], dict, list[Step]]:
    """Step 3: every stage's held-out error on the final rows and folds; a stage worse than the one
    before it is flagged (`worse_than_previous`)."""
    stages: list[dict] = []
    hist: dict[str, list[float]] = {}
    cv_by_stage: list[np.ndarray] = []
    for k, (label, m) in enumerate(path.stage_models):
        tell("held-out figures of every stage", k, len(path.stage_models))
        mfree = free_mask(m, path.prob)[0]
        if label.startswith("uncompensated"):
            mfree = registration(m, path.prob)
        cv = _cv_positions(m, mfree, path.prob, path.folds)
        cv_by_stage.append(cv)
        stage = _stage(label, "heldout", cv)
        if len(stages) > 1 and stage["rms_mm"] > stages[-1]["rms_mm"] * 1.0001:
            stage["worse_than_previous"] = True
        stages.append(stage)
        hist[label] = (np.linalg.norm(cv, axis=1) * 1000).tolist()
    tell("held-out figures of every stage", len(path.stage_models), len(path.stage_models))
    steps: list[Step] = []
    for k, info in enumerate(path.pending):
        before, after = cv_by_stage[path.first_step + k], cv_by_stage[path.first_step + k + 1]
        plot = {}
        if info.get("action", "added") in ("added", "replaced"):
            stage_model = path.stage_models[path.first_step + k + 1][1]
            eff_index = len(stage_model.effects) - 1
            disp = _effect_displacement(stage_model, path.prob, eff_index)
            norm = np.linalg.norm(disp, axis=1, keepdims=True)
            u = disp / np.where(norm > 0, norm, 1.0)
            drv_label, drv = stage_model.effects[eff_index].driver(path.prob.ctx, stage_model.nominal)
            plot = {
                "driver_label": drv_label,
                "driver": np.asarray(drv).tolist(),
                "residual_before_mm": (np.sum(before * u, axis=1) * 1000).tolist(),
                "residual_after_mm": (np.sum(after * u, axis=1) * 1000).tolist(),
            }
        steps.append(
            Step(heldout_before=error_stats(before), heldout_after=error_stats(after), plot=plot, **info)
        )
    path.cv_final = cv_by_stage[-1]
    return stages, hist, steps


def _verdict(
    base: Baseline,
    path: _Path,
    stages: list[dict],
    hist: dict,
    steps: list[Step],
    alpha: float,
    compare_maps: bool,
) -> DiagnosisReport:
    """Step 4: what is left (noise? structure a residual map predicts?) and every caution, as data."""
    final_model, prob, free = path.current.model, path.prob, path.free
    r_fit = prob.residuals(final_model)
    dof = max(r_fit.size - int(free.sum()), 1)
    ratio = float(np.sqrt(np.sum(r_fit**2) / dof / base.sigma2))
    p_excess = float(stats.chi2.sf(np.sum(r_fit**2) / base.sigma2, dof))
    excess = bool(p_excess < alpha and ratio > 1.1)
    if excess or compare_maps:
        map_report = _map_verdict(base, path, final_model, alpha)
    else:  # at the noise floor: nothing for a map to find
        map_report = {
            "candidates": {},
            "winner": None,
            "structured": False,
            "local": False,
            "note": "residual at the noise floor",
        }
    with_map = excess and map_report["structured"]  # a map that beats no map on the spatial folds
    if with_map:
        label = f"+ residual map ({map_report['winner']})"
        stages.append(_stage(label, "heldout", np.asarray(map_report["heldout_residual"])))
        hist[label] = (np.linalg.norm(map_report["heldout_residual"], axis=1) * 1000).tolist()
        final_model.residual_map = (
            make_map(map_report["winner"])
            .fit(prob.ctx.q, _p_base(final_model, prob), r_fit[:, :3], float(np.sqrt(base.sigma2)))
            .to_dict()
        )
    map_report.pop("heldout_residual", None)
    cautions = list(path.cautions)
    for st in stages:
        if st.get("worse_than_previous"):
            cautions.append(caution("stage_worse_than_previous", stage=st["stage"], rms_mm=st["rms_mm"]))
    for amb in path.ambiguities:
        cautions.append(
            caution("ambiguous_effects", chosen=amb["chosen"], confounded_with=amb["confounded_with"])
        )
    cautions += [caution("calibration_note", text=note) for note in [*base.ridge.notes, *base.notes]]
    final_model.info["diagnosis"] = {
        "effects_added": [s.effect for s in steps],
        "noise_floor_mm": base.noise.floor_mm,
    }
    residual = "excess" if excess else "floor"
    if with_map or (excess and map_report["local"]):
        residual = "structured" if with_map else "local"
    map_kind = map_report["local_winner"] if residual == "local" else map_report["winner"]
    return DiagnosisReport(
        model=final_model,
        calibration=base.calibration,
        noise=base.noise,
        stages=stages,
        steps=steps,
        unexplained_structure=residual in ("structured", "local"),
        verdict={"residual": residual, "ratio": ratio, "map": map_kind, "cautions": cautions},
        residual_map={**map_report, "excess_ratio": ratio, "p_excess": p_excess},
        histograms=hist,
        final_round=path.final_round,
        ambiguities=path.ambiguities,
    )


def _validate(
    report: DiagnosisReport, path: _Path, df: pd.DataFrame, df_val: pd.DataFrame, reregister: str
) -> None:
    """Every stage on the validation campaign (never used for fitting), with extrapolation warnings."""
    final_model = report.model
    cautions = report.verdict["cautions"]
    val = Problem.from_frame(final_model, df_val)
    models = list(path.stage_models)
    for label, m in models:
        stage = _stage(label, "validate", val.residuals(m))
        report.stages.append(stage)
        report.histograms[f"{label} [validate]"] = (np.linalg.norm(val.residuals(m), axis=1) * 1000).tolist()
    if final_model.residual_map is not None:
        r_val = val.residuals(final_model)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            corr = map_from_dict(final_model.residual_map).predict_raw(val.ctx.q, _p_base(final_model, val))
        report.stages.append(_stage(f"+ residual map ({report.verdict['map']})", "validate", r_val - corr))
    if reregister != "none":
        on = f"validate, {reregister} re-registered"
        for label, m in models[1:]:
            moved = reregister_model(m, df_val, tool=reregister == "base+tool")
            report.stages.append(_stage(label, on, Problem.from_frame(moved, df_val).residuals(moved)))
    held = [st["rms_mm"] for st in report.stages if st["on"] == "heldout"]
    valid = [st["rms_mm"] for st in report.stages if st["on"] == "validate"]
    if valid and valid[-1] > 1.5 * held[-1]:
        cautions.append(
            caution(
                "validation_unrepresented",
                validate_rms_mm=valid[-1],
                heldout_rms_mm=held[-1],
                reregistered=reregister != "none",
            )
        )
    geo = [st["rms_mm"] for st in report.stages if st["on"] == "validate" and st["stage"] == "kinematic"]
    if valid and geo and valid[-1] > geo[0] * 1.02:
        cautions.append(
            caution("validation_worse_than_geometric", final_rms_mm=valid[-1], geometric_rms_mm=geo[0])
        )
    cautions += extrapolation_warnings(df, df_val)


def caution(kind: str, **data: Any) -> dict:
    """One caution of the verdict, as data: `kind` names it, hil.analysis.report words it."""
    return {"kind": kind, **data}


def extrapolation_warnings(df: pd.DataFrame, df_val: pd.DataFrame) -> list[dict]:
    """Validation temperatures or joint ranges outside the training's (cautions): the model extrapolates."""
    out = []
    if "temperature_c" in df.columns and "temperature_c" in df_val.columns:
        lo, hi = float(df["temperature_c"].min()), float(df["temperature_c"].max())
        vlo, vhi = float(df_val["temperature_c"].min()), float(df_val["temperature_c"].max())
        if vlo < lo - 0.5 or vhi > hi + 0.5:
            out.append(caution("validation_temperatures_outside", validate_c=[vlo, vhi], training_c=[lo, hi]))
    q, qv = joints_rad(df), joints_rad(df_val)
    margin_deg = 5.0
    margin = np.deg2rad(margin_deg)
    outside = np.flatnonzero(
        (qv.min(axis=0) < q.min(axis=0) - margin) | (qv.max(axis=0) > q.max(axis=0) + margin)
    )
    if outside.size:
        out.append(
            caution("validation_joints_outside", joints=[int(j + 1) for j in outside], margin_deg=margin_deg)
        )
    return out


def run_record(robot: KinematicModel, frames: dict[str, pd.DataFrame | None]) -> dict:
    """What the report was made from: robot, each input (file, SHA-256, rows), date and software version."""
    import datetime
    import importlib.metadata

    try:
        version = importlib.metadata.version("hil")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    inputs = {}
    for role, df in frames.items():
        if df is None:
            continue
        inputs[role] = {
            "file": df.attrs.get("source"),
            "sha256": df.attrs.get("sha256"),
            "rows_in_file": df.attrs.get("rows_in_file", len(df)),
            "rows_used": len(df),
            "duplicate_rows": df.attrs.get("duplicate_rows", []),
        }
        temperatures = pd.to_numeric(
            df.get("temperature_c", pd.Series(dtype=float)), errors="coerce"
        ).dropna()
        if len(temperatures):  # what a thermal model was fitted on: compensation warns outside it
            inputs[role]["temperature_c_range"] = [float(temperatures.min()), float(temperatures.max())]
    return {
        "robot": robot.name,
        "inputs": inputs,
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": f"hil {version}",
    }


def _p_base(model: CalibratedModel, problem: Problem) -> np.ndarray:
    q_eff = problem.ctx.q + model.joint_offsets(problem.ctx)
    return tool_points_rows(model.kinematic, q_eff, model._row_tools(problem.smr))


def _map_verdict(base: Baseline, path: _Path, model: CalibratedModel, alpha: float) -> dict:
    """Does a residual map belong in the model? It does only if it beats no map on the spatial folds.

    A map becomes part of the model, and a model is used beyond the points it was fitted on (another
    campaign, the poses a user commands next), so the map is judged as every stage is: on blocks of the
    volume held out. A map that wins on random folds (interpolation between measured points) may still
    extrapolate worse than no map: on series B of the public UR10 campaigns an IDW grid map won on random
    folds (0.374 against no map's 0.403 mm) yet lost on spatial ones (0.505 against 0.444 mm), and on series C
    it left 0.818 mm where the model without it left 0.803 mm. When no map extrapolates, random folds then
    tell local structure (a map interpolates it: `local`) from a residual no map predicts at all.
    """
    prob, free = path.prob, path.free
    cv_spatial = path.cv_final if path.cv_final is not None else _cv_positions(model, free, prob, path.folds)
    out = _try_residual_maps(
        model, prob, cv_spatial, path.folds, base.noise, alpha, base.progress, "residual maps: spatial folds"
    )
    out.update({"folds": "spatial", "local": False, "local_winner": None})
    if out["structured"]:
        return out
    rfolds = prob.random_folds(base.n_folds, base.seed)
    cv_random = _cv_positions(model, free, prob, rfolds)
    interp = _try_residual_maps(
        model, prob, cv_random, rfolds, base.noise, alpha, base.progress, "residual maps: random folds"
    )
    out["interpolation"] = {"candidates": interp["candidates"], "no_map_rms_mm": interp["no_map_rms_mm"]}
    out["local"] = interp["structured"]
    out["local_winner"] = interp["winner"]
    return out


def _try_residual_maps(
    model: CalibratedModel,
    prob: Problem,
    cv_res: np.ndarray,
    folds: list[np.ndarray],
    noise: NoiseFloor,
    alpha: float,
    tell: Progress = quiet,
    phase: str = "residual maps: held-out comparison",
) -> dict:
    """Can a residual map predict the held-out residual `cv_res` (of `folds`)? The map kinds fitted on the
    other folds, each tested against no map (p_value: one-sided, poses counted once)."""
    q = prob.ctx.q
    p_base = _p_base(model, prob)
    sigma = float(np.sqrt(np.mean(noise.sigma_axis_m**2)))
    e0 = np.sum(cv_res**2, axis=1)
    table: dict[str, dict[str, Any]] = {}
    best = None
    for i, kind in enumerate(MAP_KINDS):
        tell(phase, i, len(MAP_KINDS))
        try:
            res = kfold_map_errors(kind, q, p_base, cv_res, sigma, folds)
        except Exception as exc:  # a map that cannot be built on this data (e.g. no grid) is skipped
            table[kind] = {"error": str(exc), "mode": MAP_MODES[kind]}
            continue
        p = held_out_gain(e0 - np.sum(res**2, axis=1), prob.pose)[1]
        table[kind] = {**error_stats(res), "p_value": p, "mode": MAP_MODES[kind]}
        if best is None or table[kind]["rms_mm"] < table[best]["rms_mm"]:
            best = kind
            best_res = res
    tell(phase, len(MAP_KINDS), len(MAP_KINDS))
    structured = best is not None and table[best]["p_value"] < alpha
    return {
        "candidates": table,
        "no_map_rms_mm": error_stats(cv_res)["rms_mm"],
        "winner": best,
        "structured": bool(structured),
        "heldout_residual": best_res if best is not None else cv_res,
    }
