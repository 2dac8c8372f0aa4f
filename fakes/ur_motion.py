"""Motion generation of the fake UR controller: trapezoidal joint and linear moves, speedJ, stops.

Every motion is advanced in simulated seconds and yields the commanded joints each tick. Linear moves
interpolate the flange pose (position straight, rotation by slerp) and track it with a few damped
Newton steps on the nominal model per tick, so the controller's belief follows a straight line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fakes.fast_kinematics import ArmKinematics, rotvec_from_matrix
from hil.geometry.kinematics import KinematicModel


@dataclass(frozen=True)
class Trapezoid:
    """Trapezoidal (or triangular) velocity profile over a distance with speed and acceleration limits."""

    distance: float
    speed: float
    accel: float

    @property
    def _peak(self) -> float:
        return min(self.speed, math.sqrt(max(self.distance, 0.0) * self.accel))

    @property
    def duration(self) -> float:
        if self.distance <= 0:
            return 0.0
        v = self._peak
        return self.distance / v + v / self.accel

    def at(self, t: float) -> tuple[float, float]:
        """(position along the profile, speed) at time t."""
        if self.distance <= 0:
            return 0.0, 0.0
        v, a, total = self._peak, self.accel, self.duration
        t_acc = v / a
        if t <= 0:
            return 0.0, 0.0
        if t >= total:
            return self.distance, 0.0
        if t < t_acc:
            return 0.5 * a * t * t, a * t
        if t <= total - t_acc:
            return 0.5 * a * t_acc * t_acc + v * (t - t_acc), v
        tr = total - t
        return self.distance - 0.5 * a * tr * tr, a * tr


# How finely a linear move's joint path is sampled for the controller's self-collision check: the flange
# moves at most this far (or turns at most this much) between two samples, each joined to the next by a
# straight joint move, which the check certifies all along (hil.geometry.collision).
LINEAR_CHECK_STEP_M = 0.01
LINEAR_CHECK_STEP_RAD = float(np.deg2rad(2.0))


class Motion:
    """Base class: `advance(dt, q)` returns the new commanded joints and velocities."""

    finished = False
    progress = 0  # waypoint index reported through the async-progress register
    contact_at: float | None = None  # the fraction of its path where the arm meets itself, if it does

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class PlannedMotion(Motion):
    """A motion whose whole joint path is known when it starts (moveJ, moveL): the controller checks it
    against the arm's own body before the first setpoint."""

    def fraction(self) -> float:
        """How far along its path the move has come (0 to 1)."""
        raise NotImplementedError

    def joint_path(self) -> tuple[np.ndarray, np.ndarray]:
        """Fractions (K,) from 0 to 1 and the joints (K, n) there; straight joint moves between them."""
        raise NotImplementedError

    def q_at(self, fraction: float) -> np.ndarray:
        """The joints at a fraction of the path."""
        raise NotImplementedError


