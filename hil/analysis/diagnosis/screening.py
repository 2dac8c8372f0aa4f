"""Candidate screening for the diagnosis: linearised held-out (cross-validated) fits, the tests a candidate
effect must pass to be added, near-ties and the thermal preference, and the test that removes an earlier
effect a later one made redundant. The selection rule itself is told in hil/analysis/diagnosis/pipeline.py's docstring.

Batched screening (`Screen.test`): the current model's Jacobian, its identifiability basis and every fold's
held-out solve are computed once per round; a candidate only adds its own few columns, which are
orthogonalised against that basis and enter each fold's solve as a low-rank (Schur complement) update. It
gives the per-candidate refit (`Screen.test_refit`, kept as the reference) to rounding, at a fraction of the
cost: no Jacobian, identifiability analysis or normal equations of the whole model per candidate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from hil.analysis.calibration.identifiability import analyse, scale_columns
from hil.analysis.calibration.solve import Problem, flatten_jacobian
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import (
    PHYSICAL_RANK,
    THERMAL_FAMILIES,
    Effect,
    growth_direction,
    physical,
    temperature_driven,
)


def effect_label(name: str, joint: int | None) -> str:
    """'gravity_compliance (joint 2)': how stages and reports name an effect."""
    return name + (f" (joint {joint})" if joint else "")


@dataclass(kw_only=True)
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
    rows_reclaimed: int = 0  # rows the current model rejects that the candidate's fit accepts, judged too

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def carried_over(name: str, joint: int | None, n_params: int) -> Candidate:
    """An effect an earlier diagnosis named, put in the model before the screening: passed, not tested here."""
    return Candidate(
        name=name,
        joint=joint,
        n_params=n_params,
        cv_rms_mm=float("nan"),
        gain_mm2=0.0,
        p_cv=1.0,
        p_chi2=1.0,
        passed=True,
        note="carried over from the earlier diagnosis",
    )


def _not_judged(eff: Effect, n_params: int, note: str, correlation: float = float("nan")) -> Candidate:
    """A candidate refused before its tests (the geometry imitates it): no held-out figures, never passed."""
    return Candidate(
        name=eff.family,
        joint=eff.joint,
        n_params=n_params,
        cv_rms_mm=float("nan"),
        gain_mm2=0.0,
        p_cv=1.0,
        p_chi2=1.0,
        passed=False,
        note=note,
        geometry_correlation=correlation,
    )


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


def columns_outside_span(Q: np.ndarray, E: np.ndarray, tol: float = 1e-3) -> list[int]:
    """The columns of E (indices) that the span of the orthonormal columns Q and E's earlier kept columns does
    not reproduce: each unit column's part orthogonal to them exceeds `tol` (`analyse`'s rule, re-orthogonalised
    once as there); zero columns are never kept."""
    kept: list[int] = []
    basis: list[np.ndarray] = []
    for i in range(E.shape[1]):
        norm = np.linalg.norm(E[:, i])
        if norm == 0:
            continue
        c = E[:, i] / norm
        for _ in range(2):
            c = c - Q @ (Q.T @ c)
            for b in basis:
                c = c - (b @ c) * b
        if np.linalg.norm(c) > tol:
            basis.append(c / np.linalg.norm(c))
            kept.append(i)
    return kept


class Screen:
    """Linearised test of candidate effects against a base model (see the module docstring): `test` is the
    batched screening, `test_refit` the per-candidate refit it reproduces."""

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
        self._r, self._J = prob.evaluate(base)
        fit0, self.e0 = linear_fit_heldout(flatten_jacobian(self._J)[:, free], self._r, partitions)
        self.sse0 = float(np.sum(fit0**2))
        # each tested candidate's held-out squared error per row (N,), for comparing two candidates point by
        # point (hil.analysis.diagnosis.rivals); keys: `group_key` of what was added
        self.heldout_errors: dict[tuple, np.ndarray] = {}
        self._batch: _Batch | None = None

    def test(self, eff: Effect, *together: Effect) -> tuple[Candidate, CalibratedModel | None]:
        """The candidate judged from the shared factorisation (batched screening); with effects `together`,
        the group added at once (the Candidate names `eff` and says what it was tested with)."""
        if self._batch is None:
            self._batch = _Batch(self.base, self._r, self._J, self.partitions)
        trial = self.base
        for added in (*together, eff):
            trial = trial.with_effect(added)
        b = self._batch
        E = np.hstack([effect_columns(self.base, added, self.prob, self._J) for added in (*together, eff)])
        kept, norms = b.separable(E)
        if not kept:
            return self._inseparable(eff)
        Es = E[:, kept] / norms[kept]
        corr = b.geometry_correlation(Es)
        if corr > MAX_GEOMETRY_CORRELATION:
            return self._collinear(eff, len(kept), corr)
        fit, e, dx_base, dx_new = b.fit(Es)
        dx = np.zeros(len(trial.param_names))
        dx[: len(b.keep)][b.keep] = dx_base
        dx[len(b.keep) + np.asarray(kept)] = dx_new / norms[kept]
        return self._judge(eff, trial, len(kept), corr, fit, e, int(b.keep.sum()) + len(kept), dx, together)

    def test_refit(self, eff: Effect, *together: Effect) -> tuple[Candidate, CalibratedModel | None]:
        """The candidate judged from its own Jacobian, identifiability analysis and k-fold fits: what the
        batched `test` reproduces, kept as its reference."""
        trial = self.base
        for added in (*together, eff):
            trial = trial.with_effect(added)
        n_added = sum(len(added.params) for added in (*together, eff))
        r_t, J_t = self.prob.evaluate(trial)
        Jt = flatten_jacobian(J_t)
        tfree = analyse(Jt, trial.param_names).keep_mask
        n_new = int(np.sum(tfree[len(trial.param_names) - n_added :]))
        if n_new == 0:
            return self._inseparable(eff)
        corr = geometry_correlation(Jt[:, tfree], n_new)
        if corr > MAX_GEOMETRY_CORRELATION:
            return self._collinear(eff, n_new, corr)
        step: list = []
        fit, e = linear_fit_heldout(Jt[:, tfree], r_t, self.partitions, step)
        dx = np.zeros(len(trial.param_names))
        dx[tfree] = step[0]
        return self._judge(eff, trial, n_new, corr, fit, e, int(tfree.sum()), dx, together)

    @staticmethod
    def _inseparable(eff: Effect) -> tuple[Candidate, None]:
        note = "inseparable from the geometry"
        return _not_judged(eff, 0, note), None

    @staticmethod
    def _collinear(eff: Effect, n_new: int, corr: float) -> tuple[Candidate, None]:
        note = (
            f"collinear with the geometric parameters (correlation {corr:.3f}): on these poses it would "
            "fake geometry and extrapolate badly"
        )
        return _not_judged(eff, n_new, note, corr), None

    def _judge(
        self,
        eff: Effect,
        trial: CalibratedModel,
        n_new: int,
        corr: float,
        fit: np.ndarray,
        e: np.ndarray,
        n_free: int,
        dx: np.ndarray,
        together: tuple[Effect, ...] = (),
    ) -> tuple[Candidate, CalibratedModel | None]:
        """Both tests of the selection rule on the candidate's full-fit and held-out residuals."""
        self.heldout_errors[group_key(*together, eff)] = e
        sse = float(np.sum(fit**2))
        s2 = max(self.sigma2, sse / max(fit.size - n_free, 1))
        p_chi2 = float(stats.chi2.sf((self.sse0 - sse) / s2, n_new)) if self.sse0 > sse else 1.0
        gain, p_cv = held_out_gain(self.e0 - e, self.prob.pose)
        passed = gain > 0 and p_cv < self.alpha_cv and p_chi2 < self.alpha_chi2
        fitted = trial.apply_increment(dx)  # start the full refit from the linear solution
        why = None
        for added in fitted.effects[len(fitted.effects) - 1 - len(together) :] if passed else []:
            why = why or added.implausible(self.prob.ctx, fitted.nominal)
        with_ = ", ".join(effect_label(x.family, x.joint) for x in together)
        why_not_alone = f"tested together with {with_}" if together else ""
        cand = Candidate(
            name=eff.family,
            joint=eff.joint,
            n_params=n_new,
            cv_rms_mm=float(np.sqrt(np.mean(e))) * 1000.0,
            gain_mm2=gain * 1e6,
            p_cv=p_cv,
            p_chi2=p_chi2,
            passed=passed and why is None,
            note="; ".join(x for x in (why or "", why_not_alone) if x),
            geometry_correlation=corr,
        )
        return cand, fitted if cand.passed else None


