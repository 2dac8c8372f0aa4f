"""Each effect the selection added, refitted against its rivals: a confident wrong name is the worst answer.

Forward selection adds the best candidate of a round given the effects before it. An effect added early can
win on a campaign that cannot tell it from a rival (the same family on another joint, another family with a
similar signature), and later effects can change which of the two the data prefers. So, after selection,
each added effect is taken out of the final model and put back against every rival that passed in its round
(whether it passed there or not) with at least `RIVAL_SHARE` of its held-out gain; both are refitted (linearised, every free parameter) and
their held-out squared errors compared pose by pose (one-sided t-tests, as in the screening):

- the rival is better at p < alpha: the rival replaces the effect;
- the effect is not better at p < `DECIDED_P`: the data does not decide between them, and the diagnosis
  reports an open question (`ambiguous_effects`) that hil.analysis.design.plan plans poses for.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hil.analysis.calibration.solve import Problem, identify, solve_ridge_igg3
from hil.analysis.diagnosis.screening import NOT_ALONG_JOINT_NOTE, Candidate, Screen, held_out_gain
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import EffectContext, make_effect

RIVAL_SHARE = 0.3  # a rival passed in the effect's round with at least this share of the winner's gain
DECIDED_P = 0.01  # the chosen effect must beat each rival at this level, or the question stays open


@dataclass
class RivalTest:
    """One chosen effect against one rival, both refitted in the final model without the chosen one."""

    chosen: dict  # {name, joint}
    rival: dict
    chosen_gain_mm2: float  # mean held-out squared error per row the chosen effect saves over the rival
    p_chosen_better: float
    p_rival_better: float
    rival_passes: bool  # the rival alone passes the screening's tests in the reduced model
    alpha: float  # the selection's level: a rival better at this level replaces the effect

    @property
    def verdict(self) -> str:
        """'replace' (the rival is better), 'undecided' or 'kept'."""
        if self.rival_passes and self.p_rival_better < self.alpha:
            return "replace"
        return "undecided" if self.p_chosen_better >= DECIDED_P else "kept"

    def to_dict(self) -> dict:
        return {
            "chosen": self.chosen,
            "rival": self.rival,
            "chosen_gain_mm2": self.chosen_gain_mm2,
            "p_chosen_better": self.p_chosen_better,
            "p_rival_better": self.p_rival_better,
            "verdict": self.verdict,
        }


def rivals_in_round(
    candidates: list[Candidate], chosen: tuple[str, int | None]
) -> list[tuple[str, int | None]]:
    """Candidates of the chosen effect's round that passed with at least RIVAL_SHARE of its held-out gain."""
    winner = next((c for c in candidates if (c.name, c.joint) == chosen), None)
    if winner is None or winner.gain_mm2 <= 0:
        return []
    return [
        (c.name, c.joint)
        for c in candidates
        if (c.name, c.joint) != chosen
        and c.gain_mm2 >= RIVAL_SHARE * winner.gain_mm2
        and not c.note.startswith(("collinear", "inseparable", NOT_ALONG_JOINT_NOTE))
    ]


def compare_with_rivals(
    model: CalibratedModel,
    index: int,
    rivals: list[tuple[str, int | None]],
    prob: Problem,
    ctx: EffectContext,
    partitions: list[list[np.ndarray]],
    sigma2: float,
    alpha: float,
) -> tuple[list[RivalTest], dict[tuple[str, int | None], CalibratedModel]]:
    """Effect `index` of `model` against each rival (not already in the model), in the model without it.
    Returns the tests and, for rivals that pass on their own, the linearised model holding the rival in the
    effect's place (the start of a full refit when it replaces the effect)."""
    effect = model.effects[index]
    held = {(e.family, e.joint) for e in model.effects}
    rivals = [r for r in rivals if r not in held]
    if not rivals:
        return [], {}
    reduced = replace(model, effects=[e for k, e in enumerate(model.effects) if k != index])
    free = identify(reduced, prob).keep_mask
    reduced = solve_ridge_igg3(reduced, prob, free, robust=False, max_iter=3).model
    screen = Screen(reduced, prob, free, partitions, sigma2, alpha, len(rivals) + 1)
    chosen_key = (effect.family, effect.joint)
    again = make_effect(*chosen_key)
    if not again.prepare(ctx, reduced.nominal):
        return [], {}
    screen.test(again)
    e_chosen = screen.heldout_errors.get(chosen_key)
    if e_chosen is None:  # inseparable without its rivals' help: nothing to compare
        return [], {}
    tests, models = [], {}
    for key in rivals:
        rival = make_effect(*key)
        if not rival.prepare(ctx, reduced.nominal):
            continue
        cand, fitted = screen.test(rival)
        e_rival = screen.heldout_errors.get(key)
        if e_rival is None:
            continue
        gain, p_chosen = held_out_gain(e_rival - e_chosen, prob.pose)
        _, p_rival = held_out_gain(e_chosen - e_rival, prob.pose)
        test = RivalTest(
            {"name": chosen_key[0], "joint": chosen_key[1]},
            {"name": key[0], "joint": key[1]},
            gain * 1e6,
            p_chosen,
            p_rival,
            cand.passed,
            alpha,
        )
        tests.append(test)
        if fitted is not None:
            models[key] = fitted
    return tests, models
