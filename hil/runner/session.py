"""The Session: everything a procedure needs, and the rules it keeps while a campaign runs.

A procedure receives a Session and nothing else: robot and tracker (as their Protocols), the campaign
store, the operator, the safety envelope, progress and the log. The Session keeps the runner's promises:
every commanded move is checked against the envelope along its whole path before the robot moves;
every measurement is committed to the store before the next motion; a point already recorded is never
measured again (re-running resumes); every fault and retry is an event in the store; on leaving, the robot
is stopped and the store closed, whatever happened.
"""

from __future__ import annotations

import logging
import math
import platform
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hil.data.store import P_COLUMNS, Q_COLUMNS, T_COLUMNS, Campaign, MeasurementRecord, StoreLogHandler
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.se3 import transform_points
from hil.instruments.robot import Robot, RobotError
from hil.instruments.tracker import (
    StreamingTracker,
    Tracker,
    TrackerError,
    TrackerMeasurement,
)
from hil.runner.cell_config import CellConfig
from hil.runner.controller_joints import kinematic_campaign, kinematic_robot
from hil.runner.engine import AttemptPolicy, CampaignStopped, Engine, PathOptions
from hil.runner.envelope import Envelope, EnvelopeError
from hil.runner.operator import Operator, OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import linear_path_joints
from hil.runner.procedure import Role
from hil.runner.progress import Progress
from hil.runner.registry import publisher

log = logging.getLogger("hil")

MOVE_ATTEMPTS = 3


@dataclass(frozen=True)
class RecordedPoints:
    """Recorded measurements as arrays (rows in measurement order)."""

    point_id: list[str]
    step: list[str]
    location: list[str]
    q_rad: np.ndarray  # (N, 6)
    T_base_flange: np.ndarray  # (N, 4, 4)
    p_tracker_m: np.ndarray  # (N, 3)

    @classmethod
    def from_frame(cls, df: pd.DataFrame) -> RecordedPoints:
        """From CampaignStore.measurements (flat columns)."""
        return cls(
            point_id=df["point_id"].tolist(),
            step=df["step"].tolist(),
            location=df["location"].tolist(),
            q_rad=df[list(Q_COLUMNS)].to_numpy(float).reshape(-1, 6),
            T_base_flange=df[list(T_COLUMNS)].to_numpy(float).reshape(-1, 4, 4),
            p_tracker_m=df[list(P_COLUMNS)].to_numpy(float).reshape(-1, 3),
        )


@dataclass
class Registration:
    """Tracker <-> robot base: T_tracker_base and how well the points fitted (from the registration step)."""

    T_tracker_base: np.ndarray
    rms_m: float


