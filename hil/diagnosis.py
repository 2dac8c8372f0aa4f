"""Close the loop: calibrate, look at the residual, test candidate effects, add the one that helps, repeat.

Selection rule for each round (every candidate from `hil.effects` the data could reveal):
1. add the candidate to the current model and re-run the identifiability analysis on the joint
   (geometry + effects) Jacobian, so coefficients the data cannot separate from the geometry are merged;
2. k-fold cross-validation (default 5 folds, same folds for every candidate): each fold refits all free
   parameters on the other folds and predicts the held-out points;
3. the candidate must (a) lower the held-out squared error per point, tested pairwise against the current
   model (one-sided t-test, p < alpha), and (b) explain more than measurement noise on the full fit:
   (SSE_before - SSE_after) / sigma^2 ~ chi2(k) with sigma the larger of the noise-floor sigma and the
   residual sigma after, p < alpha / number of candidates;
4. the passing candidate with the largest held-out gain is added and the whole model refitted robustly.
The loop stops when nothing passes. The residual left is then tested against the noise floor; if it is
larger and a residual map predicts it on held-out points, the report says structure remains that no
candidate explains and adds the map as a fallback stage.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy import stats
from threadpoolctl import threadpool_limits

from hil.calibrated_model import CalibratedModel, initial_model
from hil.calibration import (
    CalibrationResult,
    Problem,
    calibrate,
    flatten_jacobian,
    identify,
    solve_ridge_igg3,
)
from hil.effects import Effect, candidate_effects, make_effect, tool_points_rows
from hil.identifiability import analyse, scale_columns
from hil.kinematics import KinematicModel
from hil.noise_floor import NoiseFloor, estimate_noise_floor
from hil.residual_maps import MAP_KINDS, kfold_map_errors, make_map


def error_stats(err_m: np.ndarray) -> dict[str, float]:
    """mean / RMS / max / 95th percentile of 3-D error norms, mm, from (N, 3) errors in metres."""
    e = np.linalg.norm(np.atleast_2d(err_m), axis=1) * 1000.0
    return {
        "mean_mm": float(np.mean(e)),
        "rms_mm": float(np.sqrt(np.mean(e**2))),
        "max_mm": float(np.max(e)),
        "p95_mm": float(np.percentile(e, 95)),
    }


def kfold(n: int, k: int, seed: int) -> list[np.ndarray]:
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(f) for f in np.array_split(perm, k)]


def _fit_plain(model: CalibratedModel, problem: Problem, free: np.ndarray, iters: int = 8) -> CalibratedModel:
    return solve_ridge_igg3(model, problem, free, robust=False, max_iter=iters).model


def cv_residuals(
    model: CalibratedModel, free: np.ndarray, problem: Problem, folds: list[np.ndarray]
) -> np.ndarray:
    """Held-out residuals (N, 3): each fold predicted by the model refitted on the other folds.

    The refit is one Gauss-Newton step from `model` (fitted on all rows), the same linearisation the
    candidate screening uses, so every stage and candidate is judged alike.
    """
    r, J = problem.evaluate(model)
    return linear_fit_cv(flatten_jacobian(J)[:, free], r, folds)[1]


def linear_fit_cv(
    J: np.ndarray, r: np.ndarray, folds: list[np.ndarray], step: list | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Linearised least squares r ~ J dx: full-fit residuals and k-fold held-out residuals, both (N, 3).

    If `step` is a list, the full-fit increment dx (in J's columns) is appended to it.
    """
    Js, norms = scale_columns(J)  # unit columns, identifiable set: the normal equations are well conditioned
    rv = r.reshape(-1)
    N = Js.T @ Js
    g = Js.T @ rv
    dx_s = np.linalg.solve(N, g)
    if step is not None:
        step.append(dx_s / norms)
    fit = (rv - Js @ dx_s).reshape(-1, 3)
    n = r.shape[0]
    cv = np.zeros((n, 3))
    for test in folds:
        trows = (3 * test[:, None] + np.arange(3)).ravel()
        Jt, rt = Js[trows], rv[trows]
        dxf = np.linalg.solve(N - Jt.T @ Jt, g - Jt.T @ rt)  # fit without the held-out fold
        cv[test] = (rt - Jt @ dxf).reshape(-1, 3)
    return fit, cv


