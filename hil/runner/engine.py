"""The engine: the one loop every measurement runs through, whoever decides what to measure next.

A procedure does not loop over the instruments itself. A fixed plan hands the engine its poses
(`Engine.visit`); an adaptive procedure (the pseudo-target loop, the active rounds) is a generator that
*yields* what to measure next as a typed request (`MeasurePose` for a point, `MeasurePath` for one run of a
path) and reads back what was measured (`record = yield MeasurePose(...)`), and how far it got (`Advance`:
the engine draws the progress and its ETA), and `Engine.run` drives it. The engine does the rest, the same way
for both: the envelope check of every pose it is handed (an adaptive procedure's too, at run time, before the
robot moves), the operator's manual steps, resume by recorded point (a recorded point is handed back, never
measured again), retries (`attempt`, one attempt loop for a point and for a path), progress, and pause and
stop between points (`request_pause`, `resume`, `request_stop`: Ctrl-C and any other button call the same
path). Recording stays where it was: each measurement is committed by the session before the next motion.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Generator, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

import numpy as np

from hil.data.store import Campaign, MeasurementRecord, OutcomeRecord, Verdict
from hil.errors import ActionableError
from hil.instruments.robot import RobotError
from hil.instruments.tracker import (
    NoTargetError,
    OutlierError,
    TrackerConnectionError,
    TrackerError,
    TrackerTimeoutError,
)
from hil.runner.envelope import EnvelopeError
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.procedure import Bound, Measurement
from hil.runner.progress import Progress

MEASURE_ATTEMPTS = (
    4  # a point (or a path) is given up after this many failed tries (beam breaks, dropped links)
)
LINK_BACKOFF_S = (
    0.2  # wait this many seconds x the attempt after a dropped tracker link (the driver reconnects)
)

T = TypeVar("T")
R = TypeVar("R")


class CampaignStopped(ActionableError, RuntimeError):  # noqa: N818 - reads as what happened, like KeyboardInterrupt
    """The campaign cannot go on by itself; `remedy` says what to do. Everything recorded stays recorded
    and re-running the same command resumes where it stopped."""

    def __init__(self, message: str, remedy: str):
        super().__init__(message, remedy)


class StopRequested(KeyboardInterrupt):  # noqa: N818 - reads as what happened, like KeyboardInterrupt
    """The run was asked to stop (Ctrl-C, a stop button): raised at the engine's next checkpoint, between two
    points, so the point in flight is recorded first. A KeyboardInterrupt, so Ctrl-C and a button leave the
    same way: the session stops the robot, keeps every point and records why."""


@dataclass(frozen=True)
class MeasurePose:
    """A request to the engine: measure the SMR at `pose` (or hand back its record when it is recorded).

    `shots`: tracker shots (None: the cell's); `aim`: aim the tracker at the point predicted from the robot's
    pose (False: keep the lock it has, before a registration exists); `reaim`: how to recover a lost beam
    without aiming (ask the operator, ...); `extra`: JSON-able notes recorded with the point; `strict`: a
    recorded point commanded at other joints is refused (an adaptive loop replaying a campaign); a plan
    pinned elsewhere skips its recorded points as they are. `approach_optional`: the pose's approach pose is
    passed when the move there stays inside the envelope, else skipped (an event) and the pose reached
    straight; otherwise an approach outside the envelope refuses the request before anything moves.
    """

    pose: PlannedPose
    shots: int | None = None
    aim: bool = True
    reaim: Callable[[], None] | None = None
    extra: dict = field(default_factory=dict)
    strict: bool = True
    approach_optional: bool = False


@dataclass(frozen=True)
class MeasurePath:
    """A request to the engine: one run of a path, streamed (hil.runner.session.Session.measure_path; the run
    recorded as the step's result, a recorded run handed back as it was). `options` are measure_path's."""

    procedure: str
    step: str
    q_start: np.ndarray
    T_base_flange: np.ndarray  # (K, 4, 4) flange waypoints, base frame
    options: PathOptions


@dataclass(frozen=True)
class PathOptions:
    """How a path is driven and streamed: tool speed and acceleration, the tracker's sample interval, the
    SMR's position on the flange, and the pose passed on the way to the start (None: straight there)."""

    speed_m_s: float
    accel_m_s2: float
    interval_s: float
    p_flange_m: np.ndarray
    approach_q_rad: np.ndarray | None = None


@dataclass(frozen=True)
class Advance:
    """A message to the engine: of the procedure's work `phase`, `done` of `total` units are finished. The
    engine shows it with an ETA (a terminal bar, plain lines in a log); nothing moves."""

    phase: str
    done: int
    total: int


Request = MeasurePose | MeasurePath | Advance
Reply = MeasurementRecord | dict | None  # a point's record, a path run's result, nothing for Advance
Measuring = Generator[Request, Reply, T]  # a procedure's loop: yields requests, returns T


class Cell(Protocol):
    """What the engine drives: the session's instruments and rules (hil.runner.session.Session)."""

    store: Campaign
    progress: Progress

    def check_poses(self, q: np.ndarray, labels: list[str] | None = None) -> None: ...

    def move_joints(self, q_target: np.ndarray, label: str = "") -> None: ...

    def settle(self) -> None: ...

    def ask(self, step: OperatorStep) -> None: ...

    def event(self, kind: str, message: str, **where: object) -> None: ...

    def pin_plan(self, plan: Plan) -> None: ...

    def measure_point(
        self,
        procedure: str,
        step: str,
        point_id: str,
        q_target: np.ndarray,
        *,
        smr: int,
        location: str,
        p_flange_m: np.ndarray | None = None,
        shots: int | None = None,
        reaim: Callable[[], None] | None = None,
        extra: dict | None = None,
    ) -> MeasurementRecord | None: ...

    def aim_point(self, pose: PlannedPose) -> np.ndarray | None: ...

    def measure_path(
        self, procedure: str, step: str, q_start: np.ndarray, T_base_flange: np.ndarray, options: PathOptions
    ) -> dict: ...

    def step_result(self, procedure: str, step: str) -> dict | None: ...


@dataclass(frozen=True)
class AttemptPolicy:
    """How one attempt loop words its events and its giving up: `what` is measured (`"measurement at p001"`),
    `where` the events' place (`"at p001"`), `remedy` after the last attempt; `robot_fault` handles a robot
    error between attempts (recover or raise), None lets it through."""

    what: str
    where: str
    remedy: str
    event_where: dict = field(default_factory=dict)
    robot_fault: Callable[[RobotError, int], None] | None = None


class Engine:
    """Owns the measurement loop of one session: requests in, records out; pause and stop between points."""

    def __init__(self, cell: Cell, sleep: Callable[[float], None] = time.sleep) -> None:
        self.cell = cell
        self._sleep = sleep
        self._state = threading.Condition()
        self._stop_reason: str | None = None
        self._paused = False
        self.holding = threading.Event()  # set while a pause holds the run (for a button to show it)
        self._setup: tuple[OperatorStep, ...] | None = None  # the SMR setup the operator last made
        self._recorded: dict[tuple[str, str], dict[str, MeasurementRecord]] = {}
        self._judging: Judging | None = None

    # ------------------------------------------------------------------ pause and stop (any thread)
    def request_stop(self, reason: str = "stopped by the operator") -> None:
        """Stop at the next checkpoint (the point in flight is recorded first); safe from any thread."""
        with self._state:
            if self._stop_reason is None:
                self._stop_reason = reason
            self._state.notify_all()

    def request_pause(self) -> None:
        """Hold before the next point until `resume` (or a stop); safe from any thread."""
        with self._state:
            self._paused = True

    def resume(self) -> None:
        with self._state:
            self._paused = False
            self._state.notify_all()

    @property
    def stop_reason(self) -> str | None:
        return self._stop_reason

    def checkpoint(self) -> None:
        """Between two points: wait while paused; raise StopRequested when a stop was asked for."""
        with self._state:
            if self._paused and self._stop_reason is None:
                self.cell.event("paused", "paused by the operator; the robot stands still")
                self.holding.set()
                try:
                    self._state.wait_for(lambda: not self._paused or self._stop_reason is not None)
                finally:
                    self.holding.clear()
                if self._stop_reason is None:
                    self.cell.event("resumed", "resumed by the operator")
            if self._stop_reason is not None:
                raise StopRequested(self._stop_reason)

    # ------------------------------------------------------------------ one attempt loop
    def attempt(self, try_once: Callable[[int], T], policy: AttemptPolicy) -> T:
        """`try_once(attempt)` until it returns, at most MEASURE_ATTEMPTS times: a beam break, a dropped link
        or too few consistent shots is an event and another attempt; a robot fault goes to the policy; any
        other tracker failure stops the campaign with the tracker's remedy."""
        last_error: Exception | None = None
        for attempt in range(1, MEASURE_ATTEMPTS + 1):
            if attempt > 1:
                self.checkpoint()
            try:
                return try_once(attempt)
            except NoTargetError as exc:
                last_error = exc
                self._retry_event(
                    "beam_break", f"no target {policy.where} (attempt {attempt}): {exc}", policy
                )
            except (TrackerConnectionError, TrackerTimeoutError) as exc:
                last_error = exc
                text = f"{type(exc).__name__} {policy.where} (attempt {attempt}): {exc}"
                self._retry_event("tracker_link", text, policy)
                self._sleep(LINK_BACKOFF_S * attempt)  # the driver reconnects on the next call
            except OutlierError as exc:
                last_error = exc
                text = f"too few consistent shots {policy.where} (attempt {attempt}): {exc}"
                self._retry_event("outliers", text, policy)
            except TrackerError as exc:
                raise CampaignStopped(
                    f"the tracker failed {policy.where}: {exc.message}",
                    f"{exc.remedy}; then re-run the same command to resume",
                ) from exc
            except RobotError as exc:
                if policy.robot_fault is None:
                    raise
                last_error = exc
                policy.robot_fault(exc, attempt)
        raise CampaignStopped(
            f"no {policy.what} after {MEASURE_ATTEMPTS} attempts ({type(last_error).__name__}: {last_error})",
            policy.remedy,
        )

    def _retry_event(self, kind: str, message: str, policy: AttemptPolicy) -> None:
        self.cell.event(kind, message, **policy.event_where)

    # ------------------------------------------------------------------ requests
    def run(self, procedure: Measuring[R]) -> R:
        """Drive a procedure's loop: serve each request it yields, send back what was measured, show its
        progress, return its value. The operator is asked for a setup before the first point of this run that
        needs it."""
        self._setup = None
        with self.cell.progress.phases() as update:
            try:
                request = next(procedure)
                while True:
                    reply: Reply = None
                    if isinstance(request, Advance):
                        update(request.phase, request.done, request.total)
                    elif isinstance(request, MeasurePath):
                        reply = self.serve_path(request)
                    else:
                        reply = self.serve(request)
                    request = procedure.send(reply)
            except StopIteration as finished:
                return finished.value

    def serve_path(self, request: MeasurePath) -> dict:
        """One run of a path: handed back as recorded when it is (nothing moves), else measured after the
        pause and stop checkpoint (the session checks the whole path against the reach and the envelope,
        retries through `attempt` and records the run before anything else moves)."""
        recorded = self.cell.step_result(request.procedure, request.step)
        if recorded is None:
            self.checkpoint()
        return self.cell.measure_path(
            request.procedure, request.step, request.q_start, request.T_base_flange, request.options
        )

    def serve(self, request: MeasurePose) -> MeasurementRecord:
        """One request: its recorded measurement when there is one (nothing moves), else check its pose
        against the envelope, have the operator make its setup, pass its approach pose and measure it."""
        pose = request.pose
        recorded = self.recorded_record(pose)
        if recorded is not None:
            if request.strict and not np.allclose(recorded.q_target_rad, pose.q_rad, atol=1e-6):
                raise CampaignStopped(
                    f"{pose.point_id} was recorded at other joints than this run would command",
                    "re-run with the same model and options, or use a new --campaign file",
                )
            return recorded
        self.checkpoint()
        checked = _pose_joints(pose, with_approach=not request.approach_optional)
        self.cell.check_poses(checked, [pose.point_id] * len(checked))
        if pose.setup != self._setup:
            self._set_up(pose)
            self._setup = pose.setup
        if pose.approach_q_rad is not None:
            self._approach(pose, optional=request.approach_optional)
        record = self.cell.measure_point(
            pose.procedure, pose.step, pose.point_id, pose.q_rad, smr=pose.smr, location=pose.location,
            p_flange_m=self.cell.aim_point(pose) if request.aim else None, shots=request.shots,
            reaim=request.reaim, extra=request.extra or None,
        )  # fmt: skip
        if record is None:  # recorded by another process between our read and now: read it back
            self._recorded.pop((pose.procedure, pose.step), None)
            record = self.recorded_record(pose)
            assert record is not None
        self._recorded[(pose.procedure, pose.step)][pose.point_id] = record
        return record

    def _approach(self, pose: PlannedPose, optional: bool) -> None:
        """Pass the pose's approach pose; an optional one the envelope refuses is skipped, as an event."""
        assert pose.approach_q_rad is not None
        try:
            self.cell.move_joints(pose.approach_q_rad, label=pose.point_id + " approach")
        except EnvelopeError as exc:  # checked before any motion: go straight instead
            if not optional:
                raise
            self.cell.event("approach_skipped", f"{pose.point_id}: {exc}", point_id=pose.point_id)

    def recorded_record(self, pose: PlannedPose) -> MeasurementRecord | None:
        """The pose's point as recorded in the campaign (read once per step, then kept), None if not yet."""
        key = (pose.procedure, pose.step)
        if key not in self._recorded:
            self._recorded[key] = {r.point_id: r for r in self.cell.store.records(*key)}
        return self._recorded[key].get(pose.point_id)

    def _set_up(self, pose: PlannedPose) -> None:
        """Ask the pose's manual steps; for steps at the pose, move there and settle first."""
        for step in pose.setup:
            self.cell.ask(step)
        if pose.at_pose:
            self.cell.move_joints(pose.q_rad, label=pose.point_id)
            self.cell.settle()
            for step in pose.at_pose:
                self.cell.ask(step)

    # ------------------------------------------------------------------ declared measurements, judged
    @contextmanager
    def judging(
        self, procedure: str, measurements: tuple[Measurement, ...], limits_si: dict[str, float]
    ) -> Iterator[None]:
        """While a procedure runs: the measurements it declared and its limits (SI, by limit name). When it
        ends normally, each declared measurement it did not report is recorded as not judged."""
        self._judging = Judging(procedure, {m.name: m for m in measurements}, limits_si)
        try:
            yield
            for m in measurements:
                if m.name not in self._judging.reported:
                    self._record(self._judging.judge(m, None, None, "the run gave no value"))
        finally:
            self._judging = None

    def measured(
        self, name: str, value_si: float | None, *, limit_si: float | None = None, note: str = ""
    ) -> OutcomeRecord:
        """A declared measurement's value (SI): judged against its declared limit (or `limit_si`, a limit the
        procedure computed at run time), recorded in the campaign before this returns, and returned."""
        if self._judging is None:
            raise RuntimeError(f"measurement {name} reported outside a procedure's run")
        declared = self._judging.declared.get(name)
        if declared is None:
            known = ", ".join(self._judging.declared) or "none"
            raise ValueError(
                f"{self._judging.procedure} declares no measurement {name!r} (declared: {known})"
            )
        outcome = self._judging.judge(declared, value_si, limit_si, note)
        self._judging.reported.add(name)
        self._record(outcome)
        return outcome

    def _record(self, outcome: OutcomeRecord) -> None:
        self.cell.store.record_outcome(outcome)
        if outcome.verdict is Verdict.FAIL:
            self.cell.event(
                "limit_failed",
                f"{outcome.measurement} {outcome.value:g} {outcome.unit} against the limit "
                f"{outcome.bound} {outcome.limit_value:g} {outcome.unit}",
                procedure=outcome.procedure,
            )

    # ------------------------------------------------------------------ a fixed plan
    def visit(self, plan: Plan, *, pin: bool = False, **options: object) -> int:
        """Visit every pose of a fixed plan that is not recorded yet, in order; returns how many were measured.

        The whole plan (and its approach poses) is checked against the envelope before anything moves; `pin`
        records the plan, or refuses a resume with another one; recorded points are skipped; progress counts
        the plan's points. `options`: those of MeasurePose (shots, aim, reaim, extra)."""
        self.cell.check_poses(plan.joints(), [p.point_id for p in plan.poses])
        approaches = [p.approach_q_rad for p in plan.poses if p.approach_q_rad is not None]
        if approaches:
            self.cell.check_poses(np.array(approaches))
        if pin:
            self.cell.pin_plan(plan)
        self._setup = None  # the operator is asked for the plan's first setup, whatever was asked before
        pending = [p for p in plan.poses if self.recorded_record(p) is None]
        total = len(plan.poses)
        with self.cell.progress.task(
            plan.procedure.replace("_", " "), total=total, done=total - len(pending)
        ) as advance:
            for pose in pending:
                self.serve(MeasurePose(pose, strict=False, **options))  # type: ignore[arg-type]
                advance()
        return len(pending)

    def requests(self, plan: Plan, **options: object) -> Iterator[MeasurePose]:
        """A fixed plan's poses as requests (for a generator that measures a plan among its own decisions)."""
        for pose in plan.poses:
            yield MeasurePose(pose, **options)  # type: ignore[arg-type]


def _pose_joints(pose: PlannedPose, with_approach: bool = True) -> np.ndarray:
    """The joints a request commands (its pose, and its approach pose when it has one), (K, 6)."""
    q = [np.asarray(pose.q_rad, float)]
    if with_approach and pose.approach_q_rad is not None:
        q.append(np.asarray(pose.approach_q_rad, float))
    return np.array(q)


@dataclass
class Judging:
    """The declared measurements of the procedure that runs, and what it reported so far."""

    procedure: str
    declared: dict[str, Measurement]
    limits_si: dict[str, float]
    reported: set[str] = field(default_factory=set)

    def judge(
        self, m: Measurement, value_si: float | None, limit_si: float | None, note: str
    ) -> OutcomeRecord:
        limit = limit_si if limit_si is not None else self.limits_si.get(m.limit) if m.limit else None
        return OutcomeRecord(
            self.procedure, m.name, value_si, m.si_unit, limit, m.bound.value, verdict(value_si, limit, m.bound),
            note or m.help,
        )  # fmt: skip


def verdict(value: float | None, limit: float | None, bound: Bound) -> Verdict:
    """Pass when the value keeps to its limit on the bounded side (equal passes); not judged without a
    finite value or a limit."""
    if value is None or limit is None or not math.isfinite(value):
        return Verdict.NOT_JUDGED
    within = value <= limit if bound is Bound.MAX else value >= limit
    return Verdict.PASS if within else Verdict.FAIL
