"""Pose planners: pure functions of a nominal model and the cell's approximate geometry.

The same code plans on a real cell and on the simulated one: where the tracker stands (roughly, in the
robot base frame), a box to sample, a step; out come tool poses that keep the SMR facing the tracker,
joints from the nominal IK with unreachable and near-singular poses filtered out with a reason, and a
visiting order. Nothing here moves or measures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.ik import IKOptions, default_home, solve_ik
from hil.geometry.kinematics import KinematicModel, geometric_jacobian, link_frames
from hil.geometry.se3 import rotation_exp

# Smallest singular value of the position Jacobian (m/rad) below which a pose counts as near-singular:
# a joint error of 1e-5 rad would then move the tool by less than ~0.5 um in some direction, and
# nearby commands swing the wrist. UR wrist singularities (q5 ~ 0) fall far below it.
SINGULAR_SIGMA_M = 0.02


@dataclass(frozen=True)
class Box:
    """An oriented box in the robot base frame: centre (3,) and axes (3, 3), columns = half-extent vectors."""

    centre_m: np.ndarray
    axes_m: np.ndarray

    @classmethod
    def from_limits(cls, min_m: np.ndarray, max_m: np.ndarray) -> Box:
        lo, hi = np.asarray(min_m, float), np.asarray(max_m, float)
        if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
            raise ValueError(f"box limits need min < max on every axis, got {lo} .. {hi}")
        return cls(0.5 * (lo + hi), np.diag(0.5 * (hi - lo)))

    @property
    def half_extents_m(self) -> np.ndarray:
        return np.linalg.norm(self.axes_m, axis=0)

    def corners(self, fraction: float = 1.0) -> np.ndarray:
        """The 8 corners (8, 3), optionally shrunk towards the centre."""
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        return self.centre_m + fraction * signs @ self.axes_m.T

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (min, max) of the box."""
        c = self.corners()
        return c.min(axis=0), c.max(axis=0)


