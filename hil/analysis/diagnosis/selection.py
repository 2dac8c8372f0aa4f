"""Step 2 of a diagnosis: forward selection of the effects the data prove. Each round screens every candidate
against the current model (hil.analysis.diagnosis.screening), re-judges those the rejected rows may hide
(hil.analysis.diagnosis.reclaim), adds the best passing one and refits, drops an earlier effect a later one made
redundant, settles pairs and rivals; a second selection without the first choice, or from the previous
round's effects, is kept when it predicts better on the same held-out rows.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import pandas as pd

from hil.analysis.calibration.identifiability import IdentifiabilityReport
from hil.analysis.calibration.solve import (
    CalibrationResult,
    Problem,
    calibrate,
    flatten_jacobian,
    parameter_correlations,
)
from hil.analysis.diagnosis.baseline import Baseline, error_stats, fit_plain, free_mask
from hil.analysis.diagnosis.cautions import Caution, FirstChoiceSetAside, PreviousEffectsKept
from hil.analysis.diagnosis.reclaim import reclaimed
from hil.analysis.diagnosis.rivals import compare_with_rivals, rivals_in_round
from hil.analysis.diagnosis.screening import (
    EXTRAPOLATING_FAMILIES,
    Candidate,
    Screen,
    carried_over,
    cv_residuals,
    effect_label,
    group_key,
    held_out_gain,
    linear_fit_heldout,
    pick_winner,
    predicts_along_joint,
    weakest_effect,
)
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import Effect, candidate_effects, make_effect, physical


class StepAction(enum.StrEnum):
    """What a selection step did to the model (its `action` in report.json)."""

    ADDED = "added"
    REMOVED = "removed"  # a later effect made it redundant
    REPLACED = "replaced"  # a rival the data prefers took its place


@dataclass(frozen=True, kw_only=True)
class Step:
    """One step of the selection: the effect it added, removed or replaced with, and why. The selection
    records it; the held-out figures of its stage and the plot are filled in once every stage is evaluated
    (hil.analysis.diagnosis.pipeline)."""

    effect: dict  # {name, joint}
    parameters: list[dict]  # {name, value, std}
    heldout_before: dict = field(default_factory=dict)
    heldout_after: dict = field(default_factory=dict)
    candidates: list[Candidate]
    merged: list[dict]  # identifiability notes for the effect's coefficients
    correlations: list[dict]  # strongest correlation of each effect coefficient with a geometric parameter
    plot: dict = field(default_factory=dict)  # driver label/values, residual along the effect before/after
    action: StepAction = StepAction.ADDED
    summary: dict = field(default_factory=dict)  # physical figures: deflection, amplitude, gap, ppm/K
    replaces: dict | None = None  # the effect a replacing step took out ({name, joint})
    rival_tests: list[dict] = field(
        default_factory=list
    )  # hil.analysis.diagnosis.rivals' comparisons behind it

    def title(self) -> str:
        """'gravity_compliance joint 2', 'removed backlash joint 4', 'cyclic joint 2 (replaces cyclic joint 3)'."""
        named = self.effect["name"] + (f" joint {self.effect['joint']}" if self.effect["joint"] else "")
        if self.action is StepAction.REMOVED:
            return "removed " + named
        if self.action is StepAction.REPLACED and self.replaces:
            gone = self.replaces["name"] + (
                f" joint {self.replaces['joint']}" if self.replaces["joint"] else ""
            )
            return f"{named} (replaces {gone})"
        return named

    def to_dict(self) -> dict:
        """The step as report.json holds it: its fields in declared order, the action and candidates as data."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["action"] = self.action.value
        d["candidates"] = [c.to_dict() for c in self.candidates]
        return d


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
        # the key returns a float of its own: through numpy's abs overloads mypy spent a second on this line
        k = max(geo, key=lambda k: abs(float(corr[i, k])))
        out.append({"coefficient": nm, "parameter": fnames[k], "correlation": float(corr[i, k])})
    return out


def effect_displacement(model: CalibratedModel, problem: Problem, index: int) -> np.ndarray:
    """Tracker-frame displacement (N, 3) that effect `index` contributes (model with minus without)."""
    without = replace(model, effects=[e for i, e in enumerate(model.effects) if i != index])
    problem.ctx.p_flange_tool = model._row_tools(problem.smr)
    return model.predict_ctx(problem.ctx) - without.predict_ctx(problem.ctx)


def select_effects(
    base: Baseline, df: pd.DataFrame, alpha: float, families: tuple[str, ...] | None, max_effects: int
) -> SelectionPath:
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
                FirstChoiceSetAside(
                    effect={"name": first[0], "joint": first[1]},
                    heldout_rms_mm=rms_mm[0],
                    heldout_rms_without_mm=rms_mm[1],
                )
            )
            path = other
        else:
            break
    return path


@dataclass
class SelectionPath:
    """Step 2's outcome: the stages one forward selection went through."""

    current: CalibrationResult
    prob: Problem
    partitions: list[list[np.ndarray]]  # spatial folds, several draws (see CV_REPEATS)
    free: np.ndarray
    stage_models: list[tuple[str, CalibratedModel]]
    pending: list[Step]  # the steps taken, without their held-out figures (filled in by step 3)
    ambiguities: list[dict]
    final_round: list[Candidate]
    banned: set
    cautions: list[Caution] = field(default_factory=list)
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
        return error_stats(cv_positions(self.current.model, self.free, self.prob, self.folds))["rms_mm"]


# The stage that adds the joints' gravity yield computed from the link masses (physics) to the geometric fit.
GRAVITY_STAGE = "+ gravity yield (link masses)"