class _Screen:
    """Linearised test of candidate effects against a base model (see the module docstring)."""

    def __init__(
        self,
        base: CalibratedModel,
        prob: Problem,
        free: np.ndarray,
        folds: list,
        sigma2: float,
        alpha: float,
        n: int,
    ) -> None:
        self.base, self.prob, self.folds, self.sigma2 = base, prob, folds, sigma2
        self.alpha_cv, self.alpha_chi2 = alpha, alpha / max(n, 1)
        r, J = prob.evaluate(base)
        fit0, cv0 = linear_fit_cv(flatten_jacobian(J)[:, free], r, folds)
        self.sse0 = float(np.sum(fit0**2))
        self.e0 = np.sum(cv0**2, axis=1)

    def test(self, eff: Effect) -> tuple[Candidate, CalibratedModel | None]:
        trial = self.base.with_effect(eff)
        r_t, J_t = self.prob.evaluate(trial)
        Jt = flatten_jacobian(J_t)
        tfree = analyse(Jt, trial.param_names).keep_mask
        n_new = int(np.sum(tfree[len(trial.param_names) - len(eff.params) :]))
        if n_new == 0:
            note = "inseparable from the geometry"
            return Candidate(eff.family, eff.joint, 0, float("nan"), 0.0, 1.0, 1.0, False, note), None
        step: list = []
        fit, cv = linear_fit_cv(Jt[:, tfree], r_t, self.folds, step)
        sse = float(np.sum(fit**2))
        s2 = max(self.sigma2, sse / max(fit.size - int(tfree.sum()), 1))
        p_chi2 = float(stats.chi2.sf((self.sse0 - sse) / s2, n_new)) if self.sse0 > sse else 1.0
        d = self.e0 - np.sum(cv**2, axis=1)
        se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else np.inf
        gain = float(np.mean(d))
        p_cv = float(stats.t.sf(gain / se, len(d) - 1)) if se > 0 else (0.0 if gain > 0 else 1.0)
        passed = gain > 0 and p_cv < self.alpha_cv and p_chi2 < self.alpha_chi2
        cand = Candidate(
            eff.family, eff.joint, n_new, error_stats(cv)["rms_mm"], gain * 1e6, p_cv, p_chi2, passed
        )
        if not passed:
            return cand, None
        dx = np.zeros(len(trial.param_names))
        dx[tfree] = step[0]
        return cand, trial.apply_increment(dx)  # start the full refit from the linear solution


def _weakest_effect(
    model: CalibratedModel, prob: Problem, folds: list[np.ndarray], sigma2: float, alpha: float
) -> tuple[int, Candidate] | None:
    """The earlier effect (not the last added) that no longer improves the model significantly, if any."""
    r, J = prob.evaluate(model)
    Jf = flatten_jacobian(J)
    keep = analyse(Jf, model.param_names).keep_mask
    fit, cv = linear_fit_cv(Jf[:, keep], r, folds)
    sse, e = float(np.sum(fit**2)), np.sum(cv**2, axis=1)
    s2 = max(sigma2, sse / max(fit.size - int(keep.sum()), 1))
    weakest = None
    for i, eff in enumerate(model.effects[:-1]):
        reduced = replace(model, effects=[x for k, x in enumerate(model.effects) if k != i])
        rr, Jr = prob.evaluate(reduced)
        Jrf = flatten_jacobian(Jr)
        kr = analyse(Jrf, reduced.param_names).keep_mask
        fit_r, cv_r = linear_fit_cv(Jrf[:, kr], rr, folds)
        k = max(int(keep.sum() - kr.sum()), 1)
        p_chi2 = float(stats.chi2.sf((float(np.sum(fit_r**2)) - sse) / s2, k))
        d = np.sum(cv_r**2, axis=1) - e  # what removing it costs on held-out points
        se = float(np.std(d, ddof=1) / np.sqrt(len(d)))
        gain = float(np.mean(d))
        p_cv = float(stats.t.sf(gain / se, len(d) - 1)) if se > 0 else 1.0
        if gain > 0 and p_cv < alpha and p_chi2 < alpha:
            continue
        cand = Candidate(
            eff.family,
            eff.joint,
            k,
            error_stats(cv_r)["rms_mm"],
            gain * 1e6,
            p_cv,
            p_chi2,
            False,
            "redundant once a later effect is in the model",
        )
        if weakest is None or gain < weakest[1].gain_mm2 / 1e6:
            weakest = (i, cand)
    return weakest


