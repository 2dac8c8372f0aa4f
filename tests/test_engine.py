"""The engine owns the measurement loop: an adaptive procedure yields what to measure and reads back what was
measured; the engine checks each pose against the envelope before the robot moves, resumes by recorded point,
retries, and stops or pauses between points when asked (Ctrl-C and a stop button take the same path)."""

from __future__ import annotations

import io
import itertools
import threading

import numpy as np
import pytest

from hil.data.store import CampaignStore, MeasurementRecord
from hil.instruments.tracker import NoTargetError
from hil.runner.engine import Advance, AttemptPolicy, CampaignStopped, MeasurePose, Measuring, StopRequested
from hil.runner.envelope import EnvelopeError
from hil.runner.plan import PlannedPose
from hil.runner.procedure import Procedure
from hil.runner.progress import Progress
from procedures.registration import PROCEDURE as REGISTRATION
from tests.cli_in_process import run_hil
from tests.sim_session import running_cell, session_on

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    with running_cell(tmp_path_factory.mktemp("engine")) as (running, config):
        yield running, config


def _poses(config) -> list[PlannedPose]:
    return REGISTRATION.make_plan(config, poses=6).poses


def _adaptive(session, poses: list[PlannedPose], after_each=None) -> Measuring[list[MeasurementRecord]]:
    """An adaptive procedure in miniature: each pose is decided after the last one's record came back; no
    registration yet, so a broken beam is guided back by the operator."""
    got: list[MeasurementRecord] = []
    relock = poses[0].at_pose[0]
    for pose in poses:
        record = yield MeasurePose(pose, aim=False, reaim=lambda: session.ask(relock))
        got.append(record)
        if after_each is not None:
            after_each(len(got))
    return got


def _measured(campaign) -> list[str]:
    with CampaignStore(campaign, create=False) as store:
        return store.measurements("registration")["point_id"].tolist()


def test_a_stop_request_ends_the_run_after_the_point_in_flight_and_the_rerun_measures_only_the_rest(
    cell, tmp_path
):
    _, config = cell
    campaign = tmp_path / "c.sqlite"
    poses = _poses(config)
    with pytest.raises(StopRequested), session_on(config, campaign) as session:
        stop_after_two = lambda n: n == 2 and session.engine.request_stop("stop button")  # noqa: E731
        session.engine.run(_adaptive(session, poses, stop_after_two))
    assert _measured(campaign) == [p.point_id for p in poses[:2]]
    with CampaignStore(campaign, create=False) as store:
        events = store.events()
    stopped = events[events["kind"] == "interrupted"]["message"].tolist()
    assert stopped == ["stop button; re-run the command to resume"]

    measured_now: list[str] = []
    with session_on(config, campaign) as session:
        measure = session.measure_point

        def counting(*args, **kwargs):
            measured_now.append(args[2])
            return measure(*args, **kwargs)

        session.measure_point = counting  # type: ignore[method-assign]
        records = session.engine.run(_adaptive(session, poses))
    assert measured_now == [p.point_id for p in poses[2:]]  # the two recorded points are handed back
    assert [r.point_id for r in records] == [p.point_id for p in poses]
    assert _measured(campaign) == [p.point_id for p in poses]


def test_a_paused_run_holds_between_points_until_resumed(cell, tmp_path):
    _, config = cell
    campaign = tmp_path / "c.sqlite"
    poses = _poses(config)[:3]
    seen_while_held: list[list[str]] = []
    with session_on(config, campaign) as session:
        engine = session.engine

        def operator_button() -> None:
            assert engine.holding.wait(60)
            seen_while_held.append(_measured(campaign))
            engine.resume()

        button = threading.Thread(target=operator_button)
        button.start()
        engine.run(_adaptive(session, poses, lambda n: n == 1 and engine.request_pause()))
        button.join(60)
    assert seen_while_held == [[poses[0].point_id]]  # nothing measured while held
    assert _measured(campaign) == [p.point_id for p in poses]
    with CampaignStore(campaign, create=False) as store:
        kinds = store.events()["kind"].tolist()
    assert kinds.index("paused") < kinds.index("resumed")


def test_an_adaptive_pose_outside_the_envelope_is_refused_before_the_robot_moves(cell, tmp_path):
    _, config = cell
    campaign = tmp_path / "c.sqlite"
    first = _poses(config)[0]
    turned = np.tile(first.q_rad, (72, 1))
    turned[:, 1] += np.linspace(-np.pi, np.pi, 72)  # the shoulder swung until the tool leaves the envelope
    q_out = turned[config.envelope.outside(config.nominal, turned, config.nests_flange_m)][0]
    outside = PlannedPose("x1", "registration", "poses", q_out, "nest1")
    with session_on(config, campaign) as session:
        with pytest.raises(EnvelopeError):
            session.engine.run(_adaptive(session, [first, outside]))
        q_after = np.asarray(session.robot.joints(), float)
    np.testing.assert_allclose(q_after, first.q_rad, atol=1e-3)  # it stands where the last point was
    assert _measured(campaign) == [first.point_id]


