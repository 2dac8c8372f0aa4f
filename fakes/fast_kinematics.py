"""Single-configuration FK, Jacobian and rotation-vector helpers for the controller's 500 Hz loop.

`hil.geometry.kinematics` is batched and general; per tick the fake needs one pose at a time in microseconds.
Same joint convention: Rz(q + theta) Tz(d) Tx(a) Rx(alpha) Ry(beta), then T_last_flange.
"""

from __future__ import annotations

import math

import numpy as np

from hil.geometry.kinematics import KinematicModel


class ArmKinematics:
    """Precomputed per-joint constants of one model for fast single-q FK and Jacobian."""

    def __init__(self, model: KinematicModel):
        self.model = model
        self.theta = np.asarray(model.theta, float)
        self.fixed = []  # Tz(d) Tx(a) Rx(alpha) Ry(beta) per joint
        for d, a, alpha, beta in zip(model.d, model.a, model.alpha, model.beta, strict=True):
            ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
            Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
            Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
            M = np.eye(4)
            M[:3, :3] = Rx @ Ry
            M[:3, 3] = [a, 0.0, d]
            self.fixed.append(M)
        self.T_last_flange = np.asarray(model.T_last_flange, float)

    def frames(self, q: np.ndarray) -> list[np.ndarray]:
        """Base-frame poses of frames 0..n (frame 0 = base) for one joint vector."""
        T = np.eye(4)
        out = [T]
        for i, M in enumerate(self.fixed):
            angle = float(q[i]) + float(self.theta[i])
            c, s = math.cos(angle), math.sin(angle)
            A = M.copy()
            A[0], A[1] = c * M[0] - s * M[1], s * M[0] + c * M[1]
            T = T @ A
            out.append(T)
        return out

    def fk(self, q: np.ndarray) -> np.ndarray:
        """T_base_flange (4, 4)."""
        return self.frames(q)[-1] @ self.T_last_flange

    def jacobian(self, q: np.ndarray, p_flange_tool: np.ndarray | None = None) -> np.ndarray:
        """Geometric Jacobian (6, n) at the tool point, rows [v; omega], base frame."""
        return self.fk_and_jacobian(q, p_flange_tool)[1]

    def fk_and_jacobian(
        self, q: np.ndarray, p_flange_tool: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """T_base_flange and the Jacobian at the tool point from one pass over the joints."""
        frames = self.frames(q)
        T = frames[-1] @ self.T_last_flange
        p = T[:3, 3] if p_flange_tool is None else T[:3, 3] + T[:3, :3] @ p_flange_tool
        stack = np.array(frames[:-1])
        z, o = stack[:, :3, 2], stack[:, :3, 3]
        r = p - o
        cross = np.column_stack(
            [
                z[:, 1] * r[:, 2] - z[:, 2] * r[:, 1],
                z[:, 2] * r[:, 0] - z[:, 0] * r[:, 2],
                z[:, 0] * r[:, 1] - z[:, 1] * r[:, 0],
            ]
        )
        return T, np.vstack([cross.T, z.T])


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) of a 3x3 rotation matrix, well conditioned up to and at pi."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_angle = 0.5 * math.sqrt(float(w @ w))
    cos_angle = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    angle = math.atan2(sin_angle, cos_angle)
    if angle < 1e-6:
        return 0.5 * w
    if angle < math.pi - 1e-3:
        return w * (angle / (2.0 * sin_angle))
    # near pi: n n^T = ((R + R^T)/2 - cos I) / (1 - cos); the sign of n follows w
    S = (0.5 * (R + R.T) - cos_angle * np.eye(3)) / (1.0 - cos_angle)
    k = int(np.argmax(np.diag(S)))
    axis = S[:, k] / math.sqrt(max(S[k, k], 1e-300))
    if float(axis @ w) < 0:
        axis = -axis
    return axis * angle


def pose_from_transform(T: np.ndarray) -> list[float]:
    """UR pose [x, y, z, rx, ry, rz] of one transform."""
    return [float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), *rotvec_from_matrix(T[:3, :3]).tolist()]