class JointMove(PlannedMotion):
    """moveJ: all joints start and stop together, timed by the joint that travels furthest."""

    def __init__(self, q_start: np.ndarray, q_end: np.ndarray, speed: float, accel: float):
        self.q_start = np.asarray(q_start, float).copy()
        self.q_end = np.asarray(q_end, float).copy()
        delta = self.q_end - self.q_start
        lead = float(np.max(np.abs(delta)))
        self.direction = delta / lead if lead > 0 else np.zeros(6)
        self.profile = Trapezoid(lead, _positive(speed, "speed"), _positive(accel, "acceleration"))
        self.t = 0.0
        self.lead = lead

    def fraction(self) -> float:
        return min(self.profile.at(self.t)[0] / self.lead, 1.0) if self.lead > 0 else 1.0

    def joint_path(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([0.0, 1.0]), np.stack([self.q_start, self.q_end])

    def q_at(self, fraction: float) -> np.ndarray:
        return self.q_start + fraction * (self.q_end - self.q_start)

    @property
    def duration(self) -> float:
        return self.profile.duration

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.t += dt
        s, v = self.profile.at(self.t)
        if self.t >= self.profile.duration:
            self.finished = True
            return self.q_end.copy(), np.zeros(6)
        return self.q_start + s * self.direction, v * self.direction


class LinearMove(PlannedMotion):
    """moveL: straight flange path, trapezoid on the translation (m) or the rotation (rad), the slower."""

    def __init__(
        self,
        model: KinematicModel | ArmKinematics,
        q_start: np.ndarray,
        T_base_flange_end: np.ndarray,
        speed: float,
        accel: float,
    ):
        self.kin = model if isinstance(model, ArmKinematics) else ArmKinematics(model)
        self.q = np.asarray(q_start, float).copy()
        self.q_start = self.q.copy()
        T0 = self.kin.fk(self.q)
        self.T_end = np.asarray(T_base_flange_end, float)
        self.p0, self.p1 = T0[:3, 3], self.T_end[:3, 3]
        self.R0 = T0[:3, :3]
        self.rotvec = rotvec_from_matrix(self.R0.T @ self.T_end[:3, :3])  # in the start frame
        length = float(np.linalg.norm(self.p1 - self.p0))
        angle = float(np.linalg.norm(self.rotvec))
        speed, accel = _positive(speed, "speed"), _positive(accel, "acceleration")
        by_length, by_angle = Trapezoid(length, speed, accel), Trapezoid(angle, speed, accel)
        self.profile = by_length if by_length.duration >= by_angle.duration else by_angle
        self.t = 0.0

    @property
    def duration(self) -> float:
        return self.profile.duration

    def fraction(self) -> float:
        if self.profile.distance <= 0:
            return 1.0
        return min(self.profile.at(self.t)[0] / self.profile.distance, 1.0)

    def joint_path(self) -> tuple[np.ndarray, np.ndarray]:
        """The flange's straight line every LINEAR_CHECK_STEP_M (or LINEAR_CHECK_STEP_RAD of its turn),
        each sample's joints tracked from the one before, as the move itself tracks them."""
        length = float(np.linalg.norm(self.p1 - self.p0))
        angle = float(np.linalg.norm(self.rotvec))
        steps = max(1, math.ceil(length / LINEAR_CHECK_STEP_M), math.ceil(angle / LINEAR_CHECK_STEP_RAD))
        fractions = np.linspace(0.0, 1.0, steps + 1)
        q = [self.q_start]
        for f in fractions[1:]:  # from 10 mm away, Newton's steps converge to machine precision in 4
            q.append(track_pose(self.kin, q[-1], self.pose_at(f), iterations=5))
        return fractions, np.stack(q)

    def q_at(self, fraction: float) -> np.ndarray:
        fractions, q = self.joint_path()
        before = q[int(np.searchsorted(fractions, fraction, side="right")) - 1]
        return track_pose(self.kin, before, self.pose_at(fraction), iterations=10)

    def pose_at(self, fraction: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.T_end[:3, :3] if fraction >= 1.0 else self.R0 @ rodrigues(fraction * self.rotvec)
        T[:3, 3] = self.p1 if fraction >= 1.0 else self.p0 + fraction * (self.p1 - self.p0)
        return T

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.t += dt
        s, _ = self.profile.at(self.t)
        done = self.t >= self.profile.duration
        fraction = 1.0 if done or self.profile.distance == 0 else s / self.profile.distance
        q_prev = self.q
        self.q = track_pose(self.kin, self.q, self.pose_at(fraction), iterations=10 if done else 3)
        self.finished = done
        qd = np.zeros(6) if done or dt <= 0 else (self.q - q_prev) / dt
        return self.q.copy(), qd


class PathMove(Motion):
    """moveJ/moveL through waypoints: one sub-move after another (blend radii are not modelled)."""

    def __init__(self, segments: list, start_q: np.ndarray, make_segment):
        self.segments = segments  # list of (kind, target, v, a, r, index)
        self.make_segment = make_segment
        self.current: Motion | None = None
        self.i = -1
        self.q = np.asarray(start_q, float).copy()

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.current is None or self.current.finished:
            self.i += 1
            if self.i >= len(self.segments):
                self.finished = True
                return self.q.copy(), np.zeros(6)
            self.progress = int(self.segments[self.i][5])
            self.current = self.make_segment(self.segments[self.i], self.q)
        self.q, qd = self.current.advance(dt, self.q)
        if self.current.finished and self.i == len(self.segments) - 1:
            self.finished = True
        return self.q.copy(), qd


class SpeedMove(Motion):
    """speedJ: ramp the joint velocities towards a target at the given acceleration; runs until replaced."""

    def __init__(self, qd_start: np.ndarray, qd_target: np.ndarray, accel: float):
        self.qd = np.asarray(qd_start, float).copy()
        self.target = np.asarray(qd_target, float).copy()
        self.accel = _positive(accel, "acceleration")

    def retarget(self, qd_target: np.ndarray, accel: float) -> None:
        self.target = np.asarray(qd_target, float).copy()
        self.accel = _positive(accel, "acceleration")

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        diff = self.target - self.qd
        lead = float(np.max(np.abs(diff)))
        step = self.accel * dt
        self.qd = self.target.copy() if lead <= step else self.qd + diff * (step / lead)
        return q + self.qd * dt, self.qd.copy()


@dataclass
class StopMove(Motion):
    """Decelerate from the current joint velocities to rest, all joints reaching zero together."""

    qd: np.ndarray
    decel: float
    t: float = 0.0
    duration: float = field(init=False)

    def __post_init__(self) -> None:
        self.qd = np.asarray(self.qd, float).copy()
        self.decel = _positive(self.decel, "deceleration")
        self.duration = float(np.max(np.abs(self.qd))) / self.decel

    def advance(self, dt: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.t >= self.duration:
            self.finished = True
            return q.copy(), np.zeros(6)
        t_next = min(self.t + dt, self.duration)
        # distance under a linearly decreasing velocity between t and t_next
        f0, f1 = 1 - self.t / self.duration, 1 - t_next / self.duration
        q_new = q + self.qd * self.duration * 0.5 * (f0 * f0 - f1 * f1)
        self.t = t_next
        self.finished = self.t >= self.duration
        return q_new, self.qd * f1


def track_pose(
    model: KinematicModel | ArmKinematics, q: np.ndarray, T_target: np.ndarray, iterations: int = 3
) -> np.ndarray:
    """A few damped Newton steps moving q so the nominal flange reaches T_target (tracking a nearby pose)."""
    kin = model if isinstance(model, ArmKinematics) else ArmKinematics(model)
    q = np.asarray(q, float).copy()
    for _ in range(iterations):
        T, J = kin.fk_and_jacobian(q)
        err = np.concatenate([T_target[:3, 3] - T[:3, 3], rotvec_from_matrix(T_target[:3, :3] @ T[:3, :3].T)])
        if float(np.max(np.abs(err))) < 1e-13:
            break
        q = q + J.T @ np.linalg.solve(J @ J.T + 1e-10 * _EYE6, err)
    return q


_EYE6 = np.eye(6)


def rodrigues(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector."""
    angle = math.sqrt(float(rotvec @ rotvec))
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _positive(value: float, what: str) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be a positive number, got {value}")
    return value
