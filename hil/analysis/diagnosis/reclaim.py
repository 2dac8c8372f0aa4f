"""Rows a model lacking an effect rejects as outliers are the rows that show the effect: a candidate is judged
again on the rows either model accepts (`reclaimed`), so that outlier rejection does not decide the question
for the model without it.
"""

from __future__ import annotations

import numpy as np

from hil.analysis.calibration.solve import (
    K1,
    CalibrationResult,
    flatten_jacobian,
    robust_scales,
    solve_ridge_igg3,
)
from hil.analysis.diagnosis.baseline import Baseline, fit_plain, free_mask
from hil.analysis.diagnosis.screening import Candidate, Screen
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import Effect, make_effect


def reclaimed(
    base: Baseline,
    current: CalibrationResult,
    free: np.ndarray,
    alpha: float,
    results: list[tuple[Candidate, CalibratedModel | None]],
    n_tests: int,
) -> list[tuple[Candidate, CalibratedModel | None]]:
    """The round's results, with each candidate that the full-fit test finds but the held-out test does not
    judged again on the rows that the current model or the candidate's own robust fit accepts.

    Why: outlier rejection guards against blunders, which no model explains. The screening's rows are the
    current model's inliers, and the rows a missing effect moves most are the ones that model rejects (an
    active loop's poses, measured where the rivals differ, most of all): on its inliers alone the effect it
    lacks cannot show, and the model that lacks the effect would decide the question in its own favour. Two
    rival models are judged on the rows at least one of them fits; a row both reject is a blunder for both.
    Only candidates whose verdict this can change are re-judged (one robust refit each, from the current
    model, on the rows that can enter the screening's subset): those the full-fit test passed and the
    held-out one did not; and, when nothing passes so the selection would stop, the RECLAIM_UNSEEN whose
    linearised fit on every row takes back the most rejected rows beyond the model's own
    (`_linear_reclaim`), since the inlier full-fit test cannot find an effect whose rows were rejected. A
    candidate whose fit accepts no rejected row keeps its result.
    """
    rejected = current.outliers
    if not rejected.any():
        return results
    out = list(results)
    model = current.model
    test_level = alpha / max(n_tests, 1)
    seen: list[tuple[int, Effect]] = []
    unseen: list[tuple[int, Effect]] = []
    for i, (cand, _) in enumerate(results):
        if cand.passed or cand.note:
            continue
        eff = make_effect(cand.name, cand.joint)
        if eff.prepare(base.full.ctx, model.nominal):
            (seen if cand.p_chi2 < test_level else unseen).append((i, eff))

    if not seen and not unseen:
        return out
    rows = base.contested_rows(rejected)  # only these can enter the screening's rows, whichever rival fits
    contested = base.full.subset(rows)

    def judge(i: int, eff: Effect) -> None:
        rival = model.with_effect(eff)
        fitted = solve_ridge_igg3(rival, contested, free_mask(rival, contested)[0], frozen_jacobian=True)
        both = rejected.copy()
        both[rows] &= fitted.outliers
        if both.sum() == rejected.sum():
            return
        prob, partitions = base.rows_and_folds(current, both)
        kept = free_mask(current.model, prob)[0]
        start = fit_plain(current.model, prob, kept, iters=3)
        screen = Screen(start, prob, kept, partitions, base.sigma2, alpha, n_tests)
        again, trial = (screen.test if base.screening == "batched" else screen.test_refit)(eff)
        again.rows_reclaimed = int(rejected.sum() - both.sum())
        out[i] = (again, trial)

    for i, eff in seen:
        judge(i, eff)
    if unseen and not any(c.passed for c, _ in out):  # the selection would stop: what do rejected rows hide?
        plain = _linear_reclaim(base, model, free, rejected)
        taken = [(_linear_reclaim(base, model, free, rejected, eff), i, eff) for i, eff in unseen]
        best = sorted((t for t in taken if t[0] > plain), key=lambda t: (-t[0], results[t[1]][0].p_chi2))
        for _, i, eff in best[:RECLAIM_UNSEEN]:
            judge(i, eff)
    return out


RECLAIM_UNSEEN = 3  # unseen candidates `reclaimed` re-judges per round, most rows taken back first


def _linear_reclaim(
    base: Baseline, model: CalibratedModel, free: np.ndarray, rejected: np.ndarray, eff: Effect | None = None
) -> int:
    """How many rows of `rejected` one least-squares step of `model` (with `eff` added) on every row brings
    back within the outlier threshold (K1 robust standard deviations of the other rows): `reclaimed`'s cheap
    gate before a robust refit."""
    trial = model if eff is None else model.with_effect(eff)
    r, J = base.full.evaluate(trial)
    cols = np.concatenate([free, np.ones(len(trial.param_names) - len(free), bool)])
    A = flatten_jacobian(J[:, :3])[:, cols]
    A = A / np.clip(np.linalg.norm(A, axis=0), 1e-300, None)
    after = r[:, :3] - (A @ np.linalg.lstsq(A, r[:, :3].reshape(-1), rcond=None)[0]).reshape(-1, 3)
    scale = np.maximum(robust_scales(after[~rejected], centred=True), 1e-12)
    t = np.sqrt(np.mean((after[rejected] / scale) ** 2, axis=1))
    return int(np.sum(t <= K1))
