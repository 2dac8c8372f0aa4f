"""The control program of ur-rtde 1.6.5, re-implemented: registers, the main loop's handshake, commands.

`ScriptRuntime` is mixed into `UrController`; it reads the command register and its arguments every
controller cycle, runs regular commands once (signalling done), realtime ones every cycle, starts and
supervises motions, and answers queries with the nominal model (the controller's beliefs). The
controller supplies the state it uses: `program`, the register arrays, `q_cmd`/`qd_cmd`, `motion`,
`model`/`kin`, `T_flange_tcp`, `cell` and the fault hooks.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from fakes.fast_kinematics import pose_from_transform
from fakes.ur_modes import NORMAL, PLAYING, RUNNING, STOPPED
from fakes.ur_motion import (
    JointMove,
    LinearMove,
    Motion,
    PathMove,
    PlannedMotion,
    SpeedMove,
    StopMove,
    track_pose,
)
from hil.geometry.coupling import JointCoupling
from hil.geometry.ik import IKOptions, solve_ik
from hil.geometry.kinematics import forward_kinematics, geometric_jacobian
from hil.geometry.se3 import invert, pose_to_transform, transform_to_pose

if TYPE_CHECKING:
    from fakes.cell import SimulatedCell
    from fakes.fast_kinematics import ArmKinematics
    from fakes.ur_script import ControlProgram
    from hil.geometry.collision import CellBodies
    from hil.geometry.kinematics import KinematicModel

log = logging.getLogger("fakes.ur_controller")

CONTACT_STEP_RAD = float(np.deg2rad(0.5))  # sampling of a colliding moveJ's path to find where it touches


class ScriptRuntime:
    """Register handshake and commands of the uploaded control program (see the module docstring)."""

    # The host's state this mixin reads and writes (`UrController.__init__` sets every one of them).
    cell: SimulatedCell
    model: KinematicModel  # the nominal model: the controller's beliefs
    arm_body: CellBodies | None  # the arm's own capsules: a moveJ into itself ends in a protective stop
    kin: ArmKinematics
    period_s: float
    robot_mode: int
    safety_mode: int
    runtime_state: int
    in_int: list[int]
    in_double: list[float]
    out_int: list[int]
    out_double: list[float]
    speed_slider: float
    payload: tuple[float, tuple[float, ...]]  # mass (kg), centre of gravity (m)
    _last_ii0_write: float
    _watchdog_period_s: float
    program: ControlProgram | None
    _executing: bool
    _blocking: str | None  # the sync command waiting for its motion to end
    motion: Motion | None
    _motion_fresh: bool
    _motion_is_async: bool
    _async_op_id: int
    _async_counter: int
    q_cmd: np.ndarray  # kinematic joints, as every other joint state here; the wire speaks the controller's
    qd_cmd: np.ndarray
    actual_q: np.ndarray
    coupling: (
        JointCoupling | None
    )  # how this controller reports its joints (hil.geometry.coupling); None: kinematic
    _q_history: deque[np.ndarray]
    T_flange_tcp: np.ndarray
    moves_started: int
    last_move: dict[str, Any]
    _move_started_at: float
    _still_ticks: int

    if TYPE_CHECKING:  # the host's methods this mixin calls

        def _halt_program(self, new_state: int) -> None: ...

        def _fire_planned_faults(self, motion: Motion) -> None: ...

        def trigger_protective_stop(self, why: str) -> None: ...

    # ---------------------------------------------------------------- registers
    def _loaded(self) -> ControlProgram:
        """The control program whose commands run: the host runs the script cycle only once one is loaded."""
        program = self.program
        if program is None:
            raise RuntimeError("the control script ran with no program loaded")
        return program

    def _ii(self, k: int) -> int:
        return self.in_int[self._loaded().offset + k]

    def _id(self, k: int) -> float:
        return self.in_double[self._loaded().offset + k]

    def _ids(self, start: int, count: int = 6) -> np.ndarray:
        base = self._loaded().offset + start
        return np.array(self.in_double[base : base + count], float)

    def _oi(self, k: int, value: int) -> None:
        offset = self.program.offset if self.program else 0
        self.out_int[offset + k] = int(value)

    def _od(self, values) -> None:
        offset = self.program.offset if self.program else 0
        for i, v in enumerate(np.asarray(values, float).reshape(-1)):
            self.out_double[offset + i] = float(v)

    def _async_register(self, value: int) -> None:
        """The script's write_async_progress_register: 0 starts an op, >= 0 progress, < 0 finished."""
        self._async_counter = self._async_counter + 1 if self._async_counter < 127 else 0
        if value == 0:
            self._async_op_id = self._async_op_id + 1 if self._async_op_id < 127 else 0
        reg = self._async_counter * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._oi(2, reg)

    def _advance_motion(self, dt: float) -> None:
        motion = self.motion
        if motion is None or self.safety_mode != NORMAL or self.robot_mode != RUNNING:
            self.qd_cmd = np.zeros(6)
            self._still_ticks += 1
            return
        self._still_ticks = 0
        if self._motion_fresh:
            self._motion_fresh = False
            return
        self._fire_planned_faults(motion)
        if self.motion is not motion:  # a fault replaced or ended it
            return
        segment = getattr(motion, "i", None)
        try:
            q, qd = motion.advance(dt * self.speed_slider, self.q_cmd)
        except ValueError as exc:
            log.error("motion aborted: %s", exc)
            q, qd = self.q_cmd, np.zeros(6)
            motion.finished = True
        active = motion.current if isinstance(motion, PathMove) else motion  # a path's running segment
        contact = active.contact_at if isinstance(active, PlannedMotion) else None
        if isinstance(active, PlannedMotion) and contact is not None and active.fraction() >= contact:
            # the arm meets itself: it stops where it touches
            self.q_cmd = active.q_at(contact)
            kind = "moveJ" if isinstance(active, JointMove) else "moveL"
            self.trigger_protective_stop(f"self-collision {100 * contact:.0f} % along a {kind}")
            return
        self.q_cmd, self.qd_cmd = np.asarray(q, float), np.asarray(qd, float) * self.speed_slider
        if isinstance(motion, PathMove) and motion.i != segment and not motion.finished:
            self._async_register(motion.progress)  # signal_async_progress(waypoint index)
        if motion.finished:
            log.debug("motion %s finished", type(motion).__name__)
            if self.last_move and self.last_move["finished_s"] is None:
                self.last_move["finished_s"] = self.cell.time_s
            self.motion = None
            self.qd_cmd = np.zeros(6)
            if self._motion_is_async:
                self._motion_is_async = False
                self._async_register(-1)
            if self._blocking:
                self._blocking = None
                self._oi(0, 2)
                self._executing = True

    # ---------------------------------------------------------------- script emulation
    def _script_cycle(self) -> None:
        if self._blocking:
            return
        cmd = self._ii(0)
        program = self._loaded()
        if cmd in program.realtime_commands:
            self._realtime(cmd)
            self._oi(0, 1)
        elif cmd == 0:
            self._executing = False
            self._oi(0, 1)
        elif not self._executing:
            if cmd == 255:
                self._halt_program(STOPPED)
                return
            log.debug("command %d", cmd)
            try:
                blocking = self._command(cmd)
            except ValueError as exc:
                log.error("command %d rejected: %s", cmd, exc)
                blocking = False
            if self.runtime_state != PLAYING:
                return
            if blocking:
                self._blocking = f"cmd {cmd}"
            else:
                self._oi(0, 2)
                self._executing = True

    def _command(self, cmd: int) -> bool:
        """Execute a regular command; True if it blocks until its motion ends."""
        if cmd in (1, 2, 3, 4):
            return self._move(cmd)
        if cmd == 45:
            return self._path_move()
        if cmd in (15, 16):  # speedStop, servoStop
            return self._stop_motion(decel=self._id(0) or 10.0, blocking=True)
        if cmd in (33, 34):  # stopL, stopJ
            decel = self._id(0)
            if cmd == 33:
                decel = self._joint_decel_for_tool(decel)
            return self._stop_motion(decel=decel or 2.0, blocking=not self._ii(1), is_async=bool(self._ii(1)))
        if cmd == 29:
            self.T_flange_tcp = pose_to_transform(self._ids(0))
        elif cmd == 40:
            self._od(transform_to_pose(self.T_flange_tcp))
        elif cmd == 43:
            self._od(self._tcp_pose(self.actual_q, self.T_flange_tcp))
        elif cmd == 44:
            self._od(self._tcp_pose(self.joints_in(self._ids(0)), pose_to_transform(self._ids(6))))
        elif cmd in (30, 46, 60, 61):
            self._inverse_kinematics(cmd)
        elif cmd == 47:
            self._oi(1, int(self.motion is None and self._still_ticks > 1))
        elif cmd in (36, 37):
            q = (
                self.joints_in(self._ids(0))
                if cmd == 37
                else self._ik(pose_to_transform(self._ids(0)) @ invert(self.T_flange_tcp))
            )
            self._oi(1, int(q is not None and bool(self.model.within_limits(q))))
        elif cmd == 31:
            self.trigger_protective_stop("triggerProtectiveStop")
        elif cmd == 39:
            self._od(transform_to_pose(pose_to_transform(self._ids(0)) @ pose_to_transform(self._ids(6))))
        elif cmd == 28:
            self._od(self._target_waypoint())
        elif cmd in (17, 65):
            self.payload = (self._id(0), tuple(self._ids(1, 3)))
        elif cmd == 35:
            frequency = self._id(0)
            self._watchdog_period_s = 1.0 / frequency if frequency > 0 else 0.0
            self._last_ii0_write = time.monotonic()
        elif cmd in (54, 64):
            self._oi(1, 0)
        # every other command (payload, gravity, teach mode, freedrive, force settings, ...) is
        # acknowledged without a modelled effect: it still signals done, never a silent stall
        return False

    def _realtime(self, cmd: int) -> None:
        if cmd == 9:  # speedJ
            self._speed(self.joints_in(self._ids(0)), self._id(6))
        elif cmd == 10:  # speedL: tool speed mapped through the nominal Jacobian
            J = geometric_jacobian(self.model, self.q_cmd[None])[0]
            self._speed(np.linalg.lstsq(J, self._ids(0), rcond=None)[0], self._id(6))
        elif cmd == 11:  # servoJ
            self._servo(self.joints_in(self._ids(0)))
        elif cmd == 24:  # servoL
            target = pose_to_transform(self._ids(0)) @ invert(self.T_flange_tcp)
            self._servo(track_pose(self.model, self.q_cmd, target, iterations=5))
        elif cmd == 26:
            self._od([self.period_s])
        elif cmd == 27:
            steps = max(0, min(self._ii(1), len(self._q_history) - 1))
            self._od(self.joints_out(self._q_history[steps] if self._q_history else self.actual_q))
        elif cmd == 38:
            self._od(np.zeros(6))
        elif cmd == 58:
            self._od(pose_from_transform(self.kin.fk(self.actual_q)))
        elif cmd == 25:
            self._oi(1, 0)

    def _speed(self, qd: np.ndarray, accel: float) -> None:
        accel = accel if accel > 0 else 1.4
        if isinstance(self.motion, SpeedMove):
            self.motion.retarget(qd, accel)
        else:
            self._start_motion(SpeedMove(self.qd_cmd, qd, accel), is_async=False, count=False)

    def _servo(self, q: np.ndarray) -> None:
        self.motion = None
        self.qd_cmd = (q - self.q_cmd) / self.period_s
        self.q_cmd = np.asarray(q, float)

    def _move(self, cmd: int) -> bool:
        target, v, a, is_async = self._ids(0), self._id(6), self._id(7), bool(self._ii(1))
        if cmd == 1:
            motion: Motion = JointMove(self.q_cmd, self._checked_joints(target), v, a)
        elif cmd == 2:
            q = self._ik(pose_to_transform(target) @ invert(self.T_flange_tcp))
            if q is None:
                raise ValueError(f"moveJ_IK: no inverse kinematics solution for {np.round(target, 4)}")
            motion = JointMove(self.q_cmd, q, v, a)
        elif cmd == 3:
            motion = LinearMove(
                self.model, self.q_cmd, pose_to_transform(target) @ invert(self.T_flange_tcp), v, a
            )
        else:
            T_flange = forward_kinematics(self.model, self._checked_joints(target)[None])[0]
            motion = LinearMove(self.model, self.q_cmd, T_flange, v, a)
        self._start_motion(motion, is_async)
        return not is_async

    def _path_move(self) -> bool:
        segments = self._loaded().path
        if not segments:
            return False
        self._start_motion(PathMove(list(segments), self.q_cmd, self._path_segment), bool(self._ii(1)))
        return not bool(self._ii(1))

    def _path_segment(self, segment: tuple, q_start: np.ndarray) -> Motion:
        kind, target, v, a, _r, _index = segment
        target = np.asarray(target, float)
        q: np.ndarray | None
        if kind.endswith("_joints"):
            q = self._checked_joints(target)
            T = forward_kinematics(self.model, q[None])[0]
        else:
            T = pose_to_transform(target) @ invert(self.T_flange_tcp)
            q = self._ik(T, q_start)
        segment_motion: PlannedMotion
        if kind.startswith("movej"):
            if q is None:
                raise ValueError(f"path waypoint {np.round(target, 4)} has no inverse kinematics solution")
            segment_motion = JointMove(q_start, q, v, a)
        else:
            segment_motion = LinearMove(self.model, q_start, T, v, a)
        self._mark_contact(segment_motion)  # each leg of a path is checked as it starts
        return segment_motion

    def _mark_contact(self, motion: Motion) -> None:
        """Where a moveJ or moveL would first drive the arm into itself (`contact_at`), when it would."""
        if self.arm_body is not None and isinstance(motion, PlannedMotion):
            fractions, q = motion.joint_path()
            motion.contact_at = self._self_contact(self.arm_body, fractions, q)

    def _self_contact(self, body: CellBodies, fractions: np.ndarray, q_path: np.ndarray) -> float | None:
        """Where along a joint path (fractions (K,) with joints (K, n), straight joint moves between them)
        the arm's own body, the capsules of its robot file on the nominal model, first touches itself (no
        margin: a real arm's protective stop comes on contact); None when the path check certifies every
        leg clear. Only the arm itself: the controller knows no tool or cell around it. In the first leg
        that is not certified, the contact is found on samples every CONTACT_STEP_RAD of the leading
        joint's travel, then bisected to a micro-fraction of the leg."""
        first = body.path_collisions(self.model, q_path[:-1], q_path[1:])
        legs = np.flatnonzero(~np.isnan(first))
        if not legs.size:
            return None
        leg = int(legs[0])
        s0, s1 = float(fractions[leg]), float(fractions[leg + 1])
        q_start, delta = q_path[leg], q_path[leg + 1] - q_path[leg]
        samples = int(np.ceil(np.max(np.abs(delta)) / CONTACT_STEP_RAD)) + 2
        s = np.linspace(0.0, 1.0, samples)
        touching = body.pair_slack_m(self.model, q_start + s[:, None] * delta).min(axis=1) < 0
        if not touching.any():
            return s0 + float(first[leg]) * (s1 - s0)  # a graze between samples: where the check found it
        k = int(np.argmax(touching))
        if k == 0:
            return s0
        clear, touch = s[k - 1], s[k]
        for _ in range(20):
            mid = 0.5 * (clear + touch)
            if body.pair_slack_m(self.model, (q_start + mid * delta)[None]).min() < 0:
                touch = mid
            else:
                clear = mid
        return s0 + float(touch) * (s1 - s0)

    def _checked_joints(self, q_wire: np.ndarray) -> np.ndarray:
        """A joint target as the client sent it (the controller's joints), kinematic, within the limits."""
        q_wire = np.asarray(q_wire, float)
        q = self.joints_in(q_wire)
        if not np.all(np.isfinite(q)) or not bool(self.model.within_limits(q)):
            raise ValueError(f"joint target outside the limits: {np.round(q_wire, 4)}")
        if self.coupling is not None and not bool(self.coupling.within_limits(q_wire)[0]):
            raise ValueError(f"joint target beyond the joint interaction limits: {np.round(q_wire, 4)}")
        return q

    def joints_in(self, q_wire: np.ndarray) -> np.ndarray:
        """Joints (or joint speeds) a client sent, in the controller's convention, as the kinematic ones."""
        q_wire = np.asarray(q_wire, float)
        return q_wire if self.coupling is None else self.coupling.to_kinematic(q_wire[None])[0]

    def joints_out(self, q: np.ndarray) -> np.ndarray:
        """Kinematic joints (or joint speeds) as this controller reports them."""
        q = np.asarray(q, float)
        return q if self.coupling is None else self.coupling.to_controller(q[None])[0]

    def _kill_async_move(self) -> None:
        """stop_async_move: kill a running async move, keeping its velocity for a following stop."""
        if self.motion is not None and self._motion_is_async:
            self.motion = None
            self._motion_is_async = False
            self._async_register(-1)

    def _start_motion(self, motion: Motion, is_async: bool, count: bool = True) -> None:
        self._kill_async_move()
        self._mark_contact(motion)
        self.motion = motion
        self._motion_fresh = True  # its first setpoint comes on the next cycle
        self._motion_is_async = is_async
        if is_async:
            self._async_register(0)
        if count:
            self.moves_started += 1
            self._move_started_at = self.cell.time_s
            self.last_move = {
                "kind": type(motion).__name__,
                "planned_duration_s": getattr(motion, "duration", None),
                "started_s": self.cell.time_s,
                "finished_s": None,
            }

    def _stop_motion(self, decel: float | None, blocking: bool = False, is_async: bool = False) -> bool:
        """Decelerate the current motion to rest (decel None: stop dead). True if the caller waits."""
        self._kill_async_move()
        if decel is None or not np.any(self.qd_cmd):
            self.motion = None
            self.qd_cmd = np.zeros(6)
            return False
        self.motion = StopMove(self.qd_cmd, decel)
        self._motion_fresh = True
        log.debug("stop: from %s over %.3f s", np.round(self.qd_cmd, 4), self.motion.duration)
        if is_async:  # the script's stop thread reports through the async progress register
            self._motion_is_async = True
            self._async_register(0)
        return blocking

    def _joint_decel_for_tool(self, tool_decel: float) -> float:
        """A joint deceleration that stops the tool at about tool_decel (m/s^2)."""
        J = geometric_jacobian(self.model, self.q_cmd[None])[0]
        tool_speed = float(np.linalg.norm(J[:3] @ self.qd_cmd))
        joint_speed = float(np.max(np.abs(self.qd_cmd)))
        if tool_speed < 1e-9 or tool_decel <= 0:
            return tool_decel
        return tool_decel * joint_speed / tool_speed

    def _target_waypoint(self) -> list[float] | np.ndarray:
        motion = self.motion
        if isinstance(motion, JointMove):
            return self._tcp_pose(motion.q_end, self.T_flange_tcp)
        if isinstance(motion, LinearMove):
            return transform_to_pose(motion.T_end @ self.T_flange_tcp)
        return self._tcp_pose(self.q_cmd, self.T_flange_tcp)

    # ---------------------------------------------------------------- kinematics (nominal model)
    def _tcp_pose(self, q: np.ndarray, T_flange_tcp: np.ndarray) -> list[float]:
        return pose_from_transform(self.kin.fk(np.asarray(q, float)) @ T_flange_tcp)

    def flange_pose_of(self, q: np.ndarray) -> np.ndarray:
        """T_base_flange (4, 4) of joints q on the nominal model (what the controller believes)."""
        return np.asarray(self.kin.fk(np.asarray(q, float)), float)

    def _ik(self, T_base_flange: np.ndarray, q_seed: np.ndarray | None = None) -> np.ndarray | None:
        """Joints reaching the flange pose on the nominal model, nearest the seed; None if unreachable."""
        seed = self.q_cmd if q_seed is None else np.asarray(q_seed, float)
        result = solve_ik(
            self.model, T_base_flange[None], q_seed=seed[None], q_near=seed, options=IKOptions(restarts=5)
        )
        return np.asarray(result.q[0], float) if bool(result.success[0]) else None

    def _inverse_kinematics(self, cmd: int) -> None:
        target = pose_to_transform(self._ids(0)) @ invert(self.T_flange_tcp)
        seed = self.joints_in(self._ids(6)) if cmd in (30, 61) and np.any(self._ids(6)) else None
        q = self._ik(target, seed)
        if cmd in (60, 61):
            self._oi(1, int(q is not None))
        else:
            self._od(self.joints_out(q) if q is not None else np.zeros(6))
