"""Close the loop: calibrate, look at the residual, test candidate effects, add the one that helps, repeat.

Every fit and test uses every equation the data has: each SMR's position and, from a 6-DoF probe, its
orientation, each weighted by its noise (the tracker's MPE, the probe's stated angle noise; see
hil.analysis.calibration.solve.Problem); the held-out figures (mm) are of positions. A probe whose rotation residual
after the geometric fit is beyond its stated noise (ORIENTATION_SELECTION_FACTOR) refutes that weight: the
effects are then tested on positions only, and a caution says so. Several SMRs at one pose are
one sample of the pose's error (they share its fold and count once in the tests).

Selection rule for each round (every candidate from `hil.model.effects` the data could reveal):
1. add the candidate to the current model and re-run the identifiability analysis on the joint
   (geometry + effects) Jacobian, so coefficients the data cannot separate from the geometry are merged;
2. k-fold cross-validation on blocks of the workspace (default 5 folds, the same for every candidate;
   CV_REPEATS partitions, each point's held-out squared error averaged over them; the poses of a
   single-joint sweep dealt to the folds in turn, hil.analysis.calibration.folds.campaign_folds): each fold refits all
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
fitted with the material's coefficient as its prior (hil.model.effects.material_expansion); data that
contradict the material drop the prior, data that find no growth hold it at zero (`material_decision`), and
the report gives the fitted coefficient beside the material's and calls it found, assumed or rejected
(`thermal_summary`). So is the joints' yield
under gravity when the robot file gives the links' masses: one compliance per joint that carries a gravity
torque, the torque computed from the masses, fitted with a prior centred on a rigid joint
(hil.model.effects.gravity_physics); a yield the data carry but do not find stays only while it predicts
held-out points better than a rigid joint (`yields_no_better`); the report gives each joint's stiffness and
its standing (`gravity_summary`). So is the tracker's scale when the campaign records the tracker's air
temperature and it stays put while the recorded temperature rises (a hand-entered air, a stuck weather
station: hil.analysis.diagnosis.physics_terms.stuck_air): driven by the recorded temperature, fitted with a
prior on how much of that rise the real air followed (hil.model.effects.stuck_air_tracker_scale), held at
zero where the data find no scale (`tracker_air_decision`), reported found, assumed or rejected with a
caution in the user's terms (`tracker_air_summary`); never as the arm's growth. The residual left is
then tested against the noise floor; if it is larger and a residual map predicts it on held-out blocks of the
volume (the spatial folds: better than no map, p < alpha), the report says structure remains that no
candidate explains and adds the map as a fallback stage. A map that only interpolates (wins on random folds,
not on spatial ones) is not added: the verdict calls the structure local.
"""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from hil.analysis.calibration.blas_threads import one_blas_thread
from hil.analysis.calibration.noise_floor import TRACKER_MPE_M, NoiseFloor
from hil.analysis.calibration.solve import CalibrationResult, Problem, confounded_note, confounded_pairs
from hil.analysis.calibration.solve import reregister as reregister_model
from hil.analysis.diagnosis.baseline import (
    Baseline,
    PhaseProgress,
    baseline_fit,
    error_stats,
    free_mask,
    quiet,
    registration,
)
from hil.analysis.diagnosis.cautions import (
    AmbiguousEffects,
    CalibrationNote,
    Caution,
    StageWorseThanPrevious,
    ThermalPriorContradicted,
    TrackerAirStuck,
    ValidationJointsOutside,
    ValidationTemperaturesOutside,
    ValidationUnrepresented,
    ValidationWorseThanGeometric,
)
from hil.analysis.diagnosis.drift_monitor import reference_drift
from hil.analysis.diagnosis.evidence import evidence
from hil.analysis.diagnosis.intervals import (
    fit_spread,
    heldout_coverage,
    validation_coverage,
    validation_orientation_coverage,
)
from hil.analysis.diagnosis.physics_check import yields_no_better
from hil.analysis.diagnosis.physics_terms import (
    ASSUMED,
    FOUND,
    gravity_summary,
    material_decision,
    stuck_air,
    thermal_summary,
    tracker_air_decision,
    tracker_air_summary,
)
from hil.analysis.diagnosis.questions import ConfoundedParameters, Question, open_questions
from hil.analysis.diagnosis.screening import Candidate, effect_label, held_out_gain
from hil.analysis.diagnosis.selection import (
    SelectionPath,
    Step,
    StepAction,
    cv_positions,
    effect_displacement,
    keep_previous,
    select_effects,
    settle_rivals,
)
from hil.data.dataset import drop_duplicate_rows, has_orientation, joints_rad
from hil.geometry.kinematics import KinematicModel, tool_points
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import (
    Effect,
    material_growth,
    physical,
    stuck_air_scale,
    yields_against_gravity,
)
from hil.model.residual_maps import MAP_KINDS, MAP_MODES, kfold_map_errors, make_map, map_from_dict

