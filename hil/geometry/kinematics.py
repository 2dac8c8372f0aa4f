"""Serial-arm kinematic model (standard DH, or DH with Hayati's beta on parallel axes) and batch FK.

Joint i transform, frame i-1 -> frame i:  Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i).
For a joint whose axis is parallel to the next one ("MDH" joint, Hayati 1985), d_i is not
identifiable and is replaced by beta_i as a parameter; d_i stays fixed at its nominal value.
For a standard DH joint beta_i is fixed at 0. Lengths in metres, angles in radians.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from hil.geometry.se3 import rot_y, rotation_exp

SMALL_BATCH = 24  # up to this many rows the chain is built from (4, 4) matmuls (fewer numpy calls)
PARAM_KINDS_DH: tuple[str, ...] = ("theta", "d", "a", "alpha")
PARAM_KINDS_MDH: tuple[str, ...] = ("theta", "a", "alpha", "beta")


@dataclass(frozen=True)
class KinematicModel:
    """A serial arm: per-joint geometry, which joints carry beta, joint limits and the flange offset.

    The identifiable parameter vector is built from the geometry: per joint, (theta, d, a, alpha)
    for a DH joint, (theta, a, alpha, beta) for a beta ("MDH") joint. Immutable: `with_params`
    returns a new model.
    """

    name: str
    theta: np.ndarray  # joint-angle offsets (rad)
    d: np.ndarray  # (m)
    a: np.ndarray  # (m)
    alpha: np.ndarray  # (rad)
    beta: np.ndarray  # (rad), 0 on DH joints
    uses_beta: np.ndarray  # bool per joint
    joint_limits: np.ndarray  # (n, 2) rad, [lower, upper]
    T_last_flange: np.ndarray = field(default_factory=lambda: np.eye(4))
    expansion_per_k: float | None = None  # the links' thermal expansion (1/K), None when unknown
    link_masses_kg: tuple[float, ...] | None = None  # mass of the link each joint moves, None when unknown

    def __post_init__(self) -> None:
        n = len(self.theta)
        for attr in ("d", "a", "alpha", "beta", "uses_beta"):
            if len(getattr(self, attr)) != n:
                raise ValueError(f"{self.name}: '{attr}' has {len(getattr(self, attr))} entries, need {n}")
        if np.shape(self.joint_limits) != (n, 2):
            raise ValueError(f"{self.name}: joint_limits must be ({n}, 2)")
        if np.any(np.asarray(self.beta)[~np.asarray(self.uses_beta, bool)] != 0):
            raise ValueError(f"{self.name}: beta must be 0 on joints that do not use beta")
        if self.link_masses_kg is not None and len(self.link_masses_kg) != n:
            raise ValueError(f"{self.name}: link_masses_kg has {len(self.link_masses_kg)} entries, need {n}")

    @property
    def n_joints(self) -> int:
        return len(self.theta)

    @property
    def param_names(self) -> list[str]:
        """Names of the identifiable kinematic parameters, e.g. ['theta1', 'd1', 'a1', 'alpha1', ...]."""
        return list(self._param_names)

    @cached_property
    def _param_names(self) -> tuple[str, ...]:
        # built once per model (immutable): a fit asks for the names thousands of times
        names: list[str] = []
        for i in range(self.n_joints):
            kinds = PARAM_KINDS_MDH if self.uses_beta[i] else PARAM_KINDS_DH
            names.extend(f"{k}{i + 1}" for k in kinds)
        return tuple(names)

    @cached_property
    def _param_slots(self) -> tuple[np.ndarray, np.ndarray]:
        """Where each identifiable parameter sits in the (5, n) table of theta, d, a, alpha, beta rows: its row
        and its joint (built once per model, so reading and replacing the parameters is one indexing each)."""
        rows = [_GEOMETRY_ROWS.index(_kind(nm)) for nm in self._param_names]
        joints = [_joint(nm) for nm in self._param_names]
        return np.array(rows, int), np.array(joints, int)

    def _geometry_table(self) -> np.ndarray:
        return np.array([np.asarray(getattr(self, k), dtype=float) for k in _GEOMETRY_ROWS])

    @property
    def params(self) -> np.ndarray:
        """Current values of the identifiable parameters, in `param_names` order."""
        return self._geometry_table()[self._param_slots]

    def with_params(self, values: np.ndarray) -> KinematicModel:
        """A copy with the identifiable parameters replaced by `values` (same order as `param_names`)."""
        values = np.asarray(values, dtype=float)
        if values.shape != (len(self._param_names),):
            raise ValueError(f"expected {len(self._param_names)} parameter values, got {values.shape}")
        table = self._geometry_table()
        table[self._param_slots] = values
        theta, d, a, alpha, beta = table
        return replace(self, theta=theta, d=d, a=a, alpha=alpha, beta=beta)

    def with_errors(self, errors: dict[str, float]) -> KinematicModel:
        """A copy with named parameter errors added, e.g. {'a2': 2e-4, 'beta2': 1e-4}."""
        names = self.param_names
        p = self.params.copy()
        for nm, dv in errors.items():
            if nm not in names:
                raise KeyError(f"{self.name} has no parameter '{nm}'; known: {', '.join(names)}")
            p[names.index(nm)] += dv
        return self.with_params(p)

    def check_joints(self, q: np.ndarray) -> np.ndarray:
        """Validate and return q as an (N, n) float array; raises ValueError with the bad shape."""
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f"{self.name}: joints must be (N, {self.n_joints}), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{self.name}: joints contain NaN or inf")
        return q

    def within_limits(self, q: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Bool (N,) whether each joint set lies within the joint limits (plus `tol` rad)."""
        q = self.check_joints(q)
        lo, hi = self.joint_limits[:, 0] - tol, self.joint_limits[:, 1] + tol
        return np.all((q >= lo) & (q <= hi), axis=1)


