"""The active loop's name, options, result and where it writes its model: shared by its declaration
(procedures.active_loop) and its rounds (procedures.active_rounds), which the declaration imports only when
the loop plans or runs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hil.analysis.diagnosis.pipeline import DiagnosisReport

NAME = "active_loop"


@dataclass(frozen=True)
class ActiveLoopOptions:
    """The declared parameters, SI."""

    rounds: int
    poses: int
    block: int
    seed: int
    shots: int | None


@dataclass(frozen=True)
class ActiveLoopResult:
    records: list[dict]  # one per round, as stored (hil.analysis.design.rounds.round_record)
    stop: dict  # {"rounds": n, "why": ...}
    report: DiagnosisReport  # the diagnosis of the campaign with every round's poses
    model_path: Path | None = None  # where that diagnosis' model was written (beside the campaign)


def model_path_for(campaign: Path) -> Path:
    """Where the loop writes the model of its last round: beside the campaign, named after it
    (job.sqlite -> job.active-model.json). The loop's own output, so a resumed loop writes it again."""
    return campaign.with_name(campaign.stem + ".active-model.json")