# The probability of the intervals whose coverage the report shows.
INTERVAL_PROBABILITY = 0.95


@dataclass
class DiagnosisReport:
    model: CalibratedModel
    calibration: dict  # both solvers' summaries
    noise: NoiseFloor
    stages: list[dict]
    steps: list[Step]
    unexplained_structure: bool
    verdict: dict  # residual ("floor" | "excess" | "local" | "structured"), ratio, map, cautions (records)
    residual_map: dict | None = None
    histograms: dict = field(default_factory=dict)  # stage -> held-out error norms (mm)
    final_round: list[Candidate] = field(default_factory=list)
    ambiguities: list[dict] = field(default_factory=list)  # effects this data could not tell apart
    undecided: list[Question] = field(
        default_factory=list
    )  # open questions (hil.analysis.diagnosis.questions)
    plan: dict | None = None  # the proposed measurements' groups (hil.analysis.design.plan.Proposal.to_dict)
    run: dict = field(default_factory=dict)  # robot, input files (hash, rows), date, software version
    thermal: dict | None = None  # the material's thermal growth, fitted against its prior (`thermal_summary`)
    # the joints' yield from the link masses (`gravity_summary`)
    gravity: list[dict] = field(default_factory=list)
    drift: dict | None = (
        None  # reference poses re-measured (hil.analysis.diagnosis.drift_monitor.reference_drift)
    )
    # the tracker's scale from an air reading that stayed put (`tracker_air_summary`)
    tracker_air: dict | None = None
    # the 95 % prediction intervals' coverage (hil.analysis.diagnosis.intervals.Coverage, held-out, validate)
    intervals: list[dict] = field(default_factory=list)

    @property
    def effects_added(self) -> list[dict]:
        """The effects the data found, in the order the final model holds them (the verdict's "Added"): every
        effect the selection added, and a physics term (the material's growth, a joint's gravity yield from
        the link masses, the tracker's scale from a stuck air reading) only where `thermal`, `gravity` or
        `tracker_air` calls it found."""
        return [
            {"name": e.family, "joint": e.joint} for e in self.model.effects if self._standing(e) == FOUND
        ]

    @property
    def effects_assumed(self) -> list[dict]:
        """The physics terms the final model holds on their prior rather than on the data ({name, joint,
        shift_mm}: how much each moves the prediction on the training rows, RMS mm)."""
        out = []
        for e in self.model.effects:
            summary = self._summary(e)
            if summary is not None and summary["standing"] == ASSUMED:
                out.append({"name": e.family, "joint": e.joint, "shift_mm": summary["shift_mm"]})
        return out

    def _summary(self, e: Effect) -> dict | None:
        """The physics summary (`thermal` or a `gravity` entry) of `e`; None for a selected effect."""
        if not physical(e):
            return None
        if material_growth(e):
            return self.thermal
        if stuck_air_scale(e):
            return self.tracker_air
        return next((g for g in self.gravity if g["joint"] == e.joint), None)

    def _standing(self, e: Effect) -> str:
        summary = self._summary(e)
        if not physical(e):
            return FOUND
        return summary["standing"] if summary is not None else ASSUMED

    @property
    def noise_floor_mm(self) -> float:
        return self.noise.floor_mm

    def to_dict(self) -> dict:
        return {
            "effects_added": self.effects_added,
            "effects_assumed": self.effects_assumed,
            "stages": self.stages,
            "unexplained_structure": self.unexplained_structure,
            "noise_floor_mm": self.noise.floor_mm,
            "noise_floor_method": self.noise.method,
            "verdict": {**self.verdict, "cautions": [c.to_dict() for c in self.verdict["cautions"]]},
            "steps": [s.to_dict() for s in self.steps],
            "final_round_candidates": [c.to_dict() for c in self.final_round],
            "ambiguities": self.ambiguities,
            "undecided": [q.to_dict() for q in self.undecided],
            "plan": self.plan,
            "thermal": self.thermal,
            "gravity": self.gravity,
            "tracker_air": self.tracker_air,
            "drift": self.drift,
            "intervals": self.intervals,
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


@dataclass(frozen=True)
class DiagnosisOptions:
    """How `run_diagnosis` fits, selects and judges.

    `folds` spatial folds (split with `seed`) for the held-out figures; `alpha` the selection's
    significance; `families` the candidate effects (None: all) and `max_effects` the most it adds.
    `repeatability_m`, `tool_guess_m` and `tracker_mpe_m` go to the baseline fit. `compare_maps` runs the
    k-fold residual-map comparison (IDW / SVR / GP) even when the residual is at the noise floor.
    `reregister_validation` ("none", "base", "base+tool") refits the base frame (and tool) of every stage
    on the validation campaign first, for a campaign taken from another tracker placement; the report then
    shows both. `screening` "batched" judges a round's candidates from one shared factorisation
    (hil.analysis.diagnosis.screening); "refit" fits each candidate on its own (the slow reference the
    batched path reproduces).
    """

    folds: int = 5
    alpha: float = 1e-3
    seed: int = 0
    families: tuple[str, ...] | None = None
    max_effects: int = 15
    repeatability_m: float = 0.0
    tool_guess_m: np.ndarray | None = None
    tracker_mpe_m: tuple[float, float] = TRACKER_MPE_M
    compare_maps: bool = False
    reregister_validation: str = "none"
    screening: str = "batched"


def run_diagnosis(
    df: pd.DataFrame,
    robot: str | KinematicModel,
    df_validate: pd.DataFrame | None = None,
    options: DiagnosisOptions = DiagnosisOptions(),
    progress: PhaseProgress | None = None,
    previous_effects: list[dict] | None = None,
) -> DiagnosisReport:
    """The whole loop on a training dataset (and an optional validation dataset never used for fitting).

    Named steps: baseline fit, forward selection (candidate screening each round), stage evaluation,
    verdict, as `options` says. `progress(phase, done, total)` is called as the work advances (the CLI
    draws it with an ETA). `previous_effects` ({name, joint}, the effects the diagnosis of an earlier part
    of this campaign named, as an active loop's round has): when the selection here drops any of them, a
    selection that starts from them is run too and the one whose model predicts held-out points better is
    kept (`keep_previous`): a round's measurements must not make the model worse.

    Held-out figures of every stage are computed at the end on the same rows and spatial folds: all
    points except those the final model rejects as outliers.
    """
    o = options
    alpha, families, max_effects, screening = o.alpha, o.families, o.max_effects, o.screening
    reregister_validation = o.reregister_validation
    if screening not in ("batched", "refit"):
        raise ValueError(f"screening '{screening}': use batched or refit")
    if reregister_validation not in ("none", "base", "base+tool"):
        raise ValueError(f"reregister_validation '{reregister_validation}': use none, base or base+tool")
    df = drop_duplicate_rows(df, "training data")  # copies would count twice in every test
    with one_blas_thread():  # small dense problems: threads only contend
        fit_args = (df, robot, o.folds, o.seed, o.repeatability_m, o.tool_guess_m, o.tracker_mpe_m, progress)
        base, path = _settle_physics(df, fit_args, o)
        settle_rivals(base, df, path, alpha)
        if previous_effects:
            path = keep_previous(base, df, path, previous_effects, alpha, families, max_effects)
        stages, hist, steps = _evaluate_stages(path, base.progress)
        report = _verdict(base, path, stages, hist, steps, alpha, o.compare_maps)
        report.thermal = thermal_summary(path.current, path.prob, alpha)
        report.gravity = gravity_summary(path.current, path.prob, alpha)
        report.tracker_air = tracker_air_summary(path.current, path.prob, stuck_air(df), alpha)
        if report.tracker_air is not None:
            report.verdict["cautions"].append(tracker_air_caution(report.tracker_air))
        if report.thermal and report.thermal["prior_contradicted"]:
            report.verdict["cautions"].append(
                ThermalPriorContradicted(
                    data_per_k=report.thermal.get("data_per_k", report.thermal["fitted_per_k"]),
                    material_per_k=report.thermal["material_per_k"],
                    standing=report.thermal["standing"],
                )
            )
        report.drift = reference_drift(df)
        noise_m2 = float(np.mean(np.asarray(base.noise.sigma_axis_m) ** 2))
        tell = base.progress
        tell("prediction intervals", 0, 1)
        spread = fit_spread(path.current, path.free, path.prob, path.folds, noise_m2, path.cv_final)
        assumed = [effect_label(e["name"], e["joint"]) for e in report.effects_assumed]  # section 1's rule
        report.model.spread = replace(spread, assumed_effects=assumed)
        if spread.orientation is None and has_orientation(df):
            report.model.spread = replace(
                report.model.spread,
                orientation_reason="the probe's orientations scatter beyond their stated noise, so the "
                "diagnosis left them out of its fit and measured no orientation spread",
            )
        tell("prediction intervals", 1, 1)
        report.intervals = [heldout_coverage(report.model.spread, INTERVAL_PROBABILITY).to_dict()]
        if df_validate is not None:
            report.intervals.append(
                validation_coverage(report.model, df_validate, INTERVAL_PROBABILITY).to_dict()
            )
            angles = validation_orientation_coverage(report.model, df_validate, INTERVAL_PROBABILITY)
            if angles is not None:  # a 6-DoF probe's orientations: their own intervals' coverage
                report.intervals.append(angles.to_dict())
            _validate(report, path, df, df_validate, reregister_validation)
        report.run = run_record(base.nominal.nominal, {"training": df, "validation": df_validate})
        report.undecided = undecided_questions(df, path, alpha, float(np.sqrt(base.sigma2)))
        report.verdict["cautions"] = without_decided_pairs(report.verdict["cautions"], report.undecided)
        return report


def _settle_physics(df: pd.DataFrame, fit_args: tuple, o: DiagnosisOptions) -> tuple[Baseline, SelectionPath]:
    """The baseline fit and the selection, repeated until the physics terms stand as the data have them: the
    data contradict the material's growth or find none (the recorded temperature follows the air, not the
    arm), or a joint's gravity term yields against gravity once the selected effects are in, or predicts no
    better than a rigid joint, or the data drop or reject the tracker's scale from a stuck air reading: select
    again with those terms as the data have them and those joints held rigid (and again if that selection
    turns another joint)."""
    alpha, families, max_effects = o.alpha, o.families, o.max_effects
    base = baseline_fit(*fit_args)
    base.screening = o.screening
    path = select_effects(base, df, alpha, families, max_effects)
    decided: dict[str, Effect] = {}  # physics terms as the data have them, by label
    for _ in range(base.nominal.nominal.n_joints + 3):  # each pass settles a physics term or more joints
        terms = [material_decision(path.current, path.prob, alpha)]
        terms.append(tracker_air_decision(path.current, path.prob, alpha))
        against = {
            e.joint: float(e.params[0]) for e in path.current.model.effects if yields_against_gravity(e)
        }
        if all(t is None for t in terms) and not against:
            # the yields the data carry but do not find stay only while they beat a rigid joint
            against = yields_no_better(df, path, alpha)
            if not against:
                break
        decided.update({t.label: t for t in terms if t is not None})
        held = {**base.held_gravity, **against}
        base = baseline_fit(*fit_args, decided=tuple(decided.values()), hold_gravity=held)
        base.screening = o.screening
        path = select_effects(base, df, alpha, families, max_effects)
    return base, path


def tracker_air_caution(summary: dict) -> TrackerAirStuck:
    """The caution of a tracker whose air reading stayed put (`tracker_air_summary`'s figures)."""
    return TrackerAirStuck(
        air_c=summary["air_c"],
        start_c=summary["temperature_start_c"],
        end_c=summary["temperature_end_c"],
        span_k=summary["span_k"],
        prior_per_k=summary["prior_per_k"],
        prior_std_per_k=summary["prior_std_per_k"],
        fitted_per_k=summary["fitted_per_k"],
        std_per_k=summary["std_per_k"],
        data_per_k=summary["data_per_k"],
        data_std_per_k=summary["data_std_per_k"],
        standing=summary["standing"],
    )


def undecided_questions(
    df: pd.DataFrame, path: SelectionPath, alpha: float, sigma_m: float
) -> list[Question]:
    """What the campaign leaves undecided (hil.analysis.diagnosis.questions); a statistical question whose evidence
    already passes hil.analysis.design.plan's threshold is decided and left out."""
    pairs = confounded_pairs(path.current, path.prob)
    found = open_questions(df, path.final_round, path.ambiguities, pairs, alpha, path.current.model.effects)
    weighed = {
        id(ev["question"]): replace(ev["question"], evidence_z=ev["evidence_z"], decisive_z=ev["decisive_z"])
        for ev in evidence(df, path.current.model, found, sigma_m)
    }
    out = [weighed.get(id(q), q) for q in found]
    return [q for q in out if q.evidence_z is None or q.decisive_z is None or q.evidence_z < q.decisive_z]


def without_decided_pairs(cautions: list[Caution], undecided: list[Question]) -> list[Caution]:
    """The cautions less the geometric calibration's notes on confounded pairs that the final diagnosis does
    not leave open (its evidence separates them, or the final model no longer confounds them): the report
    must not call a pair unreliable that the open questions call decided."""
    open_pairs = {frozenset(q.parameters) for q in undecided if isinstance(q, ConfoundedParameters)}

    def decided(c: Caution) -> bool:
        return isinstance(c, CalibrationNote) and c.pair is not None and frozenset(c.pair) not in open_pairs

    return [c for c in cautions if not decided(c)]


def calibration_notes(result: CalibrationResult) -> list[CalibrationNote]:
    """A geometric fit's notes as cautions, in its order; a note on a pair the fit confounds carries the pair."""
    pairs = {confounded_note(a, b, c): (a, b) for a, b, c in result.confounded}
    return [CalibrationNote(text=note, pair=pairs.get(note)) for note in result.notes]


def _evaluate_stages(path: SelectionPath, tell: PhaseProgress = quiet) -> tuple[list[dict], dict, list[Step]]:
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
        cv = cv_positions(m, mfree, path.prob, path.folds)
        cv_by_stage.append(cv)
        stage = _stage(label, "heldout", cv)
        if len(stages) > 1 and stage["rms_mm"] > stages[-1]["rms_mm"] * 1.0001:
            stage["worse_than_previous"] = True
        stages.append(stage)
        hist[label] = (np.linalg.norm(cv, axis=1) * 1000).tolist()
    tell("held-out figures of every stage", len(path.stage_models), len(path.stage_models))
    steps: list[Step] = []
    for k, taken in enumerate(path.pending):
        before, after = cv_by_stage[path.first_step + k], cv_by_stage[path.first_step + k + 1]
        plot = {}
        if taken.action is not StepAction.REMOVED:
            stage_model = path.stage_models[path.first_step + k + 1][1]
            eff_index = len(stage_model.effects) - 1
            disp = effect_displacement(stage_model, path.prob, eff_index)
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
            replace(taken, heldout_before=error_stats(before), heldout_after=error_stats(after), plot=plot)
        )
    path.cv_final = cv_by_stage[-1]
    return stages, hist, steps


