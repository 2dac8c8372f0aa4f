"""The active loop on `hil sim` through ur-rtde and emScon: the cell carries gravity sag and cyclic joint errors;
the first (small) grid leaves questions open; the loop measures the poses that decide them into the same
campaign, resumes an interrupted round without measuring anything twice, and --dry-run moves nothing.

(A once-per-turn error of joint 1 is not decided here: the planned joint-1 sweep keeps the other joints fixed,
so the SMR turns away from the tracker and no visible sweep exists on this cell.)"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from cli_in_process import hil_in_process, run_hil

from hil.data.store import CampaignStore
from hil.model.calibrated_model import CalibratedModel
from hil.runner.session import Session
from hil.runner.sight import measurable
from procedures import active_loop, active_rounds, grid_sampling, registration, tool_fit
from tests.cell_fixtures import sim_cell_toml
from tests.sim_session import running_cell, session_on

pytestmark = pytest.mark.sim  # its campaign fixture starts the simulated cell (tests/test_suite_marks.py)

OFFLINE_HOST = "127.254.254.254"  # nothing listens there: a command that tried to connect would fail
EFFECTS = ("--effects", "gravity_compliance,cyclic")  # cyclic: once- and twice-per-turn errors of joints 1-3
INTERRUPT_AFTER = 3
BLOCK = 10  # two blocks a round: the round is judged after the first (the interruption falls in it)


class _LinkDroppedError(RuntimeError):
    """Stands in for a crash in the middle of a round."""


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """Grid at 200 mm on a seeded cell; a loop of 2 rounds of <= 20 poses in blocks of 10, interrupted in round
    1, then resumed."""
    folder = tmp_path_factory.mktemp("active_loop")
    path = folder / "campaign.sqlite"
    with running_cell(folder, time_scale=200.0, seed=2, extra_args=EFFECTS) as (_, config):
        with session_on(config, path) as session:
            registration.PROCEDURE(session)
            # the paper-sized tool fit is tested in test_procedures_sim
            tool_fit.PROCEDURE(session, check_poses=6, validation_poses=4, shots=3)
            grid_sampling.PROCEDURE(session, step_m=0.2, validation=20)
        shutil.copy(path, folder / "grid_only.sqlite")  # the campaign before any round (another crash test)
        measure = Session.measure_point
        calls = {"n": 0}

        def dropping(self, procedure, *args, **kwargs):
            if procedure == active_loop.NAME:
                calls["n"] += 1
                if calls["n"] > INTERRUPT_AFTER:
                    raise _LinkDroppedError("the link dropped")
            return measure(self, procedure, *args, **kwargs)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(Session, "measure_point", dropping)
            with pytest.raises(_LinkDroppedError), session_on(config, path) as session:
                active_loop.PROCEDURE(session, rounds=2, poses=20, block=BLOCK)
        with CampaignStore(path, create=False) as store:
            before_resume = store.measurements(active_loop.NAME)
        with session_on(config, path) as session:  # resumed without --block: round 1 keeps its blocks of 10
            result = active_loop.PROCEDURE(session, rounds=2, poses=20)
        yield {
            "config": config,
            "path": path,
            "grid_only": folder / "grid_only.sqlite",
            "folder": folder,
            "result": result,
            "before_resume": before_resume,
        }


def _key(effects: list[dict]) -> set:
    return {(e["name"], e["joint"]) for e in effects}


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_each_round_decides_questions_it_measured_for(loop):
    """The first grid leaves questions open that poses can decide; a round's poses decide at least one of those
    its plan served, and every round's record says what was undecided, measured, decided and the errors."""
    records = loop["result"].records
    assert any(q["plannable"] for q in records[0]["undecided"])
    for record in records:
        served = {json.dumps(g["question"], sort_keys=True) for g in record["measured"]["groups"]}
        decided = [
            s
            for s in record["settled"]
            if s["decided"] and json.dumps(s["question"], sort_keys=True) in served
        ]
        assert decided, record["settled"]
        assert 0 < record["measured"]["poses"] <= 20
        for figures in (record["error_before"], record["error_after"]):
            assert figures["validation_rms_mm"] > 0 and figures["heldout_rms_mm"] > 0
    assert loop["result"].stop["rounds"] == len(records) <= 2


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_the_loop_writes_the_model_of_its_last_round_and_says_where(loop):
    """The next steps (compensation, the pseudo-target loop) use the model the rounds made, not the one from
    before them: it is written beside the campaign and the summary names it."""
    result = loop["result"]
    assert result.model_path == loop["path"].with_name("campaign.active-model.json")
    written = CalibratedModel.load(result.model_path)
    assert {(e.family, e.joint) for e in written.effects} == {
        (e.family, e.joint) for e in result.report.model.effects
    }
    np.testing.assert_allclose(written.T_tracker_base, result.report.model.T_tracker_base, rtol=0, atol=1e-12)
    for ours, theirs in zip(written.effects, result.report.model.effects, strict=True):
        np.testing.assert_allclose(ours.params, theirs.params, rtol=1e-12)
    assert f"model of the last round written to {result.model_path}" in active_loop.summary(result)


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_every_round_is_measured_once_in_plan_order_inside_the_envelope(loop):
    config = loop["config"]
    with CampaignStore(loop["path"], create=False) as store:
        rows = store.measurements(active_loop.NAME)
        stored = [store.step_result(active_loop.NAME, f"round{r['round']}") for r in loop["result"].records]
    assert len(loop["before_resume"]) == INTERRUPT_AFTER  # the interrupted run kept what it had measured
    keys = list(zip(rows["step"], rows["point_id"], strict=True))
    assert len(set(keys)) == len(keys)  # nothing measured twice across the interruption
    assert set(loop["before_resume"]["point_id"]) <= set(rows["point_id"])
    for record in stored:
        ids = rows.loc[rows["step"] == f"round{record['round']}", "point_id"].tolist()
        assert ids == sorted(ids) and len(ids) == record["measured"]["poses"]  # recorded in the planned order
    q = rows[[f"q{j}_rad" for j in range(1, 7)]].to_numpy(float)
    assert not config.envelope.outside(config.nominal, q, config.nests_flange_m).any()
    assert measurable(config)(q).all()
    assert stored == loop["result"].records  # each round's record is its step result


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_a_round_is_judged_after_each_block_and_measures_only_what_is_still_open(loop):
    """Each block's judgement is a step result recorded before the next motion; the rows measured after it
    serve only the purposes it left open, and the round's record counts the rows it did not need."""
    with CampaignStore(loop["path"], create=False) as store:
        rows = store.measurements(active_loop.NAME)
        for record in loop["result"].records:
            n, m = record["round"], record["measured"]
            blocks = m["blocks"]
            assert (
                blocks
                and [store.step_result(active_loop.NAME, f"round{n}/block{b['block']}") for b in blocks]
                == blocks
            )
            plan = store.step_result(active_loop.NAME, f"round{n}/plan")
            purpose, size = plan["purpose"], plan["block"]
            if (
                n == 1
            ):  # planned in blocks of BLOCK, interrupted, resumed with the default: the plan's size holds
                assert size == BLOCK
            index = [int(p.split("-")[1]) - 1 for p in rows.loc[rows["step"] == f"round{n}", "point_id"]]
            for judged in blocks:
                later = [purpose[i] for i in index if i >= judged["block"] * size]
                assert set(later) <= set(judged["open"])
            assert [b["rows"] for b in blocks] == sorted(b["rows"] for b in blocks)
            assert blocks[-1]["rows"] == m["poses"] == len(index)
            assert m["not_needed"] == m["planned"] - m["unmeasurable"] - m["poses"] >= 0


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_dry_run_shows_the_next_round_and_moves_nothing(loop, tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text(
        (loop["folder"] / "cell.toml").read_text().replace(loop["config"].robot_host, OFFLINE_HOST)
    )
    with CampaignStore(loop["path"], create=False) as store:
        count = len(store.measurements())
    # In this process, before any other test diagnoses: the campaign's rows are those the fixture's loop
    # diagnosed last, so the plan reuses that diagnosis (a subprocess repeated it: minutes on a loaded machine).
    done = run_hil("run", "active_loop", "--cell", str(cell), "--campaign", str(loop["path"]), "--dry-run",
                   "--rounds", "3", "--poses", "10", cwd=tmp_path, capsys=capsys)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "plan of active_loop" in done.stdout
    with CampaignStore(loop["path"], create=False) as store:
        assert len(store.measurements()) == count
        assert store.step_result(active_loop.NAME, "round3/plan") is None  # a dry run records nothing


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_a_crash_between_a_block_and_its_judgement_loses_nothing_and_measures_nothing_twice(loop, tmp_path):
    """The other crash window of a round: block 1 fully measured, its judgement not yet recorded. The resumed
    round measures none of block 1 again, judges it from the rows it has, and goes on."""
    path = tmp_path / "campaign.sqlite"
    shutil.copy(loop["grid_only"], path)
    # the round's plan (its dry run): two blocks at least, so the resumed round has one to go on with
    planned = active_loop.PROCEDURE.make_plan(loop["config"], campaign=path, rounds=1, poses=10, block=2)
    assert len(planned.poses) > 2, planned.dropped
    finish = Session.finish_step

    def crashing(self, procedure, step, result):
        if procedure == active_loop.NAME and step == "round1/block1":
            raise _LinkDroppedError("the process died before recording the judgement")
        return finish(self, procedure, step, result)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Session, "finish_step", crashing)
        with pytest.raises(_LinkDroppedError), session_on(loop["config"], path) as session:
            active_loop.PROCEDURE(session, rounds=1, poses=10, block=2)
    with CampaignStore(path, create=False) as store:
        before = list(store.measurements(active_loop.NAME)["point_id"])
        assert store.step_result(active_loop.NAME, "round1/block1") is None
    assert before == [pose.point_id for pose in planned.poses[:2]]  # block 1 was measured and kept
    with session_on(loop["config"], path) as session:
        active_loop.PROCEDURE(session, rounds=1, poses=10, block=2)
    with CampaignStore(path, create=False) as store:
        after = list(store.measurements(active_loop.NAME)["point_id"])
        assert store.step_result(active_loop.NAME, "round1/block1") is not None
    assert after[: len(before)] == before and len(after) == len(set(after))
    assert len(after) > len(before)  # and went on with block 2