def _free_mask(model: CalibratedModel, problem: Problem) -> tuple[np.ndarray, object]:
    report = identify(model, problem)
    return report.keep_mask, report


@dataclass
class Candidate:
    name: str
    joint: int | None
    n_params: int
    cv_rms_mm: float
    gain_mm2: float  # mean held-out squared-error reduction per point
    p_cv: float
    p_chi2: float
    passed: bool
    note: str = ""

    def to_dict(self) -> dict:
        return dict(self.__dict__)


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
    action: str = "added"  # or "removed" (an earlier effect made redundant by a later one)
    summary: dict = field(default_factory=dict)  # physical figures: deflection, amplitude, gap, ppm/K

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
    conclusion: str
    residual_map: dict | None = None
    histograms: dict = field(default_factory=dict)  # stage -> held-out error norms (mm)
    final_round: list[Candidate] = field(default_factory=list)
    ambiguities: list[dict] = field(default_factory=list)  # effects this data could not tell apart
    run: dict = field(default_factory=dict)  # robot, input files (hash, rows), date, software version

    @property
    def effects_added(self) -> list[dict]:
        """The effects the final model holds, in the order they were added."""
        return [{"name": e.family, "joint": e.joint} for e in self.model.effects]

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
            "conclusion": self.conclusion,
            "steps": [s.to_dict() for s in self.steps],
            "final_round_candidates": [c.to_dict() for c in self.final_round],
            "ambiguities": self.ambiguities,
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
        out.append({"name": nm, "value": float(v), "std": result.std.get(nm), "free": nm in result.std})
    return out


def _correlations(result: CalibrationResult, problem: Problem, eff: Effect) -> list[dict]:
    """For each free coefficient of `eff`, its strongest correlation with a geometric parameter."""
    _, J = problem.evaluate(result.model)
    names = result.model.param_names
    free = [names.index(n) for n in result.free]
    Jf = flatten_jacobian(J)[:, free]
    cov = np.linalg.pinv(Jf.T @ Jf)
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(sd, sd)
    fnames = result.free
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
    tracker_mpe_m: tuple[float, float] = (15e-6, 6e-6),
    compare_maps: bool = False,
) -> DiagnosisReport:
    """The whole loop on a training dataset (and an optional validation dataset never used for fitting).

    `compare_maps` runs the k-fold residual-map comparison (IDW / SVR / GP) even when the residual is
    at the noise floor (otherwise only when it is not).

    Held-out figures of every stage are computed at the end on the same rows: all points except those
    the final model rejects as outliers (a model that lacks an effect rejects the points that show it
    most, so its own outlier set would flatter it).
    """
    with threadpool_limits(1):  # small dense problems: threads only contend
        return _run_diagnosis(
            df,
            robot,
            df_validate,
            folds,
            alpha,
            seed,
            families,
            max_effects,
            repeatability_mm,
            tool_guess_m,
            tracker_mpe_m,
            compare_maps,
        )


