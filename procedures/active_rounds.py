"""The active loop's rounds (procedures.active_loop declares the procedure): the campaign diagnosed, the next
round planned from what it leaves undecided, measured block by block through the engine and judged after each
block, every plan and judgement recorded in the campaign so that an interrupted round resumes as it was."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from hil.analysis.design.rounds import (
    BLOCK_ROWS,
    block_record,
    plan_blocks,
    plan_round,
    plannable,
    round_record,
    still_to_measure,
)
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, DiagnosisReport, run_diagnosis
from hil.analysis.diagnosis.questions import as_question, question_to_dict, with_questions
from hil.data.campaigns import open_campaign
from hil.data.dataset import DatasetError
from hil.data.jsonable import to_jsonable
from hil.data.pg_url import is_campaign_url
from hil.data.store import Campaign, campaign_dataset
from hil.model.coupled_model import keep_coupling
from hil.runner.cell_config import CellConfig
from hil.runner.controller_joints import kinematic_campaign
from hil.runner.engine import Advance, CampaignStopped, Measuring
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.procedure import Role
from hil.runner.registry import publisher
from hil.runner.session import Session
from hil.runner.sight import measurable
from procedures.active_records import NAME, ActiveLoopOptions, ActiveLoopResult, model_path_for


@dataclass(frozen=True)
class _Rows:
    """The next round's poses: joints (M, 6) in measurement order, each row's purpose, the plan's groups,
    the open questions it does not serve (and why; the questions as records, a resumed round's read back), `keep`: the rows the cell can measure now, and `block`:
    the rows measured between two judgements (the plan's order was built for it, so a resumed round keeps it
    whatever --block says now: its recorded judgements name blocks of that size)."""

    number: int
    q_rad: np.ndarray
    purpose: list[str]
    groups: list[dict]
    not_planned: list[dict]
    keep: np.ndarray
    block: int

    def to_dict(self) -> dict:
        """The plan as the campaign records it (`roundN/plan`), each question as stored."""
        groups = [with_questions(g, question_to_dict) for g in self.groups]
        not_planned = [with_questions(n, question_to_dict) for n in self.not_planned]
        return {
            "q_rad": self.q_rad.round(12).tolist(), "purpose": self.purpose, "groups": groups,
            "not_planned": not_planned, "block": self.block,
        }  # fmt: skip


@dataclass
class _Campaign:
    """What the loop diagnoses: the grid then every finished round's rows (motion order), the validation poses."""

    store: Campaign
    config: CellConfig
    seed: int

    def records(self) -> list[dict]:
        """The finished rounds' records, round 1 first."""
        out: list[dict] = []
        while (record := self.store.step_result(NAME, f"round{len(out) + 1}")) is not None:
            out.append(record)
        return out

    def training(self, rounds: int) -> pd.DataFrame:
        """The grid, then the rows of rounds 1..`rounds` in the order they were measured."""
        try:
            grid = campaign_dataset(self.store, *publisher(Role.GRID))
        except DatasetError as exc:
            raise CampaignStopped(
                f"the active loop diagnoses the campaign's grid, and there is none: {exc}",
                "run `hil run grid_sampling` on the same campaign first",
            ) from exc
        if rounds == 0:
            return grid
        more = campaign_dataset(self.store, NAME, [f"round{k}" for k in range(1, rounds + 1)])
        return pd.concat([grid, more], ignore_index=True)

    def validation(self) -> pd.DataFrame | None:
        try:
            return campaign_dataset(self.store, *publisher(Role.VALIDATION))
        except DatasetError:
            return None

    def nest(self, train: pd.DataFrame) -> int:
        """The nest the grid was measured in (the rounds measure in the same one)."""
        return int(np.bincount(train["smr"].to_numpy(int)).argmax()) if "smr" in train else 1

    def diagnose(self, train: pd.DataFrame, previous: list[dict] | None = None) -> DiagnosisReport:
        """The diagnosis of `train` (validated on the grid's validation poses); `previous`: the effects the
        round before named (hil.analysis.diagnosis.pipeline keeps them when the new selection would predict worse without
        them). The same data diagnosed again in this process (the plan shown before connecting, then the
        loop's first round) is not diagnosed twice."""
        fit = self.store.step_result(*publisher(Role.TOOL))
        nest = str(self.nest(train))
        tool = (
            np.array(fit["nests_flange_mm"][nest], float) / 1e3
            if fit and nest in fit["nests_flange_mm"]
            else None
        )
        validation = self.validation()
        key = (
            _fingerprint(train),
            None if validation is None else _fingerprint(validation),
            self.seed,
            None if tool is None else tool.tobytes(),
            repr(self.config.nominal),
            repr(previous),
        )
        if key in _DIAGNOSED:
            _DIAGNOSED[key] = _DIAGNOSED.pop(key)  # now the most recent
        else:
            while len(_DIAGNOSED) >= _DIAGNOSES_KEPT:
                del _DIAGNOSED[next(iter(_DIAGNOSED))]  # the least recently asked for
            _DIAGNOSED[key] = run_diagnosis(
                train,
                self.config.nominal,
                df_validate=validation,
                options=DiagnosisOptions(seed=self.seed, tool_guess_m=tool),
                previous_effects=previous,
            )
        return _DIAGNOSED[key]

    def next_rows(
        self,
        number: int,
        rounds: int,
        poses: int,
        train: pd.DataFrame,
        before: DiagnosisReport,
        block: int = BLOCK_ROWS,
    ) -> tuple[_Rows | None, str]:
        """Round `number`'s poses (its recorded plan when it was started before), or None and why not."""
        if number > rounds:
            return None, f"{rounds} round(s) done (the --rounds limit)"
        pinned = self.store.step_result(NAME, f"round{number}/plan")
        admissible = measurable(self.config, self.nest(train))
        if (
            pinned is not None
        ):  # a resumed round: its recorded plan, less poses this cell config cannot measure
            q = np.asarray(pinned["q_rad"], float).reshape(-1, 6)
            rows = _Rows(
                number,
                q,
                list(pinned["purpose"]),
                [with_questions(g, as_question) for g in pinned["groups"]],
                [with_questions(n, as_question) for n in pinned.get("not_planned", [])],
                admissible(q),
                int(pinned.get("block", block)),
            )
            return rows, ""
        if not plannable(before):
            return None, "nothing is left undecided that poses can decide"
        plan = plan_round(train, before, poses, admissible, self.seed + number, block)
        if not plan.purpose:
            why = "; ".join(sorted({s["why"] for s in plan.not_planned})) or "no pose decides them"
            return None, f"the open questions cannot be planned on this cell ({why})"
        keep = np.ones(len(plan.purpose), bool)
        return _Rows(number, plan.q, list(plan.purpose), plan.groups, plan.not_planned, keep, block), ""


_DIAGNOSED: dict[tuple, DiagnosisReport] = {}
# A few, not one: a running loop only asks for the latest again, but a round resumed in the same process (a
# loop run again after it was interrupted) asks again for the grid's diagnosis and its judged blocks' in turn.
_DIAGNOSES_KEPT = 4


def _previous(records: list[dict]) -> list[dict] | None:
    """What the last finished round's diagnosis was given as the effects before it (a resumed loop diagnoses
    the campaign so far as that round did)."""
    return records[-1]["effects_before"] if records else None


def _fingerprint(df: pd.DataFrame) -> tuple:
    """What identifies a campaign's rows: their columns and a hash of every value."""
    return tuple(df.columns), len(df), int(pd.util.hash_pandas_object(df, index=False).sum())


def motion_plan(
    config: CellConfig, rows: _Rows, nest: int, only: np.ndarray | None = None, setup: bool = True
) -> Plan:
    """The round's poses as the session visits them, in the planned order (no approach poses: the order is
    the approach); `only`: these plan rows (a block); `setup=False`: the SMR is already in its nest."""
    location = f"nest{nest}"
    steps = (
        (OperatorStep(f"Put SMR 1 in tool nest {nest}.", "place_smr", smr=1, location=location),)
        if setup
        else ()
    )
    chosen = np.zeros(len(rows.keep), bool)
    chosen[np.arange(len(rows.keep)) if only is None else only] = True
    poses = [
        PlannedPose(
            f"a{rows.number}-{i + 1:03d}", NAME, f"round{rows.number}", q, location, smr=nest, setup=steps
        )
        for i, q in enumerate(rows.q_rad)
        if rows.keep[i] and chosen[i]
    ]
    dropped = {"not measurable with this cell config": int(np.sum(~rows.keep))} if not rows.keep.all() else {}
    return Plan(NAME, poses, config, operator_steps=1, dropped=dropped)


def plan_next_round(
    config: CellConfig, options: ActiveLoopOptions, campaign: str | Path | None = None
) -> Plan:
    """The next round's poses on this campaign (for --dry-run): the campaign is diagnosed, nothing moves;
    the plan's bounds say what may follow (the rounds after it are planned from what this one measures)."""
    rounds, poses, seed, block = options.rounds, options.poses, options.seed, options.block
    if campaign is None or not (is_campaign_url(campaign) or Path(campaign).exists()):
        raise ValueError("the active loop plans from a campaign's grid: give --campaign with a measured grid")
    with open_campaign(campaign, create=False, password_file=config.store_password_file) as store:
        state = _Campaign(kinematic_campaign(store, config.coupling), config, seed)
        done = len(state.records())
        try:
            train = state.training(done)
        except CampaignStopped as exc:
            raise ValueError(f"{exc.message}; {exc.remedy}") from exc
        before = state.diagnose(train, _previous(state.records()))
        rows, why = state.next_rows(done + 1, rounds, poses, train, before, block)
        nest = state.nest(train)
    if rows is None:
        return Plan(NAME, [], config, dropped={f"no round {done + 1}: {why}": 1})
    the_plan = motion_plan(config, rows, nest)
    the_plan.bounds = (
        f"round {done + 1} of at most {rounds}, measured in blocks of {rows.block} (a block whose questions are "
        f"decided ends it early); each later round: at most {poses} poses, planned from what this one measures"
    )
    return the_plan


def _measure_round(
    session: Session,
    state: _Campaign,
    rows: _Rows,
    before: DiagnosisReport,
    train: pd.DataFrame,
    shots: int | None,
) -> Measuring[list[dict]]:
    """Measure a round's plan block by block (requests to the engine); after each block the longer campaign
    is diagnosed and the rows whose questions it decided are dropped (hil.analysis.design.rounds). Each judgement is recorded
    (`roundN/blockK`) before the next motion, so a resumed round drops the same rows; returns them all.
    `train`: the campaign before the round (the round measures in its nest)."""
    nest = state.nest(train)
    todo = rows.keep.copy()
    judged: list[dict] = []
    for k, idx in enumerate(plan_blocks(len(rows.purpose), rows.block), start=1):
        idx = idx[todo[idx]]
        if not len(idx):
            continue
        # the operator places the SMR before this process' first new pose, not before every block
        plan = motion_plan(session.config, rows, nest, only=idx)
        phase = f"active loop, round {rows.number} block {k}"
        for done, request in enumerate(
            session.engine.requests(plan, shots=shots, extra={"round": rows.number}, strict=False)
        ):
            yield Advance(phase, done, len(plan.poses))
            yield request
        yield Advance(phase, len(plan.poses), len(plan.poses))
        step = f"round{rows.number}/block{k}"
        record = session.step_result(NAME, step)
        if record is None:
            longer = state.training(rows.number)
            after = state.diagnose(longer, before.effects_added)
            fresh = to_jsonable(block_record(k, len(longer) - len(train), rows.groups, after))
            assert isinstance(fresh, dict)
            session.finish_step(NAME, step, fresh)
            record = fresh
        judged.append(record)
        todo &= still_to_measure(rows.purpose, record)
        if not todo[idx[-1] + 1 :].any():
            break
    return judged


def run_rounds(session: Session, options: ActiveLoopOptions) -> ActiveLoopResult:
    """Diagnose, plan, measure block by block, diagnose again, for at most `rounds` rounds of at most `poses`
    poses; resumable. The engine measures what the rounds ask for."""
    campaign = session.store.path
    if not isinstance(campaign, Path):  # checked before anything moves
        raise CampaignStopped(
            f"the active loop writes its model beside its campaign file; {campaign} is in the shared store",
            "run the loop with a campaign file (--campaign job.sqlite), then hil campaign push it to the store",
        )
    session.require_registration()
    result = session.engine.run(_rounds(session, options))
    path = model_path_for(campaign)
    keep_coupling(result.report.model, session.config.coupling)  # compensate then writes the pendant's joints
    result.report.model.save(path)  # the model the next steps use, not the one from before the rounds
    return replace(result, model_path=path)


def _rounds(session: Session, options: ActiveLoopOptions) -> Measuring[ActiveLoopResult]:
    """The rounds as requests to the engine: each round's poses are yielded block by block, and the
    campaign, longer by what was measured, is diagnosed between them."""
    rounds, poses, seed, block, shots = (
        options.rounds,
        options.poses,
        options.seed,
        options.block,
        options.shots,
    )
    state = _Campaign(session.store, session.config, seed)
    records = state.records()
    train = state.training(len(records))
    before = state.diagnose(train, _previous(records))
    while True:
        number = len(records) + 1
        rows, why = state.next_rows(number, rounds, poses, train, before, block)
        if rows is None:
            break
        if session.step_result(NAME, f"round{number}/plan") is None:
            session.finish_step(NAME, f"round{number}/plan", rows.to_dict())  # pinned before the first motion
        blocks = yield from _measure_round(session, state, rows, before, train, shots)
        longer = state.training(number)
        after = state.diagnose(longer, before.effects_added)
        unmeasurable = int(np.sum(~rows.keep))
        record = to_jsonable(
            round_record(number, before, after, rows.to_dict(), len(train), len(longer), blocks, unmeasurable)
        )
        assert isinstance(record, dict)
        session.finish_step(NAME, f"round{number}", record)
        records.append(record)
        train, before = longer, after
    stop = {"rounds": len(records), "why": why}
    session.finish_step(NAME, "stop", stop)
    return ActiveLoopResult(records, stop, before)
