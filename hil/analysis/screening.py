"""Candidate screening for the diagnosis: linearised held-out (cross-validated) fits, the tests a candidate
effect must pass to be added, near-ties and the thermal preference, and the test that removes an earlier
effect a later one made redundant. The selection rule itself is told in hil/analysis/diagnosis.py's docstring."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from hil.analysis.calibrated_model import CalibratedModel
from hil.analysis.calibration import Problem, flatten_jacobian
from hil.analysis.effects import PHYSICAL_RANK, THERMAL_FAMILIES, Effect, temperature_driven
from hil.analysis.identifiability import analyse, scale_columns


def effect_label(name: str, joint: int | None) -> str:
    """'gravity_compliance (joint 2)': how stages and reports name an effect."""
    return name + (f" (joint {joint})" if joint else "")


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
    geometry_correlation: float = float("nan")  # largest canonical correlation with the geometry

    def to_dict(self) -> dict:
        return dict(self.__dict__)


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
    fit, cvs = _linear_fit_partitions(J, r, [folds], step)
    return fit, cvs[0]


def linear_fit_heldout(
    J: np.ndarray, r: np.ndarray, partitions: list[list[np.ndarray]], step: list | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`linear_fit_cv` over several partitions: full-fit residuals (N, 3|6) and each point's held-out squared
    error (N,) averaged over the partitions (what the selection tests compare, point by point)."""
    fit, cvs = _linear_fit_partitions(J, r, partitions, step)
    return fit, np.mean([np.sum(cv**2, axis=1) for cv in cvs], axis=0)


def _linear_fit_partitions(
    J: np.ndarray, r: np.ndarray, partitions: list[list[np.ndarray]], step: list | None
) -> tuple[np.ndarray, list[np.ndarray]]:
    Js, norms = scale_columns(J)  # unit columns, identifiable set: the normal equations are well conditioned
    rv = r.reshape(-1)
    N = Js.T @ Js
    g = Js.T @ rv
    dx_s = np.linalg.solve(N, g)
    if step is not None:
        step.append(dx_s / norms)
    n, m = r.shape  # m coordinates per row: 3 (position) or 6 (and a probe's weighted rotation)
    fit = (rv - Js @ dx_s).reshape(n, m)
    cvs = []
    for folds in partitions:
        cv = np.zeros((n, m))
        for test in folds:
            trows = (m * test[:, None] + np.arange(m)).ravel()
            Jt, rt = Js[trows], rv[trows]
            dxf = np.linalg.solve(N - Jt.T @ Jt, g - Jt.T @ rt)  # fit without the held-out fold
            cv[test] = (rt - Jt @ dxf).reshape(-1, m)
        cvs.append(cv)
    return fit, cvs


# A candidate whose every direction correlates more than this with the geometric (base, tool) columns
# only re-shapes the geometry on the measured poses: rejected. (A real 300 ppm scale error of a UR10's
# joint 2 sampled over 90 deg correlates 0.994 and is found; what correlates less but still fakes
# geometry, like a cyclic term of degrees on a short arc, is caught by its implausible size.)
MAX_GEOMETRY_CORRELATION = 0.998


def geometry_correlation(J: np.ndarray, n_effect: int) -> float:
    """Smallest canonical correlation between the last `n_effect` columns of J and the others: how well
    the geometry imitates the effect's most separable direction (1 = not separable at all)."""
    G, E = J[:, :-n_effect], J[:, -n_effect:]
    Qg = np.linalg.qr(G / np.linalg.norm(G, axis=0))[0]
    Qe = np.linalg.qr(E / np.linalg.norm(E, axis=0))[0]
    sines = np.linalg.svd(Qe - Qg @ (Qg.T @ Qe), compute_uv=False)
    return float(np.sqrt(max(0.0, 1.0 - float(np.max(sines)) ** 2)))


def held_out_gain(d: np.ndarray, pose: np.ndarray | None) -> tuple[float, float]:
    """Mean held-out gain per row and its one-sided p-value, with the rows of one pose as one sample: the
    SMRs of a pose share its error, so counting them as independent would make p too small."""
    clusters = d if pose is None else np.bincount(np.unique(pose, return_inverse=True)[1], weights=d)
    gain = float(np.sum(clusters) / len(d))
    m = len(clusters)
    se = float(np.std(clusters, ddof=1) * np.sqrt(m) / len(d)) if m > 1 else np.inf
    if se == 0.0:  # every pose gains exactly the same
        return gain, 0.0 if gain > 0 else 1.0
    return gain, float(stats.t.sf(gain / se, m - 1)) if np.isfinite(se) else 1.0