def _run_diagnosis(
    df: pd.DataFrame,
    robot: str | KinematicModel,
    df_validate: pd.DataFrame | None,
    folds: int,
    alpha: float,
    seed: int,
    families: tuple[str, ...] | None,
    max_effects: int,
    repeatability_mm: float,
    tool_guess_m: np.ndarray | None,
    tracker_mpe_m: tuple[float, float],
    compare_maps: bool,
) -> DiagnosisReport:
    noise = estimate_noise_floor(
        df, mpe_const_m=tracker_mpe_m[0], mpe_per_m=tracker_mpe_m[1], repeatability_mm=repeatability_mm
    )
    sigma2 = float(np.mean(noise.sigma_axis_m**2))
    ridge = calibrate(df, robot, "ridge", tool_guess_m=tool_guess_m)
    lm = calibrate(df, robot, "lm", tool_guess_m=tool_guess_m)
    calibration = {"ridge_igg3": ridge.to_dict(), "lm": lm.to_dict()}
    current = ridge
    full = Problem.from_frame(current.model, df)

    def ok_problem(result: CalibrationResult) -> tuple[Problem, list[np.ndarray]]:
        rows = np.flatnonzero(~result.outliers)
        return full.subset(rows), kfold(len(rows), folds, seed)

    prob, fold_idx = ok_problem(current)
    nominal = initial_model(robot, df, tool_guess_m)
    reg_free = np.array([n.startswith(("base_", "tool")) for n in nominal.param_names])
    nominal = _fit_plain(nominal, prob, reg_free)
    stage_models: list[tuple[str, CalibratedModel]] = [
        ("uncompensated (nominal)", nominal),
        ("kinematic", current.model),
    ]
    free, _ = _free_mask(current.model, prob)
    cv_cur = cv_residuals(current.model, free, prob, fold_idx)

    pending: list[dict] = []
    ambiguities: list[dict] = []
    final_round: list[Candidate] = []
    for _ in range(max_effects):
        cands = candidate_effects(full.ctx, current.model.nominal, current.model.effects, families)
        base_fit = _fit_plain(current.model, prob, free, iters=3)
        # Screening is linear: one Gauss-Newton step from the current fit, for the current model and for
        # every candidate alike (the problem is nearly linear there); the winner is refitted in full.
        screen = _Screen(base_fit, prob, free, fold_idx, sigma2, alpha, len(cands))
        results = [screen.test(eff) for eff in cands]
        winners = [(c, m) for c, m in results if c.passed]
        if not winners:
            final_round = [c for c, _ in results]
            break
        best, best_model = max(winners, key=lambda cm: cm[0].gain_mm2)
        close = [c for c, _ in winners if c is not best and c.gain_mm2 >= 0.8 * best.gain_mm2]
        if close:  # say so when the data hardly tells two candidates apart
            best.note = "nearly as good: " + ", ".join(
                c.name + (f" j{c.joint}" if c.joint else "") for c in close
            )
        current = calibrate(df, best_model, "ridge")
        if close:  # did the winner take the others' gain? Then the data cannot tell them apart.
            prob_now, folds_now = ok_problem(current)
            after = _Screen(
                current.model, prob_now, _free_mask(current.model, prob_now)[0], folds_now, sigma2, alpha, 1
            )
            for c in close:
                eff_c = make_effect(c.name, c.joint)
                eff_c.prepare(full.ctx, current.model.nominal)
                left = after.test(eff_c)[0].gain_mm2
                if left < 0.25 * c.gain_mm2:
                    ambiguities.append(
                        {
                            "chosen": {"name": best.name, "joint": best.joint},
                            "confounded_with": {"name": c.name, "joint": c.joint},
                            "gain_before_mm2": c.gain_mm2,
                            "gain_left_mm2": left,
                        }
                    )
        prob, fold_idx = ok_problem(current)
        free, rep = _free_mask(current.model, prob)
        cv_cur = cv_residuals(current.model, free, prob, fold_idx)
        label = f"+ {best.name}" + (f" (joint {best.joint})" if best.joint else "")
        stage_models.append((label, current.model))
        eff_index = len(current.model.effects) - 1
        eff = current.model.effects[eff_index]
        pending.append(
            {
                "effect": {"name": best.name, "joint": best.joint},
                "parameters": _effect_params(current, eff_index),
                "candidates": [c for c, _ in results],
                "merged": [d for d in rep.dropped if d["name"] in eff.param_names],
                "correlations": _correlations(current, prob, eff),
                "summary": eff.summary(prob.ctx, current.model.nominal),
            }
        )
        # Backward check: does every earlier effect still earn its place beside the new one?
        while len(current.model.effects) > 1:
            weakest = _weakest_effect(current.model, prob, fold_idx, sigma2, alpha)
            if weakest is None:
                break
            idx, cand = weakest
            gone = current.model.effects[idx]
            reduced = replace(
                current.model, effects=[e for k, e in enumerate(current.model.effects) if k != idx]
            )
            current = calibrate(df, reduced, "ridge")
            prob, fold_idx = ok_problem(current)
            free, rep = _free_mask(current.model, prob)
            cv_cur = cv_residuals(current.model, free, prob, fold_idx)
            label = (
                f"- {gone.family}" + (f" (joint {gone.joint})" if gone.joint else "") + " (no longer needed)"
            )
            stage_models.append((label, current.model))
            pending.append(
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

    # Every stage on the final rows and folds.
    stages: list[dict] = []
    hist: dict[str, list[float]] = {}
    cv_by_stage: list[np.ndarray] = []
    for label, m in stage_models:
        mfree = reg_free if label.startswith("uncompensated") else _free_mask(m, prob)[0]
        cv = cv_residuals(m, mfree, prob, fold_idx)
        cv_by_stage.append(cv)
        stages.append(_stage(label, "heldout", cv))
        hist[label] = (np.linalg.norm(cv, axis=1) * 1000).tolist()
    steps: list[Step] = []
    final_model = current.model
    for k, info in enumerate(pending):
        before, after = cv_by_stage[k + 1], cv_by_stage[k + 2]
        plot = {}
        if info.get("action", "added") == "added":
            stage_model = stage_models[k + 2][1]
            eff_index = len(stage_model.effects) - 1
            disp = _effect_displacement(stage_model, prob, eff_index)
            norm = np.linalg.norm(disp, axis=1, keepdims=True)
            u = disp / np.where(norm > 0, norm, 1.0)
            drv_label, drv = stage_model.effects[eff_index].driver(prob.ctx, stage_model.nominal)
            plot = {
                "driver_label": drv_label,
                "driver": np.asarray(drv).tolist(),
                "residual_before_mm": (np.sum(before * u, axis=1) * 1000).tolist(),
                "residual_after_mm": (np.sum(after * u, axis=1) * 1000).tolist(),
            }
        steps.append(
            Step(heldout_before=error_stats(before), heldout_after=error_stats(after), plot=plot, **info)
        )
    cv_cur = cv_by_stage[-1]

    # What is left: more than noise? structured (a residual map predicts it)?
    r_fit = prob.residuals(final_model)
    dof = max(r_fit.size - int(free.sum()), 1)
    ratio = float(np.sqrt(np.sum(r_fit**2) / dof / sigma2))
    p_excess = float(stats.chi2.sf(np.sum(r_fit**2) / sigma2, dof))
    if (p_excess < alpha and ratio > 1.1) or compare_maps:
        map_report = _try_residual_maps(final_model, prob, cv_cur, fold_idx, noise, alpha)
    else:  # at the noise floor: nothing for a map to find
        map_report = {
            "candidates": {},
            "winner": None,
            "structured": False,
            "note": "residual at the noise floor",
        }
    unexplained = bool(p_excess < alpha and ratio > 1.1 and map_report["structured"])
    residual_map_obj = None
    if unexplained:
        best_kind = map_report["winner"]
        label = f"+ residual map ({best_kind})"
        stages.append(_stage(label, "heldout", np.asarray(map_report["heldout_residual"])))
        hist[label] = (np.linalg.norm(map_report["heldout_residual"], axis=1) * 1000).tolist()
        residual_map_obj = make_map(best_kind).fit(
            prob.ctx.q, _p_base(final_model, prob), r_fit, float(np.sqrt(sigma2))
        )
        final_model.residual_map = residual_map_obj.to_dict()
    map_report.pop("heldout_residual", None)
    added = ", ".join(f"{e.family}" + (f" (joint {e.joint})" if e.joint else "") for e in final_model.effects)
    if unexplained:
        conclusion = (
            f"Added: {added or 'nothing'}. Structured residual remains that no candidate effect explains "
            f"(residual sigma {ratio:.2f}x the noise floor; a {map_report['winner']} residual map predicts it on "
            "held-out points), so a residual map is used as the fallback."
        )
    elif ratio > 1.1 and p_excess < alpha:
        conclusion = (
            f"Added: {added or 'nothing'}. The residual is {ratio:.2f}x the noise floor but shows no structure a "
            "residual map can predict: the noise floor is probably underestimated (robot repeatability?)."
        )
    else:
        conclusion = f"Added: {added or 'nothing'}. The residual is at the noise floor ({ratio:.2f}x)."
    for amb in ambiguities:
        a, b = amb["chosen"], amb["confounded_with"]
        conclusion += (
            f" Caution: on this data {a['name']}"
            + (f" (joint {a['joint']})" if a["joint"] else "")
            + f" and {b['name']}"
            + (f" (joint {b['joint']})" if b["joint"] else "")
            + " explain the same residual; the choice between them is not reliable (measure poses or approach"
            " directions that separate them, e.g. a random visiting order)."
        )
    if df_validate is not None:
        val = Problem.from_frame(final_model, df_validate)
        for label, m in stage_models:
            stages.append(_stage(label, "validate", val.residuals(m)))
            hist[f"{label} [validate]"] = (np.linalg.norm(val.residuals(m), axis=1) * 1000).tolist()
        if residual_map_obj is not None:
            r_val = val.residuals(final_model)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                corr = residual_map_obj.predict_raw(val.ctx.q, _p_base(final_model, val))
            stages.append(_stage(f"+ residual map ({map_report['winner']})", "validate", r_val - corr))
    held = [st["rms_mm"] for st in stages if st["on"] == "heldout"]
    valid = [st["rms_mm"] for st in stages if st["on"] == "validate"]
    if valid and valid[-1] > 1.5 * held[-1]:
        conclusion += (
            f" Caution: the validation campaign's RMS ({valid[-1]:.4f} mm) is {valid[-1] / held[-1]:.1f}x the "
            "held-out one: the training campaign does not represent it (poses, visiting order, time), so an "
            "effect may be hidden in the training data by another one; measure a campaign in a random order."
        )
    for note in ridge.notes:
        conclusion += f" Caution: {note}"
    final_model.info["diagnosis"] = {
        "effects_added": [s.effect for s in steps],
        "noise_floor_mm": noise.floor_mm,
    }
    return DiagnosisReport(
        model=final_model,
        calibration=calibration,
        noise=noise,
        stages=stages,
        steps=steps,
        unexplained_structure=unexplained,
        conclusion=conclusion,
        residual_map={**map_report, "excess_ratio": ratio, "p_excess": p_excess},
        histograms=hist,
        final_round=final_round,
        ambiguities=ambiguities,
        run=run_record(nominal.nominal, {"training": df, "validation": df_validate}),
    )


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
    return {
        "robot": robot.name,
        "inputs": inputs,
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": f"hil {version}",
    }


def _p_base(model: CalibratedModel, problem: Problem) -> np.ndarray:
    q_eff = problem.ctx.q + model.joint_offsets(problem.ctx)
    return tool_points_rows(model.kinematic, q_eff, model._row_tools(problem.smr))


def _try_residual_maps(
    model: CalibratedModel,
    prob: Problem,
    cv_res: np.ndarray,
    folds: list[np.ndarray],
    noise: NoiseFloor,
    alpha: float,
) -> dict:
    """Can a residual map predict the held-out residual? k-fold comparison of the map kinds."""
    q = prob.ctx.q
    p_base = _p_base(model, prob)
    sigma = float(np.sqrt(np.mean(noise.sigma_axis_m**2)))
    e0 = np.sum(cv_res**2, axis=1)
    table = {}
    best = None
    for kind in MAP_KINDS:
        try:
            res = kfold_map_errors(kind, q, p_base, cv_res, sigma, folds)
        except Exception as exc:  # a map that cannot be built on this data (e.g. no grid) is skipped
            table[kind] = {"error": str(exc)}
            continue
        d = e0 - np.sum(res**2, axis=1)
        se = float(np.std(d, ddof=1) / np.sqrt(len(d)))
        p = float(stats.t.sf(np.mean(d) / se, len(d) - 1)) if se > 0 else 1.0
        table[kind] = {**error_stats(res), "p_value": p}
        if best is None or table[kind]["rms_mm"] < table[best]["rms_mm"]:
            best = kind
            best_res = res
    structured = best is not None and table[best]["p_value"] < alpha
    return {
        "candidates": table,
        "winner": best,
        "structured": bool(structured),
        "heldout_residual": best_res if best is not None else cv_res,
    }