@pytest.mark.parametrize(
    "flags, says",
    [
        (["--rounds", "0"], "--rounds 0 is out of range: allowed 1..5"),
        (["--poses", "0"], "--poses 0 is out of range"),
    ],
)
def test_bad_parameters_are_refused_before_anything_connects(tmp_path, capsys, flags, says):
    (tmp_path / "cell.toml").write_text(sim_cell_toml().replace("127.0.0.9", OFFLINE_HOST))
    code, _, err = hil_in_process(
        "run",
        "active_loop",
        "--cell",
        "cell.toml",
        "--campaign",
        "c.sqlite",
        *flags,
        cwd=tmp_path,
        capsys=capsys,
    )
    assert code != 0 and says in err
    assert not (tmp_path / "c.sqlite").exists()


def test_a_campaign_without_a_grid_is_refused_before_anything_connects(tmp_path, capsys):
    (tmp_path / "cell.toml").write_text(sim_cell_toml().replace("127.0.0.9", OFFLINE_HOST))
    code, _, err = hil_in_process(
        "run", "active_loop", "--cell", "cell.toml", "--campaign", "c.sqlite", cwd=tmp_path, capsys=capsys
    )
    assert code != 0 and "grid" in err
    CampaignStore(tmp_path / "empty.sqlite").close()
    code, _, err = hil_in_process(
        "run", "active_loop", "--cell", "cell.toml", "--campaign", "empty.sqlite", cwd=tmp_path, capsys=capsys
    )
    assert code != 0 and "run `hil run grid_sampling`" in err


