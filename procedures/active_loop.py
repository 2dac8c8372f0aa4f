"""Active loop: measure what the diagnosis leaves undecided, until it decides (issue 18; docs/loop/papers.md).

Shop-floor instruction: after grid sampling (same campaign, SMR in the grid's nest), let the cell answer the
questions the data could not: the campaign's grid is diagnosed, the open questions that poses can decide (a
joint whose sampled range does not cover a once-per-turn error, backlash approached from one side only, no
pose measured again for drift, effects the geometry or each other imitate) get a plan of at most `poses`
poses inside the envelope with the SMR facing the tracker, the robot measures them into the same campaign
in that order (row order is motion order), and the longer campaign is diagnosed again. At most `rounds`
rounds; the loop stops earlier when nothing that poses can decide is left open. A round is measured in blocks
of `block` poses and the campaign is diagnosed after each: poses whose questions are already decided are not
measured, so a round ends as soon as what it was planned for is decided.

Each round is a campaign step (`round1`, `round2`, ...): its plan is recorded before the first motion
(`round1/plan`) and each block's judgement after it (`round1/block1`, ...), so an interrupted round resumes
with the same poses, drops the same ones and measures none twice; its record (what was undecided, what was
measured block by block, what got decided, the error before and after) is the step result.
`--dry-run` diagnoses the campaign and shows the next round's plan without moving anything.

The rounds are in procedures.active_rounds, imported when the loop plans or runs: declaring the procedure
(`hil run` reads every registered declaration to find which one publishes the registration) then imports no
diagnosis, which took 0.45 s of every `hil run`'s start.
"""

from __future__ import annotations

from pathlib import Path

from hil.analysis.design import BLOCK_ROWS
from hil.runner.cell_config import CellConfig
from hil.runner.plan import Plan
from hil.runner.procedure import SHOTS, Parameter, Procedure
from hil.runner.session import Session
from procedures.active_records import NAME, ActiveLoopOptions, ActiveLoopResult


def plan(config: CellConfig, options: ActiveLoopOptions, campaign: str | Path | None = None) -> Plan:
    """The next round's poses on this campaign (for --dry-run): the campaign is diagnosed, nothing moves
    (procedures.active_rounds.plan_next_round)."""
    from procedures.active_rounds import plan_next_round

    return plan_next_round(config, options, campaign)


def run_loop(session: Session, options: ActiveLoopOptions) -> ActiveLoopResult:
    """Diagnose, plan, measure block by block, diagnose again, for at most `rounds` rounds of at most `poses`
    poses; resumable (procedures.active_rounds.run_rounds)."""
    from procedures.active_rounds import run_rounds

    return run_rounds(session, options)


def summary(result: ActiveLoopResult) -> str:
    from hil.report.rounds import rounds_text

    text = rounds_text(result.records, result.stop)
    if result.model_path is None:
        return text
    return (
        f"{text}\nmodel of the last round written to {result.model_path}: compensate and close the loop with it "
        f"(hil run pseudo_target ... --model {result.model_path}); diagnose the campaign again for its report"
    )


PROCEDURE = Procedure(
    name=NAME,
    purpose="measure the poses that decide what the grid's diagnosis leaves undecided, diagnose again, repeat",
    instruction=__doc__ or "",
    parameters=(
        Parameter(
            "rounds",
            "rounds of plan, measure, diagnose (fewer when nothing is left undecided)",
            2,
            int,
            minimum=1,
            maximum=5,
        ),
        Parameter("poses", "poses per round at most", 100, int, minimum=1, maximum=500),
        Parameter(
            "block",
            "poses measured between two diagnoses of a round (it ends once its questions are decided)",
            BLOCK_ROWS,
            int,
            minimum=1,
            maximum=500,
        ),
        Parameter(
            "seed", "seed of the diagnosis' folds and of the plan's candidate poses", 0, int, minimum=0
        ),
        SHOTS,
    ),
    plan=plan,
    body=run_loop,
    steps=("round1/plan", "round1/block1", "...", "round1", "round2/plan", "...", "stop"),
    summary=summary,
    options=ActiveLoopOptions,
)