def test_one_attempt_loop_retries_a_beam_break_and_gives_up_with_the_last_error(cell, tmp_path):
    _, config = cell
    with session_on(config, tmp_path / "c.sqlite") as session:
        policy = AttemptPolicy("measurement at p1", "at p1", "clear the beam", {"point_id": "p1"})
        tries: list[int] = []

        def breaks_twice(attempt: int) -> str:
            tries.append(attempt)
            if attempt < 3:
                raise NoTargetError("beam broken")
            return "measured"

        assert session.engine.attempt(breaks_twice, policy) == "measured"
        assert tries == [1, 2, 3]

        def always_breaks(attempt: int) -> str:
            raise NoTargetError("beam broken")

        with pytest.raises(CampaignStopped, match="no measurement at p1 after 4 attempts .*beam broken"):
            session.engine.attempt(always_breaks, policy)
        events = session.store.events()
    assert (events["kind"] == "beam_break").sum() == 2 + 4


def test_the_body_measures_the_plan_it_is_handed(cell, tmp_path):
    """A fixed plan is built once: the body executes the plan given to it, not one of its own."""
    _, config = cell
    campaign = tmp_path / "c.sqlite"
    planned = REGISTRATION.make_plan(config, poses=9)
    planned.poses = planned.poses[:7]  # what the caller checked and showed
    with session_on(config, campaign) as session:
        REGISTRATION(session, planned=planned, poses=9)
    assert _measured(campaign) == [p.point_id for p in planned.poses]


def test_hil_run_builds_the_plan_once_for_the_dry_run_check_and_the_run(cell, tmp_path, capsys, monkeypatch):
    _, config = cell
    built: list[str] = []
    plan_for = Procedure.plan_for

    def counted(self, *args, **kwargs):
        built.append(self.name)
        return plan_for(self, *args, **kwargs)

    monkeypatch.setattr(Procedure, "plan_for", counted)
    cell_toml = str(config.source)
    done = run_hil(
        "run", "registration", "--cell", cell_toml, "--campaign", str(tmp_path / "c.sqlite"), "--poses", "6",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert built == ["registration"]


def test_an_optional_approach_the_envelope_refuses_is_skipped_and_a_required_one_refuses_the_pose(
    cell, tmp_path
):
    _, config = cell
    campaign = tmp_path / "c.sqlite"
    first, second = _poses(config)[:2]
    turned = np.tile(second.q_rad, (72, 1))
    turned[:, 1] += np.linspace(-np.pi, np.pi, 72)
    q_out = turned[config.envelope.outside(config.nominal, turned, config.nests_flange_m)][0]
    via_outside = PlannedPose(
        second.point_id, "registration", "poses", second.q_rad, "nest1", approach_q_rad=q_out
    )

    def requests(optional: bool) -> Measuring[None]:
        yield MeasurePose(first, aim=False)
        yield MeasurePose(via_outside, aim=False, approach_optional=optional)

    with session_on(config, campaign) as session:
        with pytest.raises(EnvelopeError):
            session.engine.run(requests(optional=False))
        assert _measured(campaign) == [first.point_id]
        session.engine.run(requests(optional=True))
        session.engine.run(
            requests(optional=True)
        )  # a resume replays both: nothing moves, nothing is skipped
        events = session.store.events()
    assert _measured(campaign) == [first.point_id, second.point_id]
    skipped = events[events["kind"] == "approach_skipped"]
    assert skipped["point_id"].tolist() == [second.point_id]


def test_an_adaptive_procedure_reports_its_progress_to_the_engine_which_draws_it(cell, tmp_path):
    """A procedure yields `Advance` between its requests and opens no progress of its own: the engine shows
    each phase (here as the plain lines a log gets; a clock that moves 10 s per reading writes every one)."""
    _, config = cell
    poses = _poses(config)[:3]

    def counted(session) -> Measuring[int]:
        for done, pose in enumerate(poses):
            yield Advance("miniature loop", done, len(poses))
            record = yield MeasurePose(pose, aim=False, reaim=lambda: session.ask(poses[0].at_pose[0]))
            assert isinstance(record, MeasurementRecord)
        yield Advance("miniature loop", len(poses), len(poses))
        return len(poses)

    stream, ticks = io.StringIO(), itertools.count(step=10.0)
    with session_on(config, tmp_path / "c.sqlite") as session:
        session.progress = Progress(enabled=True, stream=stream, clock=lambda: next(ticks))
        assert session.engine.run(counted(session)) == 3
    lines = stream.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "miniature loop: 0/3 (0%)",  # the phase appears when first reported and is redrawn as it goes
        "miniature loop: 1/3 (33%)",
        "miniature loop: 2/3 (67%)",
        "miniature loop: 3/3 (100%)",
    ]