def group_key(*effects: Effect) -> tuple:
    """(family, joint) of one effect, or a tuple of those for a group tested together (in the order added)."""
    keys = tuple((e.family, e.joint) for e in effects)
    return keys[0] if len(keys) == 1 else keys


class Screen:
    """Linearised test of candidate effects against a base model (see the module docstring)."""

    def __init__(
        self,
        base: CalibratedModel,
        prob: Problem,
        free: np.ndarray,
        partitions: list[list[np.ndarray]],
        sigma2: float,
        alpha: float,
        n: int,
    ) -> None:
        self.base, self.prob, self.partitions, self.sigma2 = base, prob, partitions, sigma2
        self.alpha_cv, self.alpha_chi2 = alpha, alpha / max(n, 1)
        r, J = prob.evaluate(base)
        fit0, self.e0 = linear_fit_heldout(flatten_jacobian(J)[:, free], r, partitions)
        self.sse0 = float(np.sum(fit0**2))
        # each tested candidate's held-out squared error per row (N,), for comparing two candidates point by
        # point (hil.analysis.rivals)
        self.heldout_errors: dict[tuple, np.ndarray] = {}  # keys: `group_key` of what was added

    def test(self, eff: Effect, *together: Effect) -> tuple[Candidate, CalibratedModel | None]:
        """`eff` added to the base model (after the effects `together` with it, when a group is tested: the
        Candidate then names `eff` and says what it was tested with)."""
        trial = self.base
        for added in (*together, eff):
            trial = trial.with_effect(added)
        n_added = sum(len(added.params) for added in (*together, eff))
        r_t, J_t = self.prob.evaluate(trial)
        Jt = flatten_jacobian(J_t)
        tfree = analyse(Jt, trial.param_names).keep_mask
        n_new = int(np.sum(tfree[len(trial.param_names) - n_added :]))
        if n_new == 0:
            note = "inseparable from the geometry"
            return Candidate(eff.family, eff.joint, 0, float("nan"), 0.0, 1.0, 1.0, False, note), None
        corr = geometry_correlation(Jt[:, tfree], n_new)
        if corr > MAX_GEOMETRY_CORRELATION:
            note = (
                f"collinear with the geometric parameters (correlation {corr:.3f}): on these poses it would "
                "fake geometry and extrapolate badly"
            )
            cand = Candidate(eff.family, eff.joint, n_new, float("nan"), 0.0, 1.0, 1.0, False, note, corr)
            return cand, None
        step: list = []
        fit, e = linear_fit_heldout(Jt[:, tfree], r_t, self.partitions, step)
        self.heldout_errors[group_key(*together, eff)] = e
        sse = float(np.sum(fit**2))
        s2 = max(self.sigma2, sse / max(fit.size - int(tfree.sum()), 1))
        p_chi2 = float(stats.chi2.sf((self.sse0 - sse) / s2, n_new)) if self.sse0 > sse else 1.0
        gain, p_cv = held_out_gain(self.e0 - e, self.prob.pose)
        passed = gain > 0 and p_cv < self.alpha_cv and p_chi2 < self.alpha_chi2
        dx = np.zeros(len(trial.param_names))
        dx[tfree] = step[0]
        fitted = trial.apply_increment(dx)  # start the full refit from the linear solution
        why = None
        for added in fitted.effects[len(fitted.effects) - 1 - len(together) :] if passed else []:
            why = why or added.implausible(self.prob.ctx, fitted.nominal)
        with_ = ", ".join(effect_label(x.family, x.joint) for x in together)
        why_not_alone = f"tested together with {with_}" if together else ""
        cand = Candidate(
            eff.family,
            eff.joint,
            n_new,
            float(np.sqrt(np.mean(e))) * 1000.0,
            gain * 1e6,
            p_cv,
            p_chi2,
            passed and why is None,
            "; ".join(x for x in (why or "", why_not_alone) if x),
            corr,
        )
        return cand, fitted if cand.passed else None


NEAR_TIE = 0.9  # candidates within 10 % of the best held-out gain are a near-tie


