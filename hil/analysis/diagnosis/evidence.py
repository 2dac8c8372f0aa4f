"""How far the campaign already decides each statistical open question: a rival model's coefficients and their
evidence z (the smallest relevant size over its standard error), decided at `DECISIVE_Z`.

The diagnosis uses it to leave out questions the campaign already decides; the active design
(hil.analysis.design.plan) uses the same rivals to choose the poses that raise that evidence."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy import stats

from hil.analysis.calibration.solve import Problem, flatten_jacobian, identify
from hil.analysis.diagnosis.questions import (
    STATISTICAL,
    AmbiguousEffects,
    ConfoundedParameters,
    ConfoundedWithGeometry,
    Marginal,
    Question,
    ThermalRivals,
)
from hil.analysis.diagnosis.screening import columns_outside_span
from hil.data.dataset import smr_ids
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import EffectContext, approach_signs, make_effect

RELEVANT_LENGTH_M = 20e-6  # smallest RMS displacement of the SMR worth deciding (about the tracker's noise)


DECISIVE_Z = (
    4.6  # z_(1e-3/2) + z_(0.9): a test at 1e-3 that finds an effect of the relevant size 9 times in 10
)


@dataclass
class Rival:
    """One statistical question: the model's Jacobian with the rival's columns and their evidence."""

    question: Question
    label: str
    cols: np.ndarray  # indices of the rival's columns in the scaled Jacobian
    size: np.ndarray  # smallest relevant size of each rival coefficient, scaled units
    cov: np.ndarray  # inverse information (scaled) of the campaign plus the rows chosen so far
    trial: CalibratedModel
    keep: np.ndarray  # columns of trial used
    norms: np.ndarray
    z_test: float | None = None  # the held-out test's own z (`held_out_z`), for a question it leaves open
    n_poses: int = 0  # the campaign's poses

    def rows_needed(self) -> int:
        """Poses a test-led question needs (`held_out_z`): the held-out t statistic grows as the square root
        of the number of poses that show the effect, so reaching DECISIVE_Z from z_test takes n ((DECISIVE_Z /
        z_test)^2 - 1) more poses that show it as well as the campaign's do (the design's rows show it better,
        so this errs on the side of measuring more)."""
        if self.z_test is None:
            return 0
        return int(np.ceil(self.n_poses * ((DECISIVE_Z / max(self.z_test, 1e-3)) ** 2 - 1)))

    def test_z_after(self, rows: float) -> float:
        """The held-out z expected after `rows` more poses (see `rows_needed`; a bound on a plan's worth
        counts its rows as campaign-average poses, not a whole number)."""
        return float((self.z_test or 0.0) * np.sqrt((self.n_poses + rows) / max(self.n_poses, 1)))

    def z(self, diag: np.ndarray, sigma_m: float) -> np.ndarray:
        """Evidence: the smallest size / standard error over the rival's coefficients (per candidate row)."""
        return np.min(self.size / (sigma_m * np.sqrt(np.clip(diag, 1e-300, None))), axis=-1)


def unmeasured_problem(model: CalibratedModel, df: pd.DataFrame, q: np.ndarray) -> Problem:
    """A Problem at joints `q` measured nowhere yet: the campaign's main SMR, its last time and temperature."""
    sid = int(np.bincount(smr_ids(df)).argmax())
    n = len(q)

    def last(col: str) -> np.ndarray | None:
        return np.full(n, float(df[col].iloc[-1])) if col in df.columns and len(df) else None

    ctx = EffectContext(q=q, t_s=last("t_s"), temperature_c=last("temperature_c"), approach=approach_signs(q))
    return Problem(ctx, np.full(n, sid), np.zeros((n, 3)))


def scaled_rows(trial: CalibratedModel, prob: Problem, keep: np.ndarray, norms: np.ndarray) -> np.ndarray:
    """(M, 3, p) position Jacobian rows at the problem's joints, in the design's scaled columns."""
    _, J = prob.evaluate(trial)
    return J[:, :3, keep] / norms