# Families whose claim reaches beyond the sampled arc of their joint: a scale error turns the joint (1 + s) times
# what its encoder says at every angle, so its offset grows without bound along the joint. On a short arc a
# linear offset of the angle is what many other things look like locally, and the slope then extrapolates
# wrongly: fitted on the public series B (joint 1 over -180..-45 deg) a 600 ppm scale of joint 1 passed the
# spatial folds and took the model on series C (joint 1 over -308..-180 deg) from 0.75 to 1.18 mm. Such a
# candidate must also predict each half of its joint's sampled range from the other (`predicts_along_joint`).
EXTRAPOLATING_FAMILIES = ("joint_scale",)
NOT_ALONG_JOINT_NOTE = "does not extrapolate along joint"  # how such a failed candidate's note starts


def joint_halves(prob: Problem, joint: int) -> list[np.ndarray]:
    """Two folds of the rows: the joint's angle up to its median, and beyond (a pose's rows share a fold)."""
    qj = prob.ctx.q[:, joint - 1]
    low = qj <= np.median(qj)
    return [np.flatnonzero(low), np.flatnonzero(~low)]


def predicts_along_joint(
    base: CalibratedModel,
    prob: Problem,
    free: np.ndarray,
    eff: Effect,
    sigma2: float,
    alpha: float,
) -> str | None:
    """Why a candidate of EXTRAPOLATING_FAMILIES fails to predict one half of its joint's sampled range from
    the other better than `base` (one-sided test at `alpha`), or None when it does (or is of another family)."""
    if eff.family not in EXTRAPOLATING_FAMILIES or eff.joint is None:
        return None
    halves = joint_halves(prob, eff.joint)
    if min(len(h) for h in halves) == 0:
        return f"joint {eff.joint} has one angle only: a scale cannot be told from its offset"
    screen = Screen(base, prob, free, [halves], sigma2, alpha, 1)
    screen.test(eff)
    e = screen.heldout_errors[group_key(eff)]
    gain, p = held_out_gain(screen.e0 - e, prob.pose)
    if gain > 0 and p < alpha:
        return None
    return (
        f"{NOT_ALONG_JOINT_NOTE} {eff.joint}: fitted on either half of its sampled range it predicts "
        f"the other {'worse' if gain <= 0 else 'no better'} (held-out gain {gain * 1e6:+.3g} mm^2, p {p:.1g})"
    )


