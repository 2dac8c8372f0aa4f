"""Pseudo-target generators of the PT paper (methods.md section 4): the next pose to ask the IK for.

Every generator maps (target T_d, pose reached T_a, current pseudo target T_p) to a new pseudo target,
batched over (N, 4, 4) poses in one frame. The reached pose may come from a model (model-based
compensation) or from a measurement (the measured loop): the update does not care which.
Position part: P_p + P_d - P_a for all generators but Yin's, which updates the whole transform.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from hil.geometry.se3 import invert, rotation_log

GENERATORS: tuple[str, ...] = ("yin", "fixed", "add", "multiply", "zyz", "rpy", "quaternion")
DESCRIPTIONS: dict[str, str] = {
    "yin": "whole transform: T_p <- T_p T_a^-1 T_d",
    "fixed": "orientation kept at the target's: R_p <- R_d",
    "add": "add/subtract: R_p <- R_p + R_d - R_a (projected onto SO(3) for the IK)",
    "multiply": "R_p <- R_d R_a^T R_p",
    "zyz": "triple angle, ZYZ Euler: angles_p <- angles_p + angles_d - angles_a",
    "rpy": "triple angle, XYZ roll-pitch-yaw: angles_p <- angles_p + angles_d - angles_a",
    "quaternion": "unit quaternion: q_p <- q_p * conj(q_a) * q_d",
}
# scipy sequences: ZYZ intrinsic; roll-pitch-yaw = rotations about the fixed X, Y, Z axes (extrinsic xyz).
_EULER_SEQ = {"zyz": "ZYZ", "rpy": "xyz"}


def check_generator(name: str) -> str:
    if name not in GENERATORS:
        raise ValueError(f"unknown pseudo-target generator {name!r}; known: {', '.join(GENERATORS)}")
    return name


def update_pseudo_target(
    generator: str, T_target: np.ndarray, T_reached: np.ndarray, T_pseudo: np.ndarray
) -> np.ndarray:
    """The next pseudo targets (N, 4, 4) from targets, reached poses and current pseudo targets (N, 4, 4).

    The rotation block of the "add" generator is not a rotation (by design); `ik_pose` gives the pose
    to hand to an IK solver.
    """
    check_generator(generator)
    Td, Ta, Tp = (np.asarray(T, dtype=float) for T in (T_target, T_reached, T_pseudo))
    if generator == "yin":
        return Tp @ invert(Ta) @ Td
    out = np.array(Tp, dtype=float)
    out[:, :3, 3] = update_pseudo_position(Td[:, :3, 3], Ta[:, :3, 3], Tp[:, :3, 3])
    Rd, Ra, Rp = Td[:, :3, :3], Ta[:, :3, :3], Tp[:, :3, :3]
    if generator == "fixed":
        out[:, :3, :3] = Rd
    elif generator == "add":
        out[:, :3, :3] = Rp + Rd - Ra
    elif generator == "multiply":
        out[:, :3, :3] = Rd @ np.swapaxes(Ra, 1, 2) @ Rp
    elif generator in _EULER_SEQ:
        out[:, :3, :3] = _triple_angle(_EULER_SEQ[generator], Rp, Rd, Ra)
    else:  # quaternion
        qp, qa, qd = (Rotation.from_matrix(nearest_rotation(R)).as_quat() for R in (Rp, Ra, Rd))
        qa_conj = qa * np.array([-1.0, -1.0, -1.0, 1.0])
        out[:, :3, :3] = Rotation.from_quat(quat_multiply(quat_multiply(qp, qa_conj), qd)).as_matrix()
    return out


def update_pseudo_position(P_target: np.ndarray, P_reached: np.ndarray, P_pseudo: np.ndarray) -> np.ndarray:
    """Position-only update (N, 3): shift the pseudo target by what the reached point missed."""
    return np.asarray(P_pseudo, float) + np.asarray(P_target, float) - np.asarray(P_reached, float)


def ik_pose(T_pseudo: np.ndarray) -> np.ndarray:
    """The pseudo targets as proper poses (N, 4, 4): rotation blocks projected onto SO(3)."""
    T = np.array(T_pseudo, dtype=float)
    T[:, :3, :3] = nearest_rotation(T[:, :3, :3])
    return T


def pose_errors(T_reached: np.ndarray, T_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error (N,) m and orientation error angle (N,) rad between reached and target poses."""
    dp = np.linalg.norm(T_reached[:, :3, 3] - T_target[:, :3, 3], axis=1)
    R = np.swapaxes(T_target[:, :3, :3], 1, 2) @ T_reached[:, :3, :3]
    return dp, np.linalg.norm(rotation_log(R), axis=1)


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """Nearest proper rotations (N, 3, 3) to matrices R (N, 3, 3) (polar decomposition via SVD)."""
    U, _, Vt = np.linalg.svd(R)
    sign = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[:, :, 2] *= sign[:, None]
    return U @ Vt


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a * b of quaternions (N, 4) stored scalar-last [x, y, z, w] (scipy's order)."""
    av, aw = a[:, :3], a[:, 3:]
    bv, bw = b[:, :3], b[:, 3:]
    v = aw * bv + bw * av + np.cross(av, bv)
    w = aw * bw - np.einsum("ni,ni->n", av, bv)[:, None]
    return np.concatenate([v, w], axis=1)


def _triple_angle(seq: str, Rp: np.ndarray, Rd: np.ndarray, Ra: np.ndarray) -> np.ndarray:
    """E2R(R2E(Rp) + R2E(Rd) - R2E(Ra)) with angle differences wrapped into (-pi, pi].

    Near gimbal lock the angle split is arbitrary (scipy warns; silenced here): the update may then
    not reduce the error, and the loop's no-improvement rule stops the target.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        ep, ed, ea = (Rotation.from_matrix(nearest_rotation(R)).as_euler(seq) for R in (Rp, Rd, Ra))
    diff = np.pi - np.mod(np.pi - (ed - ea), 2.0 * np.pi)
    return Rotation.from_euler(seq, ep + diff).as_matrix()
