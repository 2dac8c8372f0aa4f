"""Physics of the simulated arm, written independently of hil/: the true DH chain with per-row
parameters (so thermal growth can differ per sample), and gravity torques from link masses.

hil/ models these effects with its own parametric candidates; nothing in hil/ imports this module.
"""

from __future__ import annotations

import numpy as np

GRAVITY_BASE = np.array([0.0, 0.0, -9.81])  # m/s^2, robot mounted upright (base z up)


def chain_frames(
    q: np.ndarray,
    theta: np.ndarray,
    d: np.ndarray,
    a: np.ndarray,
    alpha: np.ndarray,
    beta: np.ndarray,
) -> np.ndarray:
    """Frames of base and every link, (N, n+1, 4, 4), for joints q (N, n).

    Each geometry array is (n,) or (N, n), so each row can carry its own geometry.
    Joint transform: Rz(q + theta) Tz(d) Tx(a) Rx(alpha) Ry(beta).
    """
    q = np.atleast_2d(q)
    N, n = q.shape
    th = q + theta
    d, a, alpha, beta = (np.broadcast_to(x, (N, n)) for x in (d, a, alpha, beta))
    ct, st = np.cos(th), np.sin(th)
    ca, sa = np.cos(alpha), np.sin(alpha)
    cb, sb = np.cos(beta), np.sin(beta)
    # Rotation Rz(th) Rx(alpha) Ry(beta), written out.
    R = np.empty((N, n, 3, 3))
    R[..., 0, 0] = ct * cb - st * sa * sb
    R[..., 0, 1] = -st * ca
    R[..., 0, 2] = ct * sb + st * sa * cb
    R[..., 1, 0] = st * cb + ct * sa * sb
    R[..., 1, 1] = ct * ca
    R[..., 1, 2] = st * sb - ct * sa * cb
    R[..., 2, 0] = -ca * sb
    R[..., 2, 1] = sa
    R[..., 2, 2] = ca * cb
    frames = np.empty((N, n + 1, 4, 4))
    frames[:, 0] = np.eye(4)
    for i in range(n):
        A = np.zeros((N, 4, 4))
        A[:, :3, :3] = R[:, i]
        A[:, 0, 3] = a[:, i] * ct[:, i]
        A[:, 1, 3] = a[:, i] * st[:, i]
        A[:, 2, 3] = d[:, i]
        A[:, 3, 3] = 1.0
        frames[:, i + 1] = frames[:, i] @ A
    return frames


def gravity_torques(
    frames: np.ndarray,
    link_masses_kg: np.ndarray,
    payload_kg: float = 0.0,
    p_flange_payload: np.ndarray | None = None,
) -> np.ndarray:
    """Gravity torque about each joint axis (N, n), N*m, from lumped link masses.

    Link i's mass sits midway between the origins of frames i-1 and i (the link's span in the
    DH chain); the payload sits at `p_flange_payload` in the last frame. Torque about joint i's
    axis z_{i-1} through o_{i-1} sums the moments of every mass outboard of it.
    """
    N, n1 = frames.shape[:2]
    n = n1 - 1
    origins = frames[:, :, :3, 3]  # (N, n+1, 3)
    points = 0.5 * (origins[:, :-1] + origins[:, 1:])  # (N, n, 3): link i+1's mass
    f = np.broadcast_to(link_masses_kg[None, :, None] * GRAVITY_BASE, (N, n, 3))
    if payload_kg > 0:  # the payload rides on the last link
        p = np.zeros(3) if p_flange_payload is None else np.asarray(p_flange_payload, dtype=float)
        T_last = frames[:, -1]
        p_payload = T_last[:, :3, :3] @ p + T_last[:, :3, 3]
        f_payload = np.broadcast_to(payload_kg * GRAVITY_BASE, (N, 3))
        points = np.concatenate([points, p_payload[:, None, :]], axis=1)
        f = np.concatenate([f, f_payload[:, None, :]], axis=1)
    # Moment about o_i of every mass outboard of joint i: sum (p - o_i) x f = sum(p x f) - o_i x sum(f),
    # both sums taken from the tip inwards (the payload counts with the last link).
    moments = _cross(points, f)
    if payload_kg > 0:
        moments = np.concatenate(
            [moments[:, : n - 1], moments[:, n - 1 :].sum(axis=1, keepdims=True)], axis=1
        )
        f = np.concatenate([f[:, : n - 1], f[:, n - 1 :].sum(axis=1, keepdims=True)], axis=1)
    outboard_moment = np.cumsum(moments[:, ::-1], axis=1)[:, ::-1]  # (N, n)
    outboard_force = np.cumsum(f[:, ::-1], axis=1)[:, ::-1]
    moment = outboard_moment - _cross(origins[:, :-1], outboard_force)  # about o_0 .. o_{n-1}
    return np.einsum("nij,nij->ni", moment, frames[:, :-1, :3, 2])


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v over the last axis, written out (np.cross costs more than the physics on these small arrays)."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out