def pick_winner(winners: list[tuple[Candidate, CalibratedModel]]) -> tuple[Candidate, CalibratedModel]:
    """The largest held-out gain, except that a near-tie goes to the simpler effect (fewer parameters),
    then to the more physically expected family (the data cannot tell them apart; parsimony can), and a
    temperature-driven thermal effect as good per parameter goes first (`_thermal_preferred`)."""
    top = max(c.gain_mm2 for c, _ in winners)
    tied = [cm for cm in winners if cm[0].gain_mm2 >= NEAR_TIE * top]
    best = min(tied, key=lambda cm: (cm[0].n_params, PHYSICAL_RANK.get(cm[0].name, 9), -cm[0].gain_mm2))
    if best[0].gain_mm2 < top:
        best[0].note = (
            best[0].note + "; " if best[0].note else ""
        ) + "chosen in a near-tie: simpler / physically expected"
    thermal = _thermal_preferred(best, winners)
    return thermal or best


def _per_param(c: Candidate) -> float:
    return c.gain_mm2 / max(c.n_params, 1)


def _thermal_preferred(
    best: tuple[Candidate, CalibratedModel], winners: list[tuple[Candidate, CalibratedModel]]
) -> tuple[Candidate, CalibratedModel] | None:
    """A passing thermal candidate driven by the recorded temperature that explains as much per parameter
    as a pose effect with more parameters goes first. A warm-up measured in raster order makes temperature
    collinear with one axis of the grid: the pose effect's extra coefficients then imitate the warm-up as a
    function of the pose, and once it is in, the temperature has too little left to pass, so the model
    extrapolates in temperature as badly as a model without it. Taken first, the thermal term leaves the
    pose effect its own share. (Time alone is no such cause: it orders the poses too.)"""
    if best[0].name in THERMAL_FAMILIES:
        return None
    fits = [
        cm
        for cm in winners
        if temperature_driven(cm[1].effects[-1])
        and cm[0].n_params < best[0].n_params
        and _per_param(cm[0]) >= _per_param(best[0])
    ]
    if not fits:
        return None
    chosen = max(fits, key=lambda cm: cm[0].gain_mm2)
    label = effect_label(best[0].name, best[0].joint)
    chosen[0].note = (chosen[0].note + "; " if chosen[0].note else "") + (
        f"preferred to {label}: the temperature explains as much per parameter with fewer parameters"
    )
    return chosen


# A thermal effect driven by the recorded temperature stays in the model while removing it costs held-out
# error at this level (or `alpha`, if looser): a looser level to remove than to enter. The spatial folds cannot score what a thermal term is
# for (a warmer day than any training row), and a pose effect added after it imitates part of a raster-order
# warm-up, which would otherwise remove the (preferred, see `_thermal_preferred`) thermal term again.
# Pose effects are removed at `alpha`.
ALPHA_TO_REMOVE_THERMAL = 0.05


def weakest_effect(
    model: CalibratedModel, prob: Problem, partitions: list[list[np.ndarray]], sigma2: float, alpha: float
) -> tuple[int, Candidate] | None:
    """The earlier effect (not the last added) that no longer improves the model significantly, if any."""
    r, J = prob.evaluate(model)
    Jf = flatten_jacobian(J)
    keep = analyse(Jf, model.param_names).keep_mask
    fit, e = linear_fit_heldout(Jf[:, keep], r, partitions)
    sse = float(np.sum(fit**2))
    s2 = max(sigma2, sse / max(fit.size - int(keep.sum()), 1))
    weakest = None
    for i, eff in enumerate(model.effects[:-1]):
        reduced = replace(model, effects=[x for k, x in enumerate(model.effects) if k != i])
        rr, Jr = prob.evaluate(reduced)
        Jrf = flatten_jacobian(Jr)
        kr = analyse(Jrf, reduced.param_names).keep_mask
        fit_r, e_r = linear_fit_heldout(Jrf[:, kr], rr, partitions)
        k = max(int(keep.sum() - kr.sum()), 1)
        p_chi2 = float(stats.chi2.sf((float(np.sum(fit_r**2)) - sse) / s2, k))
        gain, p_cv = held_out_gain(e_r - e, prob.pose)  # what removing it costs on held-out points
        level = max(alpha, ALPHA_TO_REMOVE_THERMAL) if temperature_driven(eff) else alpha
        if gain > 0 and p_cv < level and p_chi2 < level:
            continue
        cand = Candidate(
            eff.family,
            eff.joint,
            k,
            float(np.sqrt(np.mean(e_r))) * 1000.0,
            gain * 1e6,
            p_cv,
            p_chi2,
            False,
            "redundant once a later effect is in the model",
        )
        if weakest is None or gain < weakest[1].gain_mm2 / 1e6:
            weakest = (i, cand)
    return weakest