class Session:
    """Robot + tracker + campaign store + operator + envelope + progress + log, for one campaign."""

    def __init__(
        self,
        config: CellConfig,
        robot: Robot,
        tracker: Tracker,
        store: Campaign,
        operator: Operator,
        progress: Progress | None = None,
        station: dict | None = None,
        clock: Callable[[], float] | None = None,
    ):
        self.config = config
        # the one place joints cross to the controller's convention (a robot that couples its joints)
        self.robot = kinematic_robot(robot, config.coupling)
        self.store = kinematic_campaign(store, config.coupling)
        self.tracker = tracker
        self.operator = operator
        self.progress = progress or Progress(enabled=False)
        self.envelope: Envelope = config.envelope
        self.nominal: KinematicModel = config.nominal
        self.log = log
        self._station = station or {}
        # the measurements' timestamps (UNIX s): a simulated cell's own clock, else the tracker's (the host's)
        self._clock = clock
        self._log_handler = StoreLogHandler(store)
        self._closed = False
        self._step_cache: dict[tuple[str, str], dict | None] = {}
        self.engine = Engine(self)

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Session:
        log.addHandler(self._log_handler)
        if log.level == logging.NOTSET or log.level > logging.INFO:
            log.setLevel(logging.INFO)
        self.store.add_snapshot(
            {
                **self.config.snapshot(),
                "software": _software_versions(),
                "station": self._station,
                "started_s": time.time(),
            }
        )
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(interrupted=exc_type is not None and issubclass(exc_type, KeyboardInterrupt))

    def close(self, interrupted: bool = False) -> None:
        """Stop the robot, release the instruments and the operator, close the store; never hangs: robot and
        tracker are released side by side and given a bounded time (1 s after Ctrl-C, 10 s otherwise)."""
        if self._closed:
            return
        self._closed = True
        if interrupted:
            why = self.engine.stop_reason or "stopped by the operator (Ctrl-C)"
            self.event("interrupted", f"{why}; re-run the command to resume")

        def release_robot() -> None:
            try:
                self.robot.stop()
            finally:
                self.robot.close()

        _bounded([("robot", release_robot), ("tracker", self.tracker.close)], 1.0 if interrupted else 10.0)
        try:
            self.operator.close()
        finally:
            log.removeHandler(self._log_handler)
            self.store.close()

    # ------------------------------------------------------------------ store shortcuts
    def event(self, kind: str, message: str, **where) -> None:
        """Record a fault, retry or other happening in the campaign (and the log)."""
        log.info("%s: %s", kind, message)
        self.store.record_event(kind, message, **where)

    def recorded(self, procedure: str, step: str, point_id: str) -> bool:
        return self.store.has_measurement(procedure, step, point_id)

    # ------------------------------------------------------------------ cell knowledge from earlier steps
    def finish_step(self, procedure: str, step: str, result: dict) -> None:
        """Record a step's result (the registration, a tool fit, ...) for this and later sessions."""
        self.store.finish_step(procedure, step, result)
        self._step_cache.pop((procedure, step), None)

    def step_result(self, procedure: str, step: str) -> dict | None:
        """A step's latest result in this campaign (read once, then kept until the step is redone)."""
        key = (procedure, step)
        if key not in self._step_cache:
            self._step_cache[key] = self.store.step_result(procedure, step)
        return self._step_cache[key]

    @property
    def registration(self) -> Registration | None:
        """The latest tracker <-> base registration recorded in this campaign, if any."""
        result = self.step_result(*publisher(Role.REGISTRATION))
        if result is None:
            return None
        return Registration(np.array(result["T_tracker_base"], float), float(result["rms_mm"]) / 1e3)

    def require_registration(self) -> Registration:
        reg = self.registration
        if reg is None:
            raise CampaignStopped(
                "this campaign has no tracker-to-robot registration yet",
                "run `hil run registration` on the same campaign first",
            )
        return reg

    def nest_flange_m(self, nest: int) -> np.ndarray:
        """SMR nest centre in the flange frame: the tool fit's value when this campaign has one, else the drawing."""
        fit = self.step_result(*publisher(Role.TOOL))
        if fit is not None and str(nest) in fit.get("nests_flange_mm", {}):
            return np.array(fit["nests_flange_mm"][str(nest)], float) / 1e3
        return np.asarray(self.config.nests_flange_m[nest - 1], float)

    def predict_tracker_point(self, q: np.ndarray, p_flange_m: np.ndarray) -> np.ndarray | None:
        """Where the SMR at p_flange_m should be, tracker frame, for joints q (nominal model + registration)."""
        reg = self.registration
        if reg is None:
            return None
        T = forward_kinematics(self.nominal, np.atleast_2d(q))[0]
        p_base = T[:3, :3] @ np.asarray(p_flange_m, float) + T[:3, 3]
        return transform_points(reg.T_tracker_base, p_base[None])[0]

    def recorded_points(self, procedure: str, step: str | None = None) -> RecordedPoints:
        """The measurements recorded so far for a procedure (optionally one step), as arrays in order."""
        return RecordedPoints.from_frame(self.store.measurements(procedure, step))

    def pin_plan(self, plan: Plan) -> None:
        """Record the plan on first run; on a resume refuse a plan that differs (other options or config),
        since its point ids would no longer name the same poses."""
        q = plan.joints()
        ids = [p.point_id for p in plan.poses]
        pinned = self.step_result(plan.procedure, "plan")
        if pinned is None:
            self.finish_step(plan.procedure, "plan", {"point_ids": ids, "q_rad": q.round(9).tolist()})
            return
        same = pinned["point_ids"] == ids and np.allclose(
            np.asarray(pinned["q_rad"]).reshape(-1, 6), q, atol=1e-6
        )
        if not same:
            raise CampaignStopped(
                f"this campaign already holds a different {plan.procedure} plan",
                "re-run with the same options and cell config to resume it, or use a new --campaign file",
            )

    # ------------------------------------------------------------------ operator
    def ask(self, step: OperatorStep) -> None:
        """Have the operator carry out a manual step (recorded as an event)."""
        self.store.record_event("operator", step.text)
        self.operator.perform(step)

    # ------------------------------------------------------------------ motion
    def check_poses(self, q: np.ndarray, labels: list[str] | None = None) -> None:
        """Refuse joint sets (N, 6) whose tool points or wrist leave the envelope (raises EnvelopeError)."""
        self.envelope.check_poses(self.nominal, q, self.config.nests_flange_m, labels)

    def move_joints(self, q_target: np.ndarray, label: str = "") -> None:
        """Move to q_target along a path checked against the envelope before any motion: straight in joint
        space when that stays inside, else through the configured home pose (a detour, recorded as an
        event); recoverable faults are ridden through and the rest of the path is checked again."""
        q_target = np.asarray(q_target, float)
        for leg in self._legs(q_target, label):
            self._move_leg(leg, label)

    def _legs(self, q_target: np.ndarray, label: str) -> list[np.ndarray]:
        """The joint targets to move through: [q_target], or the safe detour the dry run's path check finds
        (Envelope.detour: through one or more intermediate poses) when only that is safe."""
        tools = self.config.nests_flange_m
        q_now = np.asarray(self.robot.joints(), float)
        try:
            self.envelope.check_joint_move(self.nominal, q_now, q_target, tools)
            return [q_target]
        except EnvelopeError as direct:
            legs = self.envelope.detour(self.nominal, q_now, q_target, tools, self.config.q_home_rad)
            if legs is None:
                raise direct from None
            self.event(
                "detour",
                f"the direct move to {label or 'the target'} would leave the envelope; going through "
                f"{len(legs) - 1} intermediate pose(s)",
                point_id=label or None,
            )
            return legs

    def _move_leg(self, q_target: np.ndarray, label: str) -> None:
        for attempt in range(1, MOVE_ATTEMPTS + 1):
            try:
                self.robot.move_joints(q_target)
                return
            except RobotError as exc:  # protective stop, lost connection, interrupted move: recover, retry
                self._robot_fault(exc, label, attempt)
            # after recovery the arm may stand anywhere along the old path: re-check from where it is
            self.envelope.check_joint_move(
                self.nominal, self.robot.joints(), q_target, self.config.nests_flange_m
            )

    def _robot_fault(self, exc: RobotError, label: str, attempt: int) -> None:
        self.event(
            "robot_fault",
            f"{type(exc).__name__} at {label or 'a move'}: {exc.message}",
            point_id=label or None,
        )
        if attempt >= MOVE_ATTEMPTS:
            raise CampaignStopped(
                f"the robot failed {attempt} times at {label}: {exc.message}", exc.remedy
            ) from exc
        try:
            self.robot.recover()
            self.event("retry", f"robot recovered; retrying {label or 'the move'}", point_id=label or None)
        except RobotError as again:
            raise CampaignStopped(f"the robot could not recover: {again.message}", again.remedy) from again

    def settle(self) -> None:
        self.robot.wait_settled(dwell_s=self.config.settle_s)

    def aim_point(self, pose: PlannedPose) -> np.ndarray | None:
        """Where on the flange the SMR of a pose sits, for aiming: the plan's, else its nest's (tool fit)."""
        if pose.p_flange_m is not None:
            return np.asarray(pose.p_flange_m, float)
        if pose.location.startswith("nest"):
            return self.nest_flange_m(int(pose.location.removeprefix("nest")))
        return None

    # ------------------------------------------------------------------ measurement
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
    ) -> MeasurementRecord | None:
        """Move to q_target, settle, aim, measure, and commit the record before anything else moves.

        Returns None when the point is already recorded (a resumed campaign skips it). The tracker is aimed
        at the point predicted from the robot's reported pose when the campaign has a registration and
        `p_flange_m` is given; otherwise it keeps the lock it has (tracking), and `reaim` (e.g. asking the
        operator) recovers a lost beam. Beam breaks and dropped links are retried, each an event.
        """
        if self.recorded(procedure, step, point_id):
            return None
        self.move_joints(q_target, label=point_id)
        self.settle()
        shots = shots or self.config.shots_per_point

        def once(attempt: int) -> MeasurementRecord:
            q_rad = np.asarray(self.robot.joints(), float)
            predicted = self.predict_tracker_point(q_rad, p_flange_m) if p_flange_m is not None else None
            if predicted is not None:
                self.tracker.point_at(predicted)
            elif attempt > 1 and reaim is not None:
                reaim()
            m = self.tracker.measure(shots)
            record = MeasurementRecord(
                procedure=procedure,
                step=step,
                point_id=point_id,
                q_target_rad=np.asarray(q_target, float),
                q_rad=q_rad,
                T_base_flange=np.asarray(self.robot.flange_pose(), float),
                p_tracker_m=m.p_tracker_m,
                spread_m=m.spread_m,
                std_m=m.std_m,
                shots=len(m.shots_m),
                rejected_shots=tuple(m.rejected_shots),
                smr=smr if location.startswith("nest") else 0,
                location=location,
                temperature_c=m.temperature_c,
                pressure_hpa=m.pressure_hpa,
                humidity_pct=m.humidity_pct,
                timestamp_s=m.timestamp_s if self._clock is None else self._clock(),
                extra={
                    "attempts": attempt,
                    **({"predicted_mm": (predicted * 1e3).tolist()} if predicted is not None else {}),
                    **_object_temperature(m),
                    **_robot_temperature(self.robot),
                    **(extra or {}),
                },
            )
            self.store.record_measurement(record)
            return record

        policy = AttemptPolicy(
            what=f"measurement at {point_id}",
            where=f"at {point_id}",
            remedy="clear the line of sight between tracker and SMR and check the tracker's connection, "
            "then re-run the same command: recorded points are kept and skipped",
            event_where={"procedure": procedure, "step": step, "point_id": point_id},
        )
        return self.engine.attempt(once, policy)

    # ------------------------------------------------------------------ paths (the SMR sampled while moving)
    def streaming_tracker(self, interval_s: float) -> StreamingTracker:
        """The tracker, checked (nothing moves, nothing is measured) to sample a moving SMR every interval_s."""
        tracker = self.tracker
        if not isinstance(tracker, StreamingTracker):
            raise CampaignStopped(
                f"the tracker ({type(tracker).__name__}) cannot sample a moving SMR",
                "use a tracker whose driver streams (emScon continuous time mode), or leave paths out",
            )
        try:
            tracker.check_stream(interval_s)
        except TrackerError as exc:
            raise CampaignStopped(
                f"the tracker cannot sample a moving SMR every {interval_s * 1e3:g} ms: {exc.message}",
                "use a tracker that offers a continuous time mode, or leave paths out",
            ) from exc
        return tracker

    def measure_path(
        self, procedure: str, step: str, q_start: np.ndarray, T_base_flange: np.ndarray, options: PathOptions
    ) -> dict:
        """One run of a path: move to its start (checked against the envelope), aim, stream the tracker while
        the robot moves linearly through the flange waypoints T_base_flange (K, 4, 4), and record every sample
        as the step's result before anything else moves. A run already recorded is returned as it was (a
        resumed campaign never repeats it); one recorded with other waypoints or speed is refused. Beam breaks
        are retried from the start, each an event. The whole path (every 5 mm) is checked reachable and inside
        the envelope before anything moves. Procedures ask for a run through the engine (`MeasurePath`)."""
        o = options
        speed_m_s, accel_m_s2, interval_s = o.speed_m_s, o.accel_m_s2, o.interval_s
        p_flange_m, approach_q_rad = o.p_flange_m, o.approach_q_rad
        T = np.asarray(T_base_flange, float)
        waypoints_mm = (T[:, :3, 3] * 1e3).round(6).tolist()
        recorded = self.step_result(procedure, step)
        if recorded is not None:
            same = np.allclose(recorded["waypoints_mm"], waypoints_mm, atol=1e-4)
            if not same or abs(recorded["speed_m_s"] - speed_m_s) > 1e-9:
                raise CampaignStopped(
                    f"{step} was recorded with another path or speed than this run would command",
                    "re-run with the same options and model, or use a new --campaign file",
                )
            return recorded
        _, joints = linear_path_joints(self.nominal, T, p_flange_m, q_start)
        outside = self.envelope.outside(self.nominal, joints.q, self.config.nests_flange_m)
        if not joints.usable.all() or outside.any():
            raise EnvelopeError(f"{step}: the linear path leaves the reach or the envelope; nothing moved")
        tracker = self.streaming_tracker(interval_s)

        def once(attempt: int) -> dict:
            if approach_q_rad is not None:
                self.move_joints(approach_q_rad, label=step + " approach")
            self.move_joints(q_start, label=step)
            self.settle()
            predicted = self.predict_tracker_point(self.robot.joints(), p_flange_m)
            if predicted is not None:
                tracker.point_at(predicted)
            tracker.start_stream(interval_s)
            try:
                self.robot.move_path(T, speed_m_s, accel_m_s2)
            finally:
                stream = tracker.stop_stream()
            result = {
                "speed_m_s": speed_m_s,
                "accel_m_s2": accel_m_s2,
                "interval_s": interval_s,
                "waypoints_mm": waypoints_mm,
                "attempts": attempt,
                "t_s": stream.t_s.tolist(),
                "p_tracker_mm": (stream.p_tracker_m * 1e3).tolist(),
            }
            self.finish_step(procedure, step, result)
            return result

        policy = AttemptPolicy(
            what=f"complete run of {step}",
            where=f"during {step}",
            remedy="clear the line of sight between tracker and SMR along the path, then re-run the same command",
            event_where={"procedure": procedure, "step": step},
            robot_fault=lambda exc, attempt: self._robot_fault(exc, step, attempt),
        )
        return self.engine.attempt(once, policy)