def effect_columns(model: CalibratedModel, eff: Effect, prob: Problem, J: np.ndarray) -> np.ndarray:
    """The Jacobian columns (N m, k) that `eff` (coefficients zero) adds to `model` on `prob`, from the
    model's own Jacobian J (N, m, P) of `prob.evaluate`: a joint effect moves the point (and turns a probe)
    like its joint's theta, a growth scales every link length, an offset shifts the tracker frame, a scale
    stretches the point about the tracker."""
    ctx = prob.ctx
    ctx.p_flange_tool = model._row_tools(prob.smr)
    reg = eff.cached_regressors(ctx, model.nominal)
    n, m, _ = J.shape
    k = len(eff.params)
    cols = np.zeros((n, m, k))
    if eff.kind == "joint":
        theta = J[:, :, model.kinematic.param_names.index(f"theta{eff.joint_index + 1}")]
        cols[:] = theta[:, :, None] * reg[:, None, :]
    elif eff.kind == "growth":
        q_eff = ctx.q + model.joint_offsets(ctx)
        G = growth_direction(model.kinematic, q_eff) @ model.T_tracker_base[:3, :3].T
        cols[:, :3] = G[:, :, None] * reg[:, None, :]
    elif eff.kind == "scale":
        cols[:, :3] = model.predict_ctx(ctx)[:, :, None] * reg[:, None, :]
    else:
        cols[:, :3] = reg[:, :1, None] * np.eye(3)[None]
    return cols.reshape(n * m, k)