_GEOMETRY_ROWS = ("theta", "d", "a", "alpha", "beta")


def _kind(param_name: str) -> str:
    return param_name.rstrip("0123456789")


def _joint(param_name: str) -> int:
    return int(param_name[len(_kind(param_name)) :]) - 1


def joint_transforms(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Per-joint transforms (N, n, 4, 4) for joints q (N, n)."""
    q = model.check_joints(q)
    th = q + model.theta
    ct, st = np.cos(th), np.sin(th)
    ca, sa = np.cos(model.alpha), np.sin(model.alpha)
    N, n = q.shape
    A = np.zeros((N, n, 4, 4))
    A[..., 0, 0] = ct
    A[..., 0, 1] = -st * ca
    A[..., 0, 2] = st * sa
    A[..., 0, 3] = model.a * ct
    A[..., 1, 0] = st
    A[..., 1, 1] = ct * ca
    A[..., 1, 2] = -ct * sa
    A[..., 1, 3] = model.a * st
    A[..., 2, 1] = sa
    A[..., 2, 2] = ca
    A[..., 2, 3] = model.d
    A[..., 3, 3] = 1.0
    if np.any(model.beta != 0):  # skip the extra product on a nominal model (beta all 0)
        Ry = rot_y(np.asarray(model.beta, dtype=float))  # (n,3,3)
        A[..., :3, :3] = A[..., :3, :3] @ Ry
    return A


def link_frames(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Frames of every link in the base frame, (N, n+1, 4, 4): index 0 is the base, n the last link."""
    q = model.check_joints(q)
    N, n = q.shape
    frames = np.zeros((N, n + 1, 4, 4))
    frames[:, :, 3, 3] = 1.0
    frames[:, 0, :3, :3] = np.eye(3)
    _chain(model, q, frames)
    return frames


def forward_kinematics(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Flange poses T_base_flange (N, 4, 4) for joints q (N, n)."""
    return flange_poses_and_last_origins(model, q)[0]


def flange_poses_and_last_origins(model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flange poses T_base_flange (N, 4, 4) and the last link's origin (N, 3) (see `last_link_origins`) from
    one pass over the chain: a model whose links grow needs both for every prediction."""
    q = model.check_joints(q)
    R, p = _chain(model, q, None)
    return _flange_poses(model, R, p), p.copy()  # the chain's own arrays stay read-only in its memo


AxisPair = tuple[np.ndarray, np.ndarray]  # per-joint axis arrays (n, 3, N) `_chain` fills: (Z, O) or (X, Y)


def _chain(
    model: KinematicModel,
    q: np.ndarray,
    frames: np.ndarray | None,
    axes: AxisPair | None = None,
    mids: AxisPair | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Last-link rotation (N, 3, 3) and origin (N, 3), optionally filling every link frame into `frames`,
    every frame's z axis and origin into `axes` = (Z (n, 3, N), O (n + 1, 3, N)), and each joint's x axis
    after Rz(theta) and y axis after Rx(alpha) into `mids` = (X (n, 3, N), Y (n, 3, N)), base frame.

    A fit asks for the same chain twice in a row: its Jacobian, then the prediction at the same parameters
    (or the prediction at an accepted step, then the Jacobian there). `_ChainMemo` keeps the last few whole
    chains by content, so the second asks for nothing new. The returned arrays are read-only.
    """
    N, n = q.shape
    if N <= SMALL_BATCH and frames is None and mids is None:
        return _chain_small(model, q, axes)
    if frames is not None or N > _ChainMemo.MAX_ROWS:
        return _chain_loop(model, q, _ChainOut(frames, axes, mids))
    key = (_geometry_key(model), q.shape, q.tobytes())
    chain = _CHAIN_MEMO.get(key)
    if chain is None:
        Z, O = np.empty((n, 3, N)), np.empty((n + 1, 3, N))
        X, Y = np.empty((n, 3, N)), np.empty((n, 3, N))
        R, p = _chain_loop(model, q, _ChainOut(axes=(Z, O), mids=(X, Y)))
        chain = (R, p, Z, O, X, Y)
        for array in chain:
            array.flags.writeable = False
        _CHAIN_MEMO.put(key, chain)
    R, p, Z, O, X, Y = chain
    if axes is not None:
        axes[0][...], axes[1][...] = Z, O
    if mids is not None:
        mids[0][...], mids[1][...] = X, Y
    return R, p


class _ChainMemo:
    """The last `SIZE` chains `_chain` built, by the model's geometry and the joints' bytes (exact: a key
    holds the bytes themselves). Campaigns up to MAX_ROWS rows: a chain holds 25 (3, N) arrays."""

    SIZE = 4
    MAX_ROWS = 20_000

    def __init__(self) -> None:
        self._chains: OrderedDict[tuple, tuple[np.ndarray, ...]] = OrderedDict()
        self._lock = threading.Lock()  # a console thread and the engine may fit at once

    def get(self, key: tuple) -> tuple[np.ndarray, ...] | None:
        with self._lock:
            chain = self._chains.get(key)
            if chain is not None:
                self._chains.move_to_end(key)
            return chain

    def put(self, key: tuple, chain: tuple[np.ndarray, ...]) -> None:
        with self._lock:
            self._chains[key] = chain
            while len(self._chains) > self.SIZE:
                self._chains.popitem(last=False)


_CHAIN_MEMO = _ChainMemo()


def _geometry_key(model: KinematicModel) -> bytes:
    """The bytes of everything `_chain` reads of a model (its joint offsets and link geometry), once per
    model (it is immutable)."""
    got = model.__dict__.get("_geometry_key")
    if got is None:
        got = b"".join(
            np.asarray(v, float).tobytes() for v in (model.theta, model.d, model.a, model.alpha, model.beta)
        )
        model.__dict__["_geometry_key"] = got
    return got


@dataclass(frozen=True)
class _ChainOut:
    """What `_chain_loop` fills besides its result: every link frame (N, n + 1, 4, 4), every frame's z axis and
    origin (Z, O), every joint's mid axes (X, Y), as `_chain` says; None: not wanted."""

    frames: np.ndarray | None = None
    axes: AxisPair | None = None
    mids: AxisPair | None = None


def _chain_loop(model: KinematicModel, q: np.ndarray, out: _ChainOut) -> tuple[np.ndarray, np.ndarray]:
    """`_chain` computed: the same product as `joint_transforms` chained, written column by column on (3, N)
    axis arrays: a batched 4x4 matmul per joint costs an order of magnitude more for small matrices. The
    constant factors are Python floats and zero lengths are skipped: the loop's cost is its number of numpy
    calls. Rz(th) turns x, y about z; Tz(d) Tx(a) moves the origin by d z + a x'; Rx(alpha), Ry(beta) turn
    again."""
    frames, axes, mids = out.frames, out.axes, out.mids
    N, n = q.shape
    th = (q + model.theta).T  # (n, N): every axis array below is (3, N), contiguous per component
    ct, st = np.cos(th, order="C"), np.sin(th, order="C")  # rows contiguous too: faster products
    d, a, cal, sal, cbe, sbe, has_beta, _, _ = _chain_constants(model)
    x, y, z = np.zeros((3, N)), np.zeros((3, N)), np.zeros((3, N))
    x[0] = y[1] = z[2] = 1.0
    p = np.zeros((3, N))
    for i in range(n):
        if axes is not None:
            axes[0][i] = z
            axes[1][i] = p
        c, s = ct[i], st[i]
        x1 = c * x
        x1 += s * y
        y1 = c * y
        y1 -= s * x
        if d[i] != 0.0:
            p = p + d[i] * z
        if a[i] != 0.0:
            p = p + a[i] * x1
        ca, sa = cal[i], sal[i]
        if sa == 0.0 and ca == 1.0:  # alpha = 0 (a nominal parallel axis): no turn about x
            y, z2 = y1, z
        else:
            y = ca * y1
            y += sa * z
            z2 = ca * z
            z2 -= sa * y1
        if mids is not None:  # Ry(beta) below leaves y as it is
            mids[0][i] = x1
            mids[1][i] = y
        if has_beta[i]:
            cb, sb = cbe[i], sbe[i]
            x, z = cb * x1 - sb * z2, sb * x1 + cb * z2
        else:
            x, z = x1, z2
        if frames is not None:
            frames[:, i + 1, :3, 0] = x.T
            frames[:, i + 1, :3, 1] = y.T
            frames[:, i + 1, :3, 2] = z.T
            frames[:, i + 1, :3, 3] = p.T
    if axes is not None:
        axes[1][n] = p
    return np.stack([x, y, z], axis=1).transpose(2, 0, 1), p.T


_CONSTANTS: dict[tuple[bytes, ...], tuple] = {}


def _chain_constants(model: KinematicModel) -> tuple:
    """A model's constant chain factors, computed once per geometry (the arrays are read-only):
    d, a, cos/sin alpha, cos/sin beta and which joints use beta as Python floats/bools, and the rows
    (c0, c1, c2) of every joint's Rx(alpha) Ry(beta), (n, 3) each."""
    got = model.__dict__.get("_chain_constants")  # the model's own, once found (it is immutable)
    if got is not None:
        return got
    arrays = [np.asarray(v, float) for v in (model.d, model.a, model.alpha, model.beta)]
    key = tuple(v.tobytes() for v in arrays)
    got = _CONSTANTS.get(key)
    if got is None:
        d, a, alpha, beta = arrays
        ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
        rows = (
            np.stack([cb, np.zeros(len(cb)), sb], 1),
            np.stack([sa * sb, ca, -sa * cb], 1),
            np.stack([-ca * sb, sa, ca * cb], 1),
        )
        # `_small_frames`: A[:2, :3] = cos(th) P + sin(th) Q (the rows of Rz(th) times the rows above),
        # and a template holding every joint transform's constant rows (c2 and d; 0 0 0 1).
        P = np.stack([rows[0], rows[1]], 1)
        Q = np.stack([-rows[1], rows[0]], 1)
        template = np.zeros((len(d), 4, 4))
        template[:, 2, :3], template[:, 2, 3], template[:, 3, 3] = rows[2], d, 1.0
        for r in (*rows, P, Q, template):
            r.flags.writeable = False
        got = (
            d.tolist(),
            a.tolist(),
            ca.tolist(),
            sa.tolist(),
            cb.tolist(),
            sb.tolist(),
            (beta != 0).tolist(),
            rows,
            (P, Q, template, a[:, None]),
        )
        if len(_CONSTANTS) > 256:  # many models in one process (calibration sweeps): start again
            _CONSTANTS.clear()
        _CONSTANTS[key] = got
    model.__dict__["_chain_constants"] = got
    return got


_IDENTITY_4X4 = np.eye(4)
_IDENTITY_4X4.flags.writeable = False


def _small_frames(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Every link frame (N, n + 1, 4, 4) for a few rows (index 0 the base): every joint's (4, 4) transform
    built at once, then n - 1 batched matmuls, each written into its frame. Fewer numpy calls than the
    column-wise loop of `_chain`, which wins from a few dozen rows on."""
    N, n = q.shape
    th = q + model.theta
    P, Q, template, a = _chain_constants(model)[-1]
    cs = np.empty((N, n, 2))  # cos, sin of every joint angle
    np.cos(th, out=cs[..., 0])
    np.sin(th, out=cs[..., 1])
    A = np.empty((N, n, 4, 4))
    A[:] = template
    A[..., :2, 3] = cs * a  # a cos, a sin
    A[..., :2, :3] = cs[..., :1, None] * P + cs[..., 1:, None] * Q  # Rz(th) Rx(alpha) Ry(beta)
    F = np.empty((N, n + 1, 4, 4))
    F[:, 0] = _IDENTITY_4X4
    F[:, 1] = A[:, 0]
    for i in range(1, n):
        np.matmul(F[:, i], A[:, i], out=F[:, i + 1])
    return F


def _chain_small(
    model: KinematicModel, q: np.ndarray, axes: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray]:
    """`_chain` for a few rows, from `_small_frames`."""
    n = q.shape[1]
    F = _small_frames(model, q)
    if axes is not None:
        axes[0][:] = F[:, :n, :3, 2].transpose(1, 2, 0)
        axes[1][:] = F[:, :, :3, 3].transpose(1, 2, 0)
    return F[:, n, :3, :3], F[:, n, :3, 3]


def last_link_origins(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """The last link's origin (N, 3) in the base frame, before the fixed flange transform: the sum of every
    link's length (a, d) along its axes, so it grows in proportion when all link lengths are scaled."""
    q = model.check_joints(q)
    return _chain(model, q, None)[1].copy()  # the chain's own arrays stay read-only in its memo


def tool_points(model: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray) -> np.ndarray:
    """Tool points in the base frame (N, 3) for a point p_flange_tool (3,) given in the flange, or one per row
    (N, 3)."""
    return points_on_flanges(forward_kinematics(model, q), p_flange_tool)


def points_on_flanges(T_base_flange: np.ndarray, p_flange_tool: np.ndarray) -> np.ndarray:
    """Tool points (N, 3) in the base frame on flange poses (N, 4, 4): one tool point (3,) for every row, or
    one per row (N, 3)."""
    R, t = T_base_flange[:, :3, :3], T_base_flange[:, :3, 3]
    if np.ndim(p_flange_tool) == 1:
        return R @ np.asarray(p_flange_tool, dtype=float) + t
    return np.einsum("nij,nj->ni", R, p_flange_tool) + t


def tool_poses(model: KinematicModel, q: np.ndarray, T_flange_tool: np.ndarray) -> np.ndarray:
    """Tool frames T_base_tool (N, 4, 4) for a tool frame T_flange_tool (4, 4)."""
    return forward_kinematics(model, q) @ np.asarray(T_flange_tool, dtype=float)


def geometric_jacobian(
    model: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray | None = None
) -> np.ndarray:
    """Geometric Jacobian (N, 6, n) in the base frame at the tool point: rows [v; omega]."""
    return pose_and_jacobian(model, q, p_flange_tool)[1]


def chain_axes(model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flange poses T_base_flange (N, 4, 4), joint axes Z (n, 3, N) and link origins O (n + 1, 3, N) in
    the base frame, in one pass over the chain: joint i + 1 turns about Z[i] through O[i] (frame i's z
    axis and origin); O[n] is the last link's origin. What Jacobians and lever arms need, without
    filling every (4, 4) link frame."""
    q = model.check_joints(q)
    N, n = q.shape
    Z, O = np.empty((n, 3, N)), np.empty((n + 1, 3, N))
    R, p = _chain(model, q, None, (Z, O))
    return _flange_poses(model, R, p), Z, O


_IDENTITY_4 = _IDENTITY_4X4.ravel().tolist()  # compared as a list: the check runs on every chain


def _flange_poses(model: KinematicModel, R_base_last: np.ndarray, o_base_last: np.ndarray) -> np.ndarray:
    """T_base_flange (N, 4, 4) from the last link's rotations (N, 3, 3) and origins (N, 3), as `_chain` gives
    them."""
    T = np.zeros((len(o_base_last), 4, 4))
    T[:, :3, :3] = R_base_last
    T[:, :3, 3] = o_base_last
    T[:, 3, 3] = 1.0
    return _with_last_flange(model, T)


def _with_last_flange(model: KinematicModel, T_base_last: np.ndarray) -> np.ndarray:
    """The flange poses from the last link's (N, 4, 4): times the model's fixed T_last_flange."""
    L = np.asarray(model.T_last_flange, dtype=float)
    return T_base_last if L.ravel().tolist() == _IDENTITY_4 else T_base_last @ L


def pose_and_jacobian(
    model: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Flange poses T_base_flange (N, 4, 4) and the geometric Jacobian (N, 6, n) at the tool point, in one
    pass over the chain (the Newton step of the IK needs both)."""
    q = model.check_joints(q)
    N, n = q.shape
    if N <= SMALL_BATCH:  # the link frames at once: their z axes and origins are views
        F = _small_frames(model, q)
        T = _with_last_flange(model, F[:, n].copy())
        Z, O = F[:, :n, :3, 2].transpose(1, 2, 0), F[:, :n, :3, 3].transpose(1, 2, 0)
    else:
        T, Z, O = chain_axes(model, q)
    tip = (
        T[:, :3, 3]
        if p_flange_tool is None
        else T[:, :3, :3] @ np.asarray(p_flange_tool, float) + T[:, :3, 3]
    )
    r = tip.T - O[:n]  # (n, 3, N): from a point on each axis to the tip
    # Rows [v; omega], v_i = z_i x (tip - o_i), omega_i = z_i, filled as (6, n, N) and returned as a view.
    Jt = np.empty((6, n, N))
    Zx, Zy, Zz = Z[:, 0], Z[:, 1], Z[:, 2]
    rx, ry, rz = r[:, 0], r[:, 1], r[:, 2]
    np.subtract(Zy * rz, Zz * ry, out=Jt[0])
    np.subtract(Zz * rx, Zx * rz, out=Jt[1])
    np.subtract(Zx * ry, Zy * rx, out=Jt[2])
    Jt[3:] = Z.transpose(1, 0, 2)
    return T, Jt.transpose(2, 0, 1)


def kinematic_point_jacobian(
    model: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Derivative of the tool point (base frame) w.r.t. every identifiable parameter.

    Returns (points (N,3), J (N, 3, len(param_names))). Analytic: each elementary factor of a
    joint transform is a rotation about, or translation along, a known axis in the base frame.
    """
    p, J, _ = _point_jacobian(model, q, p_flange_tool)
    return p, J


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v over axis 1 of (n, 3, N) arrays (np.cross moves the axis last and back: several times slower)."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    np.subtract(u[:, 1] * v[:, 2], u[:, 2] * v[:, 1], out=out[:, 0])
    np.subtract(u[:, 2] * v[:, 0], u[:, 0] * v[:, 2], out=out[:, 1])
    np.subtract(u[:, 0] * v[:, 1], u[:, 1] * v[:, 0], out=out[:, 2])
    return out


def _point_jacobian(
    model: KinematicModel, q: np.ndarray, p_flange_tool: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`kinematic_point_jacobian` and the flange rotations R_base_flange (N, 3, 3), from one pass over the
    chain on (3, N) axis arrays. Joint i's columns: theta turns the tip about the previous z axis through the
    previous origin; d moves it along that z; a along the x axis after Rz(theta); alpha turns it about that x
    through the joint's origin; beta (where used, in place of d) about the y axis after Rx(alpha)."""
    q = model.check_joints(q)
    N, n = q.shape
    Z, O = np.empty((n, 3, N)), np.empty((n + 1, 3, N))
    X_mid, Y_alpha = np.empty((n, 3, N)), np.empty((n, 3, N))
    T_flange = _flange_poses(model, *_chain(model, q, None, (Z, O), (X_mid, Y_alpha)))
    R_flange = T_flange[:, :3, :3]
    tip = R_flange @ np.asarray(p_flange_tool, dtype=float) + T_flange[:, :3, 3]  # (N, 3)
    to_tip_prev = tip.T - O[:n]  # (n, 3, N): from the previous origin to the tip
    to_tip_here = tip.T - O[1:]  # from the joint's own origin (after Tz(d) Tx(a); beta does not translate)
    beta = np.asarray(model.uses_beta, bool)[:, None, None]
    d_alpha = _cross(X_mid, to_tip_here)
    columns = np.empty((n, 4, 3, N))
    columns[:, 0] = _cross(Z, to_tip_prev)  # theta
    columns[:, 1] = np.where(beta, X_mid, Z)  # MDH: a; DH: d
    columns[:, 2] = np.where(beta, d_alpha, X_mid)  # MDH: alpha; DH: a
    columns[:, 3] = np.where(beta, _cross(Y_alpha, to_tip_here), d_alpha) if beta.any() else d_alpha
    J = np.ascontiguousarray(columns.reshape(4 * n, 3, N).transpose(2, 1, 0))
    return tip, J, R_flange


BASE_PARAM_NAMES: tuple[str, ...] = ("base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz")
TOOL_PARAM_NAMES: tuple[str, ...] = ("tool_x", "tool_y", "tool_z")


def measured_point(
    model: KinematicModel, q: np.ndarray, T_tracker_base: np.ndarray, p_flange_tool: np.ndarray
) -> np.ndarray:
    """Predicted SMR centre in the tracker frame (N, 3)."""
    p_base = tool_points(model, q, p_flange_tool)
    return p_base @ T_tracker_base[:3, :3].T + T_tracker_base[:3, 3]


def identification_jacobian(
    model: KinematicModel, q: np.ndarray, T_tracker_base: np.ndarray, p_flange_tool: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted tracker-frame points (N,3) and their Jacobian (N, 3, P) for identification.

    Columns: the model's `param_names`, then the 6 base-frame parameters, then the 3 tool-point
    coordinates. Base parameters perturb T_tracker_base as Trans(dt) @ T_tracker_base @ Rot(dr):
    dt in tracker axes, dr a small rotation vector about the robot base origin in base axes
    (see `perturb_base`).
    """
    p_base, J_kin, R_base_flange = _point_jacobian(model, q, p_flange_tool)
    R_LB = T_tracker_base[:3, :3]
    p_L = p_base @ R_LB.T + T_tracker_base[:3, 3]
    N = p_base.shape[0]
    J_kin_L = R_LB @ J_kin
    J_base_t = np.broadcast_to(np.eye(3), (N, 3, 3))
    # d/d(dr) of R_LB (p_B + dr x p_B) = R_LB @ (-[p_B]x)
    px, py, pz = p_base[:, 0], p_base[:, 1], p_base[:, 2]
    zero = np.zeros(N)
    neg_skew = -np.stack(
        [np.stack([zero, -pz, py], -1), np.stack([pz, zero, -px], -1), np.stack([-py, px, zero], -1)], -2
    )
    J_base_r = R_LB @ neg_skew
    J_tool = R_LB @ R_base_flange
    J = np.concatenate([J_kin_L, J_base_t, J_base_r, J_tool], axis=2)
    return p_L, J


def perturb_base(T_tracker_base: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply the 6 base-parameter increments [dt (tracker axes), dr (base axes)] to T_tracker_base."""
    T_t = np.eye(4)
    T_t[:3, 3] = delta[:3]
    T_r = np.eye(4)
    T_r[:3, :3] = rotation_exp(delta[3:6])
    return T_t @ T_tracker_base @ T_r


def kinematic_rotation_jacobian(model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flange rotations R_base_flange (N, 3, 3) and the angular part of their derivative w.r.t. every
    identifiable parameter, (N, 3, len(param_names)), base frame.

    A parameter that turns the chain (theta, alpha, beta) turns the flange about that factor's axis in
    the base frame, so its column is the axis: z of the previous joint frame for theta, the x axis after
    Rz(theta) for alpha, the y axis after Rx(alpha) for beta. Lengths (d, a) do not turn it: zero.
    """
    q = model.check_joints(q)
    frames = link_frames(model, q)
    R_flange = frames[:, -1, :3, :3] @ np.asarray(model.T_last_flange, float)[:3, :3]
    N = q.shape[0]
    zero = np.zeros((N, 3))
    th = q + model.theta
    cols = []
    for i in range(model.n_joints):
        R_prev = frames[:, i, :3, :3]
        x_prev, y_prev, z_prev = R_prev[:, :, 0], R_prev[:, :, 1], R_prev[:, :, 2]
        c, s = np.cos(th[:, i])[:, None], np.sin(th[:, i])[:, None]
        x_mid = c * x_prev + s * y_prev
        if model.uses_beta[i]:
            y_mid = -s * x_prev + c * y_prev
            ca, sa = np.cos(model.alpha[i]), np.sin(model.alpha[i])
            cols.extend([z_prev, zero, x_mid, ca * y_mid + sa * z_prev])
        else:
            cols.extend([z_prev, zero, zero, x_mid])
    J = np.stack(cols, axis=2) if cols else np.zeros((N, 3, 0))
    return R_flange, J