def _object_temperature(m: TrackerMeasurement) -> dict:
    """The object probe's reading for a record's extra, nothing when the tracker has no probe."""
    t = getattr(m, "object_temperature_c", None)
    return {} if t is None or not math.isfinite(t) else {"object_temperature_c": float(t)}


def _robot_temperature(robot: object) -> dict:
    """The robot's own temperature reading (its joint sensors) for a record's extra, nothing when the robot
    plug-in offers none (`temperature_c` is optional: not part of the Robot protocol)."""
    read = getattr(robot, "temperature_c", None)
    try:
        t = read() if callable(read) else None
    except RobotError as exc:  # an auxiliary reading: the measurement stands without it
        log.warning("no robot temperature for this measurement: %s", exc)
        return {}
    return {} if t is None or not math.isfinite(t) else {"robot_temperature_c": float(t)}


def _software_versions() -> dict:
    versions: dict[str, str | None] = {"python": platform.python_version(), "platform": platform.platform()}
    from importlib import metadata

    for package in ("hil", "ur-rtde", "pyserial", "numpy", "scipy", "pandas"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return versions


def abandoned_cleanups() -> list[str]:
    """Names of clean-up threads still running after their time ran out (a dead controller's driver)."""
    return [t.name for t in threading.enumerate() if t.name.startswith("hil-close-") and t.is_alive()]


def _bounded(actions: list[tuple[str, Callable[[], None]]], timeout_s: float) -> None:
    """Run clean-up actions side by side in helper threads and stop waiting after timeout_s in all (a dead
    controller must not keep a stopping process hanging); failures are logged, never raised."""
    errors: dict[str, BaseException] = {}

    def guarded(name: str, action: Callable[[], None]) -> Callable[[], None]:
        def target() -> None:
            try:
                action()
            except BaseException as exc:  # noqa: BLE001 - clean-up must go on
                errors[name] = exc

        return target

    threads = [threading.Thread(target=guarded(n, a), name=f"hil-close-{n}", daemon=True) for n, a in actions]
    for thread in threads:
        thread.start()
    deadline = time.monotonic() + timeout_s
    for (name, _), thread in zip(actions, threads, strict=True):
        thread.join(max(0.0, deadline - time.monotonic()))
        if thread.is_alive():
            why = "the controller stops the arm when its connection drops; " if name == "robot" else ""
            log.warning(
                "the %s had not finished closing after %.1f s; hil leaves without waiting (%severy recorded "
                "point is kept)",
                name,
                timeout_s,
                why,
            )
        elif name in errors:
            log.warning("releasing the %s failed: %s", name, errors[name])