def _verdict(
    base: Baseline,
    path: SelectionPath,
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
            cautions.append(StageWorseThanPrevious(stage=st["stage"], rms_mm=st["rms_mm"]))
    for amb in path.ambiguities:
        cautions.append(AmbiguousEffects(chosen=amb["chosen"], confounded_with=amb["confounded_with"]))
    cautions += calibration_notes(base.ridge) + [CalibrationNote(text=note) for note in base.notes]
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
    report: DiagnosisReport, path: SelectionPath, df: pd.DataFrame, df_val: pd.DataFrame, reregister: str
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
            ValidationUnrepresented(
                validate_rms_mm=valid[-1],
                heldout_rms_mm=held[-1],
                reregistered=reregister != "none",
            )
        )
    geo = [st["rms_mm"] for st in report.stages if st["on"] == "validate" and st["stage"] == "kinematic"]
    if valid and geo and valid[-1] > geo[0] * 1.02:
        cautions.append(ValidationWorseThanGeometric(final_rms_mm=valid[-1], geometric_rms_mm=geo[0]))
    cautions += extrapolation_warnings(df, df_val)


def extrapolation_warnings(df: pd.DataFrame, df_val: pd.DataFrame) -> list[Caution]:
    """Validation temperatures or joint ranges outside the training's (cautions): the model extrapolates."""
    out: list[Caution] = []
    if "temperature_c" in df.columns and "temperature_c" in df_val.columns:
        lo, hi = float(df["temperature_c"].min()), float(df["temperature_c"].max())
        vlo, vhi = float(df_val["temperature_c"].min()), float(df_val["temperature_c"].max())
        if vlo < lo - 0.5 or vhi > hi + 0.5:
            out.append(ValidationTemperaturesOutside(validate_c=[vlo, vhi], training_c=[lo, hi]))
    q, qv = joints_rad(df), joints_rad(df_val)
    margin_deg = 5.0
    margin = np.deg2rad(margin_deg)
    outside = np.flatnonzero(
        (qv.min(axis=0) < q.min(axis=0) - margin) | (qv.max(axis=0) > q.max(axis=0) + margin)
    )
    if outside.size:
        out.append(ValidationJointsOutside(joints=[int(j + 1) for j in outside], margin_deg=margin_deg))
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
    station: dict = {}
    for role, df in frames.items():
        if df is None:
            continue
        station = station or dict(df.attrs.get("station") or {})
        inputs[role] = {
            "file": df.attrs.get("source"),
            "sha256": df.attrs.get("sha256") or content_sha256(df),
            "rows_in_file": df.attrs.get("rows_in_file", len(df)),
            "rows_used": len(df),
            "duplicate_rows": df.attrs.get("duplicate_rows", []),
        }
        temperatures = pd.to_numeric(
            df.get("temperature_c", pd.Series(dtype=float)), errors="coerce"
        ).dropna()
        if len(temperatures):  # what a thermal model was fitted on: compensation warns outside it
            inputs[role]["temperature_c_range"] = [float(temperatures.min()), float(temperatures.max())]
    import platform

    import scipy

    record = {
        "robot": robot.name,
        "inputs": inputs,
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": f"hil {version} (Python {platform.python_version()}, numpy {np.__version__}, scipy "
        f"{scipy.__version__}, pandas {pd.__version__})",
    }
    if station:
        record["station"] = station
    return record


def content_sha256(df: pd.DataFrame) -> str:
    """SHA-256 of a frame's rows as CSV text: the identity of data that came from no file (a campaign's rows,
    a frame built in Python), so a report can still be traced to exactly the rows it was made from."""
    return hashlib.sha256(df.to_csv(index=False).encode()).hexdigest()


def _p_base(model: CalibratedModel, problem: Problem) -> np.ndarray:
    q_eff = problem.ctx.q + model.joint_offsets(problem.ctx)
    return tool_points(model.kinematic, q_eff, model._row_tools(problem.smr))


def _map_verdict(base: Baseline, path: SelectionPath, model: CalibratedModel, alpha: float) -> dict:
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
    cv_spatial = path.cv_final if path.cv_final is not None else cv_positions(model, free, prob, path.folds)
    out = _try_residual_maps(
        model, prob, cv_spatial, path.folds, base.noise, alpha, base.progress, "residual maps: spatial folds"
    )
    out.update({"folds": "spatial", "local": False, "local_winner": None})
    if out["structured"]:
        return out
    rfolds = prob.random_folds(base.n_folds, base.seed)
    cv_random = cv_positions(model, free, prob, rfolds)
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
    tell: PhaseProgress = quiet,
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