class _Batch:
    """What every candidate of a round shares: the model's identifiable columns (unit norm), an orthonormal
    basis of them, and for each fold of each partition the inverse normal matrix without the fold, its
    solution and held-out residuals. A candidate's k columns then cost O(rows P k) per fold."""

    def __init__(
        self, model: CalibratedModel, r: np.ndarray, J: np.ndarray, partitions: list[list[np.ndarray]]
    ) -> None:
        Jf = flatten_jacobian(J)
        self.keep = analyse(Jf, model.param_names).keep_mask
        self.G, self.norms = scale_columns(Jf[:, self.keep])
        self.Q = np.linalg.qr(self.G)[0]
        self.n, self.m = r.shape
        self.rv = r.reshape(-1)
        N0 = self.G.T @ self.G
        self.g0 = self.G.T @ self.rv
        self.N0inv = np.linalg.inv(N0)
        self.x0 = self.N0inv @ self.g0
        self.fit0 = self.rv - self.G @ self.x0
        self.folds: list[list[tuple]] = []
        for folds in partitions:
            per = []
            for test in folds:
                trows = (self.m * test[:, None] + np.arange(self.m)).ravel()
                Gt, rt = self.G[trows], self.rv[trows]
                Ainv = np.linalg.inv(N0 - Gt.T @ Gt)
                xf = Ainv @ (self.g0 - Gt.T @ rt)
                per.append((trows, Gt, rt, Ainv, xf, rt - Gt @ xf))
            self.folds.append(per)

    def separable(self, E: np.ndarray, tol: float = 1e-3) -> tuple[list[int], np.ndarray]:
        """The candidate's columns the identifiability analysis keeps (`analyse`'s rule: each unit column's
        part orthogonal to the model's and to the candidate's earlier kept columns exceeds `tol`), and the
        columns' norms."""
        norms = np.linalg.norm(E, axis=0)
        return columns_outside_span(self.Q, E, tol), np.where(norms > 0, norms, 1.0)

    def geometry_correlation(self, Es: np.ndarray) -> float:
        """`geometry_correlation` of the candidate's unit columns against the model's."""
        Qe = np.linalg.qr(Es)[0]
        sines = np.linalg.svd(Qe - self.Q @ (self.Q.T @ Qe), compute_uv=False)
        return float(np.sqrt(max(0.0, 1.0 - float(np.max(sines)) ** 2)))

    def fit(self, E: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Full-fit residuals (N, m), mean held-out squared error per point (N,) and the full fit's increments
        (model columns, candidate columns; scaled) with the candidate's unit columns E added."""
        C = self.G.T @ E
        D = E.T @ E
        ge = E.T @ self.rv
        W = self.N0inv @ C
        xe = np.linalg.solve(D - C.T @ W, ge - C.T @ self.x0)
        fit = (self.fit0 - (E - self.G @ W) @ xe).reshape(self.n, self.m)
        x_base = self.x0 - W @ xe
        errs = []
        for per in self.folds:
            cv = np.zeros(self.n * self.m)
            for trows, Gt, rt, Ainv, xf, cv0 in per:
                Et = E[trows]
                Cf = C - Gt.T @ Et
                Wf = Ainv @ Cf
                xef = np.linalg.solve(D - Et.T @ Et - Cf.T @ Wf, ge - Et.T @ rt - Cf.T @ xf)
                cv[trows] = cv0 - (Et - Gt @ Wf) @ xef
            errs.append(np.sum(cv.reshape(self.n, self.m) ** 2, axis=1))
        return fit, np.mean(errs, axis=0), x_base / self.norms, xe


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
        if physical(eff):  # physics (material growth, gravity yield from the masses): never removed
            continue
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
            name=eff.family,
            joint=eff.joint,
            n_params=k,
            cv_rms_mm=float(np.sqrt(np.mean(e_r))) * 1000.0,
            gain_mm2=gain * 1e6,
            p_cv=p_cv,
            p_chi2=p_chi2,
            passed=False,
            note="redundant once a later effect is in the model",
        )
        if weakest is None or gain < weakest[1].gain_mm2 / 1e6:
            weakest = (i, cand)
    return weakest
