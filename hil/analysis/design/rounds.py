"""The rounds of an active diagnosis loop as records, and in words for the terminal and the HTML report.

One round: the diagnosis of the campaign so far (`before`) lists what it leaves undecided;
hil.analysis.design.plan plans the poses that decide it; they are measured and appended to the campaign
(row order is motion order); the longer campaign's diagnosis (`after`) judges each earlier question with
hil.analysis.diagnosis.questions.settled. A record holds what was undecided, what was measured, what got decided and
the error before and after: held-out on the campaign so far (it grows by the round's poses, so the two
figures are on different rows) and on the validation poses (the same poses before and after).

A round is sequential: its plan is measured in blocks of `BLOCK_ROWS` rows (the plan's design rows are
ordered so that each block ends a greedy prefix), and after each block the longer campaign is diagnosed
again - the same test that decides at the end of a round, so a marginal (test-led) question is judged by its
own held-out test. Rows whose every question that diagnosis no longer leaves open are not measured: the
round stops when the evidence for each question it serves has passed its threshold, not at a fixed count.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd

from hil.analysis.design.plan import BLOCK_ROWS, Proposal, propose
from hil.analysis.diagnosis.pipeline import DiagnosisReport
from hil.analysis.diagnosis.questions import (
    Question,
    question_subject,
    question_to_dict,
    settled,
    with_questions,
)


def plan_round(
    df: pd.DataFrame,
    report: DiagnosisReport,
    max_rows: int,
    admissible: Callable[[np.ndarray], np.ndarray] | None,
    seed: int,
    block: int = BLOCK_ROWS,
) -> Proposal:
    """The poses (at most `max_rows`, in measurement order, most informative first in each `block`) that
    decide what `report` leaves open on `df`."""
    sigma_m = float(np.sqrt(np.mean(np.asarray(report.noise.sigma_axis_m) ** 2)))
    return propose(
        df,
        report.model,
        report.undecided,
        max_rows,
        sigma_m,
        admissible=admissible,
        seed=seed,
        block_rows=block,
    )


def plan_blocks(rows: int, size: int = BLOCK_ROWS) -> list[np.ndarray]:
    """The plan's row indices in the blocks a round measures between two judgements."""
    if size < 1:
        raise ValueError(f"a block needs at least 1 row, got {size}")
    return [np.arange(a, min(a + size, rows)) for a in range(0, rows, size)]


def served_questions(group: dict) -> list[Question]:
    """The questions a plan group's rows serve (a sweep moved back down serves backlash too)."""
    also = group.get("also_question")
    return [group["question"], *([also] if also else [])]


def open_purposes(groups: list[dict], report: DiagnosisReport) -> set[str]:
    """The plan's purposes with a question that `report` (the diagnosis after a block) still leaves open, of
    whatever kind now (a marginal effect the block's rows turned into one the geometry imitates is still open)."""
    now = {question_subject(q) for q in report.undecided}
    return {g["purpose"] for g in groups if any(question_subject(q) in now for q in served_questions(g))}


def block_record(number: int, rows_measured: int, groups: list[dict], report: DiagnosisReport) -> dict:
    """The judgement after a round's block `number`: the round's rows measured so far, the purposes still
    open (the only rows measured from here on), the effects the longer campaign's diagnosis names."""
    return {
        "block": number,
        "rows": rows_measured,
        "open": sorted(open_purposes(groups, report)),
        "effects": report.effects_added,
    }


def still_to_measure(purpose: list[str], judged: dict) -> np.ndarray:
    """Which of a plan's rows a block's judgement (`block_record`) leaves to measure."""
    return np.isin(np.asarray(purpose, dtype=object), list(judged["open"]))


def plannable(report: DiagnosisReport) -> list[Question]:
    """The open questions that poses can decide (the others need another run, e.g. at another temperature)."""
    return [q for q in report.undecided if q.plannable]


def errors_mm(report: DiagnosisReport) -> dict[str, float | None]:
    """The final model's RMS error: held-out on the training rows and on the validation poses (None: none)."""

    def last(on: str) -> float | None:
        rms = [s["rms_mm"] for s in report.stages if s["on"] == on]
        return float(rms[-1]) if rms else None

    return {"heldout_rms_mm": last("heldout"), "validation_rms_mm": last("validate")}


def round_record(
    number: int,
    before: DiagnosisReport,
    after: DiagnosisReport,
    plan: dict,
    rows_before: int,
    rows_after: int,
    blocks: list[dict] | None = None,
    unmeasurable: int = 0,
) -> dict:
    """What one round did, as JSON-ready data (each question as stored, `Question.to_dict`): `plan` is
    {purpose: [...], groups: [...]} of the measured poses, as stored; `blocks`: each block's judgement
    (`block_record`); `unmeasurable`: planned rows the cell cannot measure."""
    judged = settled(before.undecided, after.undecided, after.effects_added)
    poses = rows_after - rows_before
    return {
        "round": number,
        "undecided": [q.to_dict() for q in before.undecided],
        "measured": {
            "planned": len(plan["purpose"]),
            "poses": poses,
            "unmeasurable": unmeasurable,
            "not_needed": max(len(plan["purpose"]) - unmeasurable - poses, 0),
            "blocks": blocks or [],
            "groups": plan["groups"],
            "not_planned": plan.get("not_planned", []),
            "rows_before": rows_before,
            "rows_after": rows_after,
        },
        "settled": [with_questions(s, question_to_dict) for s in judged],
        "effects_before": before.effects_added,
        "effects_after": after.effects_added,
        "error_before": errors_mm(before),
        "error_after": errors_mm(after),
        "open_after": [q.to_dict() for q in after.undecided],
    }