def test_the_same_campaign_is_diagnosed_once_for_the_plan_and_the_first_round(monkeypatch):
    """`hil run active_loop` plans before connecting and then runs the loop: one diagnosis of the same rows,
    another as soon as a row differs."""
    from types import SimpleNamespace

    import pandas as pd

    calls: list[int] = []
    monkeypatch.setattr(
        active_rounds, "run_diagnosis", lambda train, *a, **k: calls.append(len(train)) or len(calls)
    )
    monkeypatch.setattr(active_rounds._Campaign, "validation", lambda self: None)
    store = SimpleNamespace(step_result=lambda *a: None)
    config = SimpleNamespace(nominal="ur10")
    train = pd.DataFrame({"q1_rad": [0.1, 0.2], "x_mm": [1.0, 2.0], "smr": [1, 1]})
    first = active_rounds._Campaign(store, config, 0).diagnose(train)
    again = active_rounds._Campaign(store, config, 0).diagnose(train.copy())
    assert first == again and calls == [2]
    longer = pd.concat([train, train.iloc[:1].assign(x_mm=3.0)], ignore_index=True)
    assert active_rounds._Campaign(store, config, 0).diagnose(longer) != first and calls == [2, 3]
    moved = train.assign(x_mm=[1.0, 2.5])
    active_rounds._Campaign(store, config, 0).diagnose(moved)
    assert calls == [2, 3, 2]
    # a round resumed in the same process asks again for earlier rows' diagnoses: the last few are kept
    assert active_rounds._Campaign(store, config, 0).diagnose(train.copy()) == first and calls == [2, 3, 2]
    for k in range(active_rounds._DIAGNOSES_KEPT):
        active_rounds._Campaign(store, config, 0).diagnose(train.assign(x_mm=[1.0, 10.0 + k]))
    assert len(calls) == 3 + active_rounds._DIAGNOSES_KEPT  # a bounded cache: the oldest made room
    active_rounds._Campaign(store, config, 0).diagnose(train)
    assert len(calls) == 4 + active_rounds._DIAGNOSES_KEPT
