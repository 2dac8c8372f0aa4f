"""A URDF's serial chain turned into the model calibration uses: standard DH, Hayati's beta on parallel axes.

Every DH frame is built from the chain's geometry at the URDF's zero pose and stays rigid in its link, so
the model's forward kinematics equal the URDF's at every joint value (checked on random joints before the
model is returned: a wrong conversion is refused, never used):

- frame 0: z along joint 1's axis. When that axis is the root link's z axis through its origin (every
  maker's base frame, and a ROS description's `base_link`), frame 0 IS the root link's frame and the fixed
  transforms before joint 1 go into joint 1's d and theta offset. Otherwise (a `world` link beside the arm,
  a tilted mounting) the model's base frame is put on joint 1's axis and the offset is reported
  (`ImportedRobot.T_root_base`, a note): calibration identifies the base frame anyway, but the cell's
  envelope and keep-out boxes are written in the model's base frame.
- frame i (1..n-1): z along joint i+1's axis; x along the common normal of axes i and i+1 (their cross
  product where they meet). Where the two axes are parallel (within PARALLEL_TOL_RAD) the common normal is
  not unique: the frame's origin is where axis i+1 crosses the plane normal to axis i through frame i-1's
  origin (d_i = 0), a tilt between them is alpha about x then Hayati's beta about y, and the joint carries
  beta (`uses_beta`), as in the robot files `hil axes` writes.
- frame n: z along the last axis, through the flange link's origin or its foot on the axis (then a_n the
  distance), x towards the flange origin or along the flange's x; the rest is `T_last_flange`.

Joint directions and zeros are the URDF's: a joint value means what it means in ROS (and on the controller
when the description follows it). Limits are the URDF's (a continuous joint, +-360 deg). The mass of the
link each joint moves is the sum of the masses of its child link and the links fixed to it; their centre of
mass, in the DH frame of that joint, is kept beside the model (`com_frame_m`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.se3 import invert, rot_x, rot_y
from hil.geometry.urdf_read import CONTINUOUS_LIMITS_RAD, UrdfChain, UrdfError, read_chain

# Axes closer than this to parallel carry Hayati's beta (the robot files' 1 deg on alpha).
PARALLEL_TOL_RAD = math.radians(1.0)
# Two axes closer than this meet; a point closer than this to an axis is on it (m).
ON_AXIS_TOL_M = 1e-9
# The model's flange may differ from the URDF's by this much on the self-check (m, rad): rounding only.
SELF_CHECK_TOL = 1e-9


@dataclass(frozen=True)
class ImportedRobot:
    """A URDF read as a calibration model. `T_root_base`: the model's base frame in the URDF's root link
    (identity when joint 1 turns about the root's z axis); `com_frame_m` (n, 3): the centre of mass of what
    each joint moves, in that joint's DH frame, None when the URDF gives no masses; `notes`: what a user
    should know (a moved base frame, masses left out)."""

    model: KinematicModel
    chain: UrdfChain
    T_root_base: np.ndarray
    com_frame_m: np.ndarray | None
    notes: tuple[str, ...]

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.chain.joints)


def import_urdf(text: str, source: str, use_beta: bool = True) -> ImportedRobot:
    """A URDF's text as a calibration model; `source` is the file (with '#flange' when named)."""
    chain = read_chain(text, source)
    origins, axes, F = _zero_pose_axes(chain)
    frames, rows, parallel = _dh_frames(origins, axes, F, use_beta)
    theta, d, a, alpha, beta = (np.array(col, float) for col in zip(*rows, strict=True))
    n = len(chain.joints)
    limits = np.array([j.limits_rad or CONTINUOUS_LIMITS_RAD for j in chain.joints], float)
    masses, com, mass_note = _masses(chain, frames)
    model = KinematicModel(
        name=chain.robot_name,
        theta=theta,
        d=d,
        a=a,
        alpha=alpha,
        beta=beta,
        uses_beta=np.array(parallel, bool),
        joint_limits=limits,
        T_last_flange=invert(frames[n]) @ F,
        link_masses_kg=masses,
    )
    T_root_base = frames[0]
    _self_check(chain, model, T_root_base)
    notes = [] if mass_note is None else [mass_note]
    if not np.allclose(T_root_base, np.eye(4), atol=ON_AXIS_TOL_M):
        notes.append(_base_note(chain, T_root_base))
    return ImportedRobot(model, chain, T_root_base, com, tuple(notes))


def urdf_forward_kinematics(chain: UrdfChain, q: np.ndarray) -> np.ndarray:
    """T_root_flange (N, 4, 4) by the URDF's own product: each joint's origin, then its turn about its axis."""
    q = np.atleast_2d(np.asarray(q, float))
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    for i, j in enumerate(chain.joints):
        T = T @ chain.T_before[i] @ _turn(j.axis, q[:, i])
    return T @ chain.T_last_flange


def _turn(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (N, 4, 4) about a unit axis by angles (N,) (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    T = np.broadcast_to(np.eye(4), (len(angle), 4, 4)).copy()
    T[:, :3, :3] = np.eye(3) + s * K + (1 - c) * (K @ K)
    return T


def _zero_pose_axes(chain: UrdfChain) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every moving joint's origin (n, 3) and unit axis (n, 3) in the root frame at the zero pose, and the
    flange's pose there."""
    T = np.eye(4)
    origins, axes = [], []
    for i, j in enumerate(chain.joints):
        T = T @ chain.T_before[i]
        origins.append(T[:3, 3].copy())
        axes.append(T[:3, :3] @ j.axis)
    return np.array(origins), np.array(axes), T @ chain.T_last_flange


def _frame(R: np.ndarray, o: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = o
    return T


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _across(z: np.ndarray, *candidates: np.ndarray) -> np.ndarray:
    """The first candidate's part normal to z, made unit (the next candidate where one lies along z)."""
    for c in candidates:
        v = c - (c @ z) * z
        if np.linalg.norm(v) > 1e-6:
            return _unit(v)
    raise AssertionError("no candidate direction across z")  # e_x, e_y, e_z cannot all lie along z


def _dh_frames(
    origins: np.ndarray, axes: np.ndarray, F: np.ndarray, use_beta: bool
) -> tuple[list[np.ndarray], list[tuple[float, ...]], list[bool]]:
    """The DH frames 0..n in the root frame at the zero pose, every joint's (theta, d, a, alpha, beta) and
    which joints carry beta (the module docstring says how each frame is chosen)."""
    n = len(axes)
    e = np.eye(3)
    z0 = _unit(axes[0])
    foot = origins[0] + (-origins[0] @ z0) * z0  # the root origin's foot on axis 1
    if np.linalg.norm(foot) < ON_AXIS_TOL_M and np.allclose(z0, e[2], atol=1e-12):
        frames = [np.eye(4)]
    else:
        x0 = _across(z0, e[0], e[1])
        frames = [_frame(np.column_stack([x0, np.cross(z0, x0), z0]), foot)]
    rows: list[tuple[float, ...]] = []
    parallel: list[bool] = []
    for i in range(n):
        prev = frames[-1]
        x_prev, z, o = prev[:3, 0], prev[:3, 2], prev[:3, 3]
        if i == n - 1:
            R, origin, d, a, alpha, beta, is_parallel = _last_frame(z, o, F)
        else:
            u, p = _unit(axes[i + 1]), origins[i + 1]
            angle = math.atan2(np.linalg.norm(np.cross(z, u)), abs(z @ u))
            if angle < 1e-12 or (use_beta and angle < PARALLEL_TOL_RAD):
                R, origin, d, a, alpha, beta = _parallel_frame(x_prev, z, o, u, p)
                is_parallel = use_beta
            else:
                R, origin, d, a, alpha, beta = _normal_frame(z, o, u, p)
                is_parallel = False
        x = R[:, 0]
        theta = math.atan2(z @ np.cross(x_prev, x), x_prev @ x)
        rows.append((theta, d, a, alpha, beta))
        parallel.append(is_parallel)
        frames.append(_frame(R, origin))
    return frames, rows, parallel


def _normal_frame(z: np.ndarray, o: np.ndarray, u: np.ndarray, p: np.ndarray) -> tuple:
    """Frame i of skew or meeting axes i (o, z) and i+1 (p, u): on their common normal."""
    w = o - p
    b, dz, du = z @ u, z @ w, u @ w
    denom = 1.0 - b * b
    s = (b * du - dz) / denom  # along axis i from o
    t = (du - b * dz) / denom  # along axis i+1 from p
    c_i, c_next = o + s * z, p + t * u
    gap = float(np.linalg.norm(c_next - c_i))
    x = _unit(np.cross(z, u)) if gap < ON_AXIS_TOL_M else (c_next - c_i) / gap
    alpha = math.atan2(x @ np.cross(z, u), z @ u)
    R = np.column_stack([x, np.cross(u, x), u])
    return R, c_next, float(s), gap if gap >= ON_AXIS_TOL_M else 0.0, alpha, 0.0


def _parallel_frame(x_prev: np.ndarray, z: np.ndarray, o: np.ndarray, u: np.ndarray, p: np.ndarray) -> tuple:
    """Frame i of (nearly) parallel axes i (o, z) and i+1 (p, u): where axis i+1 crosses the plane normal to
    z through o (d_i = 0), x towards it, then Rx(alpha) Ry(beta) turns z onto u."""
    origin = p + ((o - p) @ z / (u @ z)) * u
    v = origin - o
    a = float(np.linalg.norm(v))
    x = v / a if a > ON_AXIS_TOL_M else _across(z, x_prev, np.cross(z, x_prev))
    y = np.cross(z, x)
    ux, uy, uz = u @ x, u @ y, u @ z
    beta = math.asin(float(np.clip(ux, -1.0, 1.0)))
    alpha = math.atan2(-uy, uz)
    R = np.column_stack([x, y, z]) @ rot_x(alpha) @ rot_y(beta)
    return R, origin, 0.0, a if a > ON_AXIS_TOL_M else 0.0, alpha, beta


def _last_frame(z: np.ndarray, o: np.ndarray, F: np.ndarray) -> tuple:
    """Frame n: on the last axis level with the flange origin, x towards the flange origin when it is off
    the axis (a_n its distance), else along the flange's x (its y when x lies along the axis)."""
    f = F[:3, 3]
    d = float((f - o) @ z)
    r = f - (o + d * z)
    a = float(np.linalg.norm(r))
    if a > ON_AXIS_TOL_M:
        x = r / a
    else:
        x, a = _across(z, F[:3, 0], F[:3, 1]), 0.0
    R = np.column_stack([x, np.cross(z, x), z])
    return R, o + d * z + a * x, d, a, 0.0, 0.0, False


def _masses(
    chain: UrdfChain, frames: list[np.ndarray]
) -> tuple[tuple[float, ...] | None, np.ndarray | None, str | None]:
    """The mass each joint moves, its centre of mass in the joint's DH frame, and a note when the URDF gives
    masses on some of these links only (then none are used: a torque from a partial table would be wrong)."""
    totals, coms, missing = [], [], []
    T_root_child = np.eye(4)
    for i, (j, group) in enumerate(zip(chain.joints, chain.moved_links, strict=True)):
        T_root_child = T_root_child @ chain.T_before[i]  # the child link's frame at the zero pose
        T_frame_child = invert(frames[i + 1]) @ T_root_child
        masses, points = [], []
        for name, T_child_link in group:
            link = chain.links[name]
            if link.mass_kg is None or link.mass_kg <= 0:
                continue
            masses.append(link.mass_kg)
            com_link = np.zeros(3) if link.com_link_m is None else link.com_link_m
            com_child = T_child_link @ np.append(com_link, 1.0)
            points.append((T_frame_child @ com_child)[:3])
        if not masses:
            missing.append(j.name)
            totals.append(0.0)
            coms.append(np.zeros(3))
            continue
        m = np.array(masses)
        totals.append(float(m.sum()))
        coms.append(m @ np.array(points) / m.sum())
    if len(missing) == len(chain.joints):
        return None, None, None
    if missing:
        return (
            None,
            None,
            f"link masses left out: the URDF gives no <inertial> mass for what joint(s) {', '.join(missing)} "
            "move; gravity's yield is then a candidate effect, not physics from the masses",
        )
    return tuple(totals), np.array(coms), None


def _self_check(chain: UrdfChain, model: KinematicModel, T_root_base: np.ndarray) -> None:
    """Refuse a conversion whose flange differs from the URDF's on random joints (a bug, never a robot)."""
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (16, model.n_joints))
    want = urdf_forward_kinematics(chain, q)
    got = T_root_base @ forward_kinematics(model, q)
    err = float(np.max(np.abs(want - got)))
    if not err < SELF_CHECK_TOL:
        raise UrdfError(
            f"{chain.source}: the DH model differs from the URDF's chain by {err:.3g} (m or rad) on random "
            "joints; this is a fault of hil's conversion: please report it with the file"
        )


def _base_note(chain: UrdfChain, T_root_base: np.ndarray) -> str:
    """Where the model's base frame sits in the URDF's root link, in mm and degrees."""
    t_mm = T_root_base[:3, 3] * 1e3
    tilt = math.degrees(math.acos(float(np.clip(T_root_base[2, 2], -1.0, 1.0))))
    return (
        f"base frame: joint 1 does not turn about {chain.root!r}'s z axis, so the model's base frame is on "
        f"joint 1's axis, at [{t_mm[0]:.3f}, {t_mm[1]:.3f}, {t_mm[2]:.3f}] mm in {chain.root!r}, its z axis "
        f"{tilt:.3f} deg from {chain.root!r}'s: calibration identifies it; write the cell's envelope in it"
    )