def cv_positions(
    model: CalibratedModel, free: np.ndarray, prob: Problem, folds: list[np.ndarray]
) -> np.ndarray:
    """Held-out position residuals (N, 3): a 6-DoF probe's rotations take part in every fit, while the
    figures (mm) are of positions."""
    return cv_residuals(model, free, prob, folds)[:, :3]


def _excess_ratio(model: CalibratedModel, base: Baseline, path: SelectionPath) -> float:
    """Residual sigma over the noise sigma on the path's rows."""
    r = path.prob.residuals(model)
    return float(np.sqrt(np.sum(r**2) / max(r.size - int(path.free.sum()), 1) / base.sigma2))


def _screen_round(
    base: Baseline,
    path: SelectionPath,
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
    path: SelectionPath,
    sigma2: float,
    alpha: float,
    cand: Candidate,
    model: CalibratedModel | None,
) -> tuple[Candidate, CalibratedModel | None]:
    """A passing candidate whose claim reaches beyond the sampled arc of its joint (a scale) fails unless it
    also predicts each half of the joint's range from the other (hil.analysis.diagnosis.screening.predicts_along_joint)."""
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
) -> SelectionPath:
    """Step 2: add the best passing candidate, refit, drop effects a later one made redundant; repeat.
    `start`: effects (family, joint) put into the model first, one stage each, without a test."""
    current = base.ridge
    prob, partitions = base.rows_and_folds(current)
    path = SelectionPath(
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
            continue  # this campaign does not offer it (hil.model.effects' conditions)
        rep = refit(calibrate(df, path.current.model.with_effect(carried), "ridge"))
        cand = carried_over(name, joint, len(carried.params))
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
                Step(
                    action=StepAction.REMOVED,
                    effect={"name": gone.family, "joint": gone.joint},
                    parameters=[],
                    candidates=[cand],
                    merged=[],
                    correlations=[],
                    summary={},
                )
            )
    return path


def keep_previous(
    base: Baseline,
    df: pd.DataFrame,
    path: SelectionPath,
    previous: list[dict],
    alpha: float,
    families: tuple[str, ...] | None,
    max_effects: int,
) -> SelectionPath:
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
    settle_rivals(base, df, other, alpha)
    errors, prob = _shared_heldout_errors(base, path, other)
    gain, p_value = held_out_gain(errors[0] - errors[1], prob.pose)
    if gain <= 0 or set(other.effects) == set(path.effects):
        return path
    other.cautions.append(
        PreviousEffectsKept(
            effects=[{"name": n, "joint": j} for n, j in keys],
            dropped=[{"name": n, "joint": j} for n, j in keys if (n, j) not in path.effects],
            heldout_rms_mm=float(np.sqrt(np.mean(errors[0]))) * 1000.0,
            heldout_rms_kept_mm=float(np.sqrt(np.mean(errors[1]))) * 1000.0,
            p_value=p_value,
        )
    )
    return other


def _shared_heldout_errors(
    base: Baseline, a: SelectionPath, b: SelectionPath
) -> tuple[list[np.ndarray], Problem]:
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


def _refit(base: Baseline, path: SelectionPath, result: CalibrationResult) -> IdentifiabilityReport:
    """Make `result` the path's current model: its rows, folds and identifiable parameters follow it."""
    path.current = result
    path.prob, path.partitions = base.rows_and_folds(result)
    path.free, rep = free_mask(result.model, path.prob)
    return rep


def _record_added(
    path: SelectionPath,
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
        Step(
            effect={"name": added.name, "joint": added.joint},
            parameters=_effect_params(path.current, eff_index),
            candidates=candidates,
            merged=[d for d in rep.dropped if d["name"] in eff.param_names],
            correlations=_correlations(path.current, path.prob, eff),
            summary=eff.summary(path.prob.ctx, path.current.model.nominal),
            **extra,
        )
    )


# When no single candidate passes, the PAIR_POOL candidates most significant on the full fit are tried in
# pairs: two effects of one joint (gravity sag and backlash of joint 2, say) can each be half-imitated by the
# geometry and the other, so neither shows alone, while together they leave the noise floor.
PAIR_POOL = 4


def _pair_lookahead(
    base: Baseline, path: SelectionPath, results: list[tuple[Candidate, CalibratedModel | None]], alpha: float
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


def settle_rivals(base: Baseline, df: pd.DataFrame, path: SelectionPath, alpha: float) -> None:
    """Each added effect against the rivals of its round, in the final model (hil.analysis.diagnosis.rivals): a rival
    the data prefers replaces it (a step of its own); one the data does not separate from it is an open
    question. Every replacement re-checks from the start, at most once per effect."""
    for _ in range(len(path.current.model.effects) + 1):
        replaced = False
        for index, eff in enumerate(path.current.model.effects):
            key = (eff.family, eff.joint)
            round_of = next(
                (
                    s
                    for s in reversed(path.pending)
                    if s.action is not StepAction.REMOVED and _named(s.effect) == key
                ),
                None,
            )
            if round_of is None:
                continue
            tests, models = compare_with_rivals(
                path.current.model,
                index,
                rivals_in_round(round_of.candidates, key),
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
                    next(c for c in round_of.candidates if (c.name, c.joint) == rival),
                    round_of.candidates,
                    rep,
                    label=f"+ {effect_label(*rival)} for {effect_label(*key)}",
                    action=StepAction.REPLACED,
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


def _named(effect: dict) -> tuple[str, int | None]:
    """(name, joint) of an effect given as {name, joint}."""
    return effect["name"], effect["joint"]


def _confounded(
    base: Baseline, path: SelectionPath, best: Candidate, close: list[Candidate], alpha: float
) -> list:
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