def rival_for(df, model, camp: Problem, qu: Question) -> Rival | None:
    """The rival model of a question prepared on the campaign (None when its columns cannot be built)."""
    if isinstance(qu, ConfoundedParameters):
        trial = model
        names = list(qu.parameters)
        label = f"{names[0]}/{names[1]}"
    else:
        if isinstance(qu, AmbiguousEffects):
            subject = qu.rival
        elif isinstance(qu, Marginal | ConfoundedWithGeometry | ThermalRivals):
            subject = qu.effect
        else:  # no rival model: the campaign's extent decides it
            return None
        eff = make_effect(subject["name"], subject["joint"])
        camp.ctx.p_flange_tool = model._row_tools(camp.smr)
        if not eff.prepare(camp.ctx, model.nominal):
            return None
        # a term of the same label already in the model (a physics term its prior carries) is tested free
        model = replace(model, effects=[e for e in model.effects if e.label != eff.label])
        trial = model.with_effect(eff)
        names = eff.param_names
        label = eff.label
    _, J = camp.evaluate(trial)
    Jf = flatten_jacobian(J[:, :3])
    keep = identify(model, camp).keep_mask
    keep = np.concatenate([keep, np.ones(len(trial.param_names) - len(keep), bool)])
    all_names = trial.param_names
    for nm in names:
        keep[all_names.index(nm)] = True
    kept = [n for n, k in zip(all_names, keep, strict=True) if k]
    norms = np.linalg.norm(Jf[:, keep], axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    Js = Jf[:, keep] / norms
    if not isinstance(qu, ConfoundedParameters):
        names = _separable(Js, kept, names)
        if not names:
            return None
    cols = np.array([kept.index(nm) for nm in names])
    info = Js.T @ Js + 1e-9 * np.eye(Js.shape[1])
    size = (
        np.array([_relevant_size(nm, Jf[:, all_names.index(nm)], trial, camp) for nm in names]) * norms[cols]
    )
    rival = Rival(qu, label, cols, size, np.linalg.inv(info), trial, keep, norms)
    rival.z_test = held_out_z(qu)
    rival.n_poses = camp.n_poses
    return rival


def held_out_z(qu: Question) -> float | None:
    """The held-out test's own z of a marginal candidate the full fit finds (None for other questions).

    The selection adds an effect when both its tests pass. A candidate that passes the full-fit test (it is
    there, beyond noise) but narrowly misses the held-out one (it does not yet predict held-out blocks
    better) is undecided by the selection's own rule, however large the design's z for a relevant-sized
    coefficient: that z is a full-fit precision, which the full fit has already shown to suffice. So its
    evidence is what the held-out test saw, z = Phi^-1(1 - p_cv) (< z at alpha, so never decided here), and
    a plan raises it as the information grows (z scales with the coefficient's standard error)."""
    if not isinstance(qu, Marginal) or not qu.full_fit_passed:
        return None
    return float(stats.norm.isf(min(max(qu.p_cv, 1e-300), 0.5)))


def _separable(Js: np.ndarray, kept: list[str], names: list[str], tol: float = 1e-3) -> list[str]:
    """The rival's coefficients that no combination of the model's columns (and the rival's earlier ones)
    reproduces, by the screening's rule (`columns_outside_span`). A coefficient the model reproduces exactly on
    any poses (a once-per-turn term of joint 2 in phase with its gravity sag) is merged there, as in the test:
    its evidence would stay zero whatever is measured, and asking for poses to decide it would make every
    question of that rival unplannable."""
    basis = np.linalg.qr(Js[:, [i for i, n in enumerate(kept) if n not in names]])[0]
    rival = Js[:, [kept.index(nm) for nm in names]]
    return [names[i] for i in columns_outside_span(basis, rival, tol)]


def _relevant_size(name: str, column: np.ndarray, trial: CalibratedModel, camp: Problem) -> float:
    """Smallest size of a coefficient worth deciding, in its own unit: the size that moves the SMR by
    RELEVANT_LENGTH_M (RMS over the campaign's poses), whatever the parameter (geometry or effect)."""
    del trial, camp
    return RELEVANT_LENGTH_M / max(float(np.sqrt(3.0 * np.mean(column**2))), 1e-12)


def evidence(
    df: pd.DataFrame, model: CalibratedModel, questions: list[Question], sigma_m: float
) -> list[dict]:
    """Each statistical question's evidence z on the campaign alone (decided at DECISIVE_Z)."""
    camp = Problem.from_frame(model, df)
    out = []
    for qu in questions:
        if qu.kind not in STATISTICAL:
            continue
        r = rival_for(df, model, camp, qu)
        z = (
            None
            if r is None
            else r.z_test
            if r.z_test is not None
            else float(r.z(np.diag(r.cov)[r.cols], sigma_m))
        )
        out.append({"question": qu, "evidence_z": z, "decisive_z": DECISIVE_Z})
    return out