def workspace_box(nominal: KinematicModel, p_base_tracker_m: np.ndarray) -> Box:
    """A reachable box in front of the tracker, sized from the arm's link lengths (default sampling volume)."""
    reach = float(np.sum(np.abs(nominal.a)) + np.sum(np.abs(nominal.d[1:])) * 0.3)
    p = np.asarray(p_base_tracker_m, float)
    if np.linalg.norm(p[:2]) < 1e-6:
        raise ValueError("the tracker cannot stand on the robot's base axis; check tracker position_base_mm")
    towards = p[:2] / np.linalg.norm(p[:2])
    forward = np.array([towards[0], towards[1], 0.0])
    lateral = np.array([-towards[1], towards[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    half = np.array([0.22, 0.32, 0.22]) * reach
    centre = 0.55 * reach * forward + 0.25 * reach * up
    return Box(centre, np.column_stack([forward * half[0], lateral * half[1], up * half[2]]))


def grid_points(box: Box, step_m: float) -> np.ndarray:
    """Every vertex (M, 3) of a Cartesian grid of `step_m` centred in the box (the grid paper: 0.1-0.2 m)."""
    if not 0.02 <= step_m <= 0.5:
        raise ValueError(f"grid step {step_m * 1e3:g} mm is outside 20..500 mm (the papers use 100-200 mm)")
    half = box.half_extents_m
    ticks = [np.arange(-h, h + 1e-9, step_m) for h in half]
    ticks = [t - t.mean() for t in ticks]
    grid = np.stack(np.meshgrid(*ticks, indexing="ij"), axis=-1).reshape(-1, 3)
    return box.centre_m + grid @ (box.axes_m / half).T


def random_points(box: Box, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` uniform random points (count, 3) inside the box (held-out validation in the same volume)."""
    return box.centre_m + rng.uniform(-1, 1, (count, 3)) @ box.axes_m.T


def facing_poses(
    points_base_m: np.ndarray,
    p_base_tracker_m: np.ndarray,
    rng: np.random.Generator,
    tilt_deg: float = 20.0,
    roll_deg: float = 90.0,
) -> np.ndarray:
    """Tool poses T_base_tool (N, 4, 4) at the points whose z axis looks at the tracker.

    The facing direction is tilted by at most `tilt_deg` (the SMR stays inside its acceptance cone, 30 deg
    for a 1.5" SMR) and rolled up to +-`roll_deg` about it: diverse orientations, all visible.
    """
    points = np.atleast_2d(np.asarray(points_base_m, float))
    R = facing_rotations(points, p_base_tracker_m)
    count = len(points)
    tilt_axis = rng.normal(0, 1, (count, 2))
    tilt_axis /= np.linalg.norm(tilt_axis, axis=1, keepdims=True)
    tilt_angle = np.deg2rad(tilt_deg) * np.sqrt(rng.uniform(0, 1, count))
    tilt_vec = np.column_stack([tilt_axis * tilt_angle[:, None], np.zeros(count)])
    roll = np.deg2rad(roll_deg) * rng.uniform(-1, 1, count)
    roll_vec = np.column_stack([np.zeros((count, 2)), roll])
    tilt = rotation_exp(tilt_vec) @ rotation_exp(roll_vec)
    T = np.zeros((count, 4, 4))
    T[:, :3, :3] = R @ tilt
    T[:, :3, 3] = points
    T[:, 3, 3] = 1.0
    return T


def facing_rotations(points_base_m: np.ndarray, p_base_tracker_m: np.ndarray) -> np.ndarray:
    """Tool orientations R_base_tool (N, 3, 3) at the points whose z axis looks straight at the tracker."""
    points = np.atleast_2d(np.asarray(points_base_m, float))
    z = np.asarray(p_base_tracker_m, float) - points
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    helper = np.where(np.abs(z[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)


def rpy_rotation(rpy_rad: np.ndarray) -> np.ndarray:
    """R (3, 3) from roll, pitch, yaw about the base x, y, z axes: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    from scipy.spatial.transform import Rotation  # imported here: hil.geometry.se3 says why

    return Rotation.from_euler("xyz", np.asarray(rpy_rad, float)).as_matrix()


def fixed_poses(points_base_m: np.ndarray, R_base_tool: np.ndarray) -> np.ndarray:
    """Tool poses T_base_tool (N, 4, 4) at the points, all in the one orientation (the grid paper's setting)."""
    points = np.atleast_2d(np.asarray(points_base_m, float))
    T = np.tile(np.eye(4), (len(points), 1, 1))
    T[:, :3, :3] = np.asarray(R_base_tool, float)
    T[:, :3, 3] = points
    return T


@dataclass(frozen=True)
class JointPlan:
    """Joints for planned tool poses: `q` (N, 6) and, per pose, whether it is usable and why not."""

    q: np.ndarray
    usable: np.ndarray  # (N,) bool
    reason: np.ndarray  # (N,) str: "ok", "unreachable", "joint_limits", "singular", "max_iter", "envelope"

    def counts(self) -> dict[str, int]:
        values, counts = np.unique(self.reason, return_counts=True)
        return {str(v): int(c) for v, c in zip(values, counts, strict=True)}


def position_sigma_min_m(nominal: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray) -> np.ndarray:
    """Smallest singular value (N,) of the tool point's 3 x 6 position Jacobian with the wrist orientation
    rows scaled by 0.3 m: near zero at a shoulder, elbow or wrist singularity."""
    J = geometric_jacobian(nominal, q, p_flange_tool)
    J_scaled = np.concatenate([J[:, :3], 0.3 * J[:, 3:]], axis=1)
    return np.linalg.svd(J_scaled, compute_uv=False)[:, -1]


def plan_joints(
    nominal: KinematicModel,
    T_base_tool: np.ndarray,
    p_flange_tool_m: np.ndarray,
    q_near: np.ndarray | None = None,
    singular_sigma_m: float = SINGULAR_SIGMA_M,
    q_seed: np.ndarray | None = None,
    options: IKOptions | None = None,
) -> JointPlan:
    """Nominal IK of the tool poses (what the controller will be commanded), near `q_near` (from `q_seed`
    first where given: a chosen configuration), with poses that are unreachable, beyond joint limits or
    close to a singularity marked unusable with the reason."""
    q_ref = default_home(nominal) if q_near is None else np.asarray(q_near, float)
    result = solve_ik(
        nominal, T_base_tool, q_seed=q_seed, mode="pose", p_flange_tool=p_flange_tool_m, q_near=q_ref,
        options=options or IKOptions(),
    )  # fmt: skip
    reason = np.array(result.reason, dtype=object)
    usable = np.array(result.success, bool)
    if usable.any():
        sigma = position_sigma_min_m(nominal, result.q[usable], p_flange_tool_m)
        near_singular = np.zeros(len(usable), bool)
        near_singular[np.flatnonzero(usable)] = sigma < singular_sigma_m
        reason[near_singular] = "singular"
        usable &= ~near_singular
    return JointPlan(result.q, usable, reason.astype(str))


def wrist_points(nominal: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Origins of the wrist frames (joints 4, 5, 6) and the flange, (N, 4, 3) in the base frame."""
    frames = link_frames(nominal, np.atleast_2d(q))
    flange = frames[:, -1] @ nominal.T_last_flange
    return np.concatenate([frames[:, 4:7, :3, 3], flange[:, None, :3, 3]], axis=1)


def travel_order(q: np.ndarray, q_start: np.ndarray) -> np.ndarray:
    """Visiting order (indices) that keeps moves short: greedy nearest neighbour on the largest joint
    move (a joint move's duration is set by its largest joint travel)."""
    q = np.atleast_2d(q)
    left = np.ones(len(q), bool)
    order = np.empty(len(q), int)
    current = np.asarray(q_start, float)
    for k in range(len(q)):
        cost = np.max(np.abs(q - current), axis=1)
        cost[~left] = np.inf
        nxt = int(np.argmin(cost))
        order[k] = nxt
        left[nxt] = False
        current = q[nxt]
    return order


def random_order(count: int, rng: np.random.Generator) -> np.ndarray:
    """A random visiting order: consecutive moves of different joints are uncorrelated, which separates
    the backlash of different joints in the identification."""
    return rng.permutation(count)


def joint_move_time_s(
    q_from: np.ndarray, q_to: np.ndarray, speed_rad_s: float, accel_rad_s2: float
) -> np.ndarray:
    """Duration (N,) of trapezoidal joint moves, set by the joint with the largest travel."""
    d = np.max(np.abs(np.atleast_2d(q_to) - np.atleast_2d(q_from)), axis=1)
    ramp = speed_rad_s**2 / accel_rad_s2  # distance spent accelerating and braking at full speed
    triangular = 2.0 * np.sqrt(d / accel_rad_s2)
    trapezoid = d / speed_rad_s + speed_rad_s / accel_rad_s2
    return np.where(d < ramp, triangular, trapezoid)


def sequence_duration_s(
    q_sequence: np.ndarray,
    q_start: np.ndarray,
    speed_rad_s: float,
    accel_rad_s2: float,
    per_point_s: float,
) -> float:
    """Estimated wall time of visiting the joints in order: moves plus settle-and-measure per point."""
    q = np.atleast_2d(q_sequence)
    if len(q) == 0:
        return 0.0
    previous = np.vstack([np.asarray(q_start, float), q[:-1]])
    return float(np.sum(joint_move_time_s(previous, q, speed_rad_s, accel_rad_s2)) + per_point_s * len(q))


def linear_path_joints(
    nominal: KinematicModel,
    T_base_flange: np.ndarray,
    p_flange_tool_m: np.ndarray,
    q_near: np.ndarray,
    step_m: float = 0.005,
) -> tuple[np.ndarray, JointPlan]:
    """The tool points (N, 3, base frame) of a moveL through flange waypoints (K, 4, 4), every `step_m` of
    straight line between them (each leg at its end's orientation), and their nominal IK near `q_near`, so
    the whole path can be checked reachable, away from singularities and inside the envelope before it runs."""
    T_tool = np.asarray(T_base_flange, float).copy()
    T_tool[:, :3, 3] += T_tool[:, :3, :3] @ np.asarray(p_flange_tool_m, float)
    dense = [T_tool[:1]]
    for a, b in zip(T_tool[:-1], T_tool[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b[:3, 3] - a[:3, 3]) / step_m)))
        leg = np.tile(b, (n, 1, 1))
        leg[:, :3, 3] = a[:3, 3] + (np.arange(1, n + 1) / n)[:, None] * (b[:3, 3] - a[:3, 3])
        dense.append(leg)
    T_all = np.concatenate(dense)
    return T_all[:, :3, 3], plan_joints(nominal, T_all, p_flange_tool_m, q_near=q_near)
