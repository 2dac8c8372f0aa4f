"""SE(3) helpers: homogeneous transforms, UR pose vectors, rigid point-set fits, plane and circle fits.

Rotation vectors come from `rotation_log`, the one SO(3) logarithm of the project, and turn back into matrices
through `rotation_exp`, its exponential. Neither imports scipy: scipy.spatial takes 0.35 CPU-s to import, more
than a simulated cell (which turns the rotation vector of every pose command into a matrix) or a `hil` command
needs for it. Everything is vectorised over leading axes where it matters.
"""

from __future__ import annotations

import numpy as np


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotation(s) (...,3,3) and translation(s) (...,3) into homogeneous transform(s) (...,4,4)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) (...,4,4) without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_transform(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply transform(s) (...,4,4) to point(s) (...,3)."""
    return np.einsum("...ij,...j->...i", T[..., :3, :3], points) + T[..., :3, 3]


def pose_to_transform(pose: np.ndarray) -> np.ndarray:
    """UR pose vector(s) [x, y, z, rx, ry, rz] (metres, rotation vector in rad) -> (...,4,4)."""
    pose = np.asarray(pose, dtype=float)
    flat = pose.reshape(-1, 6)
    return make_transform(rotation_exp(flat[:, 3:]), flat[:, :3]).reshape(pose.shape[:-1] + (4, 4))


def transform_to_pose(T: np.ndarray) -> np.ndarray:
    """Transform(s) (...,4,4) -> UR pose vector(s) [x, y, z, rx, ry, rz]."""
    T = np.asarray(T, dtype=float)
    flat = T.reshape(-1, 4, 4)
    rv = rotation_log(flat[:, :3, :3])
    return np.concatenate([flat[:, :3, 3], rv], axis=1).reshape(T.shape[:-2] + (6,))


_SKEW_ROWS, _SKEW_COLS = np.array([2, 0, 1]), np.array([1, 2, 0])  # the axial vector's (row, column) pairs


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), rad, of rotation matrices (..., 3, 3): the SO(3) logarithm.

    Exact near identity and ~1e-13 rad near pi, vectorised without scipy's per-call overhead (the IK's
    Levenberg-Marquardt loop calls it every step).
    """
    R = np.asarray(R, dtype=float)
    lead = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    s = 0.5 * (R[:, _SKEW_ROWS, _SKEW_COLS] - R[:, _SKEW_COLS, _SKEW_ROWS])  # R21 - R12, R02 - R20, R10 - R01
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)
    sn = np.sqrt(np.add.reduce(s * s, axis=1))  # np.linalg.norm's arithmetic without its call overhead
    angle = np.arctan2(sn, c)
    rv = s * np.where(sn > 1e-12, angle / np.maximum(sn, 1e-300), 1.0)[:, None]
    near_pi = (sn <= 1e-5) & (c < 0)
    if near_pi.any():  # axis from the symmetric part, R + R^T + 2 I ~ 4 n n^T near pi
        Rn = R[near_pi]
        B = 0.25 * (Rn + np.swapaxes(Rn, 1, 2)) + 0.5 * np.eye(3)
        col = np.argmax(np.einsum("kii->ki", B), axis=1)
        axis = np.take_along_axis(B, col[:, None, None], axis=2)[:, :, 0]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        axis *= np.where(np.einsum("ki,ki->k", axis, s[near_pi]) < 0, -1.0, 1.0)[:, None]
        rv[near_pi] = angle[near_pi, None] * axis
    return rv.reshape(lead + (3,))


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3), rad: the SO(3) exponential.

    Through the unit quaternion (axis sin(angle/2), cos(angle/2)), a Taylor series for sin(angle/2)/angle below
    1 mrad, then the quaternion's matrix: the route and the order of operations of scipy's
    `Rotation.from_rotvec(...).as_matrix()`, whose matrices it reproduces (bit for bit with scipy 1.17).
    """
    v = np.asarray(rotvec, dtype=float)
    lead = v.shape[:-1]
    v = v.reshape(-1, 3)
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    angle = np.sqrt(vx * vx + vy * vy + vz * vz)
    small = angle <= 1e-3
    a2 = angle * angle
    half_sinc = np.where(
        small, 0.5 - a2 / 48 + a2 * a2 / 3840, np.sin(angle / 2) / np.where(small, 1.0, angle)
    )
    R = quaternion_matrix(vx * half_sinc, vy * half_sinc, vz * half_sinc, np.cos(angle / 2))
    return R.reshape(lead + (3, 3))


def quaternion_matrix(x: np.ndarray, y: np.ndarray, z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions x i + y j + z k + w, given component by component
    (arrays of one shape, or scalars), in the order of operations scipy's `Rotation.as_matrix` uses."""
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    R = np.empty(np.shape(x) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2
    return R


def rot_x(angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrix (or matrices) about x."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrix (or matrices) about y."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrix (or matrices) about z."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix/matrices [v]x of vector(s) (...,3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def pose_error(T_actual: np.ndarray, T_desired: np.ndarray) -> np.ndarray:
    """6-vector error(s) (...,6) taking T_actual to T_desired: [dp (m), rotation vector (rad)], base frame."""
    dp = T_desired[..., :3, 3] - T_actual[..., :3, 3]
    R_err = T_desired[..., :3, :3] @ np.swapaxes(T_actual[..., :3, :3], -1, -2)
    return np.concatenate([dp, rotation_log(R_err)], axis=-1)


def fit_rigid(
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray | None = None,
    with_scale: bool = False,
) -> tuple[np.ndarray, float]:
    """Kabsch/Umeyama fit: T (4x4) and scale s minimising sum w |target - (s R source + t)|^2.

    Needs at least three non-collinear points; raises ValueError otherwise.
    """
    src = np.asarray(source, dtype=float)
    dst = np.asarray(target, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"fit_rigid needs two (N,3) arrays of equal shape, got {src.shape}, {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"fit_rigid needs at least 3 point pairs, got {src.shape[0]}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(cov)
    if S[1] < 1e-12 * max(S[0], 1e-300):
        raise ValueError("fit_rigid: points are collinear or coincident; spread them out")
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0
    R = U @ D @ Vt
    scale = 1.0
    if with_scale:
        var_s = w @ np.sum(xs**2, axis=1)
        scale = float(np.trace(np.diag(S) @ D) / var_s)
    t = mu_d - scale * R @ mu_s
    return make_transform(R, t), scale


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane through (N>=3, 3) points: (centroid, unit normal)."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[0] < 3:
        raise ValueError(f"fit_plane needs at least 3 points as (N,3), got {pts.shape}")
    centroid = pts.mean(axis=0)
    _, S, Vt = np.linalg.svd(pts - centroid)
    if S[1] < 1e-12 * max(S[0], 1e-300):
        raise ValueError("fit_plane: points are collinear; a plane is not defined")
    return centroid, Vt[2]


def fit_circle_3d(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Circle through (N>=3, 3) points in space: (centre, unit plane normal, radius).

    Three points give the circumscribed circle exactly; more points give the algebraic
    least-squares circle in their best-fit plane.
    """
    centroid, normal = fit_plane(points)
    pts = np.asarray(points, dtype=float)
    # In-plane orthonormal basis (u, v).
    u = pts[0] - centroid
    u -= normal * (u @ normal)
    if np.linalg.norm(u) < 1e-15:
        u = pts[1] - centroid
        u -= normal * (u @ normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    x = (pts - centroid) @ u
    y = (pts - centroid) @ v
    # x^2 + y^2 + D x + E y + F = 0, linear in (D, E, F).
    A = np.column_stack([x, y, np.ones_like(x)])
    b = -(x**2 + y**2)
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = -D / 2.0, -E / 2.0
    radius = float(np.sqrt(max(cx**2 + cy**2 - F, 0.0)))
    centre = centroid + cx * u + cy * v
    return centre, normal, radius


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to R (polar decomposition through SVD)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt
