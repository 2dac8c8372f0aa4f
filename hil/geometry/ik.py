"""Inverse kinematics: batched Levenberg-Marquardt after Sugihara, and closed-form UR IK (8 branches).

`solve_ik` is the entry point. It solves N targets at once (one 6x6 linear solve per iteration for the
whole batch), never reports success unless the final error is below tolerance, and on UR-shaped models
seeds the numeric solver from the analytic branch nearest a reference posture, so the answer is both
exact for the given (possibly calibrated) model and in the expected configuration.

Conventions: joints (N, 6) in rad; targets T_base_tool (N, 4, 4) or tool points (N, 3) in metres, base
frame; errors are [dp (m), rotation vector (rad)] in the base frame, matching `geometric_jacobian`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hil.geometry.kinematics import KinematicModel, forward_kinematics, geometric_jacobian, pose_and_jacobian
from hil.geometry.se3 import invert, rotation_log

# Failure vocabulary of IKResult.reason.
REASON_OK = "ok"  # converged below tolerance, within joint limits
REASON_UNREACHABLE = "unreachable"  # target outside the workspace (provably, or no analytic branch exists)
REASON_JOINT_LIMITS = "joint_limits"  # a solution exists only outside the joint limits (solver stuck on one)
REASON_SINGULAR = "singular"  # stuck at a configuration where the Jacobian loses rank
REASON_MAX_ITER = "max_iter"  # did not converge within the iteration budget of every attempt
REASONS: tuple[str, ...] = (
    REASON_OK,
    REASON_UNREACHABLE,
    REASON_JOINT_LIMITS,
    REASON_SINGULAR,
    REASON_MAX_ITER,
)

UR_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
TWO_PI = 2.0 * np.pi
REACH_SLACK = (
    0.02  # UR pose unreachable if cos q3 or the shoulder ratio overshoot by > 2 % (>> mm model errors)
)
LAM_MIN = 1e-8  # floor of the adaptive bias multiplier (bias = LAM_MIN * wbar near convergence)
STALL_WINDOW, STALL_FACTOR = 25, 0.9  # give up an attempt whose E fell less than 10 % in 25 iterations
LAM_DOWN, LAM_UP = 0.1, 10.0  # bias multiplier after an accepted / rejected step
NEWTON_STEPS = 8  # Newton steps from the first seed before solve_ik falls back to LM


@dataclass(frozen=True)
class IKResult:
    """Outcome per target. `q` of a failed target is the best attempt found, never to be used blindly.

    reason: one of REASONS ("ok", "unreachable", "joint_limits", "singular", "max_iter").
    error: final tool-point position error (m); rotation_error: final orientation error (rad), NaN in
    position mode (no orientation was asked for).
    """

    q: np.ndarray  # (N, n) rad
    success: np.ndarray  # (N,) bool
    iterations: np.ndarray  # (N,) int, LM iterations summed over all attempts
    reason: np.ndarray  # (N,) str
    error: np.ndarray  # (N,) m
    rotation_error: np.ndarray  # (N,) rad
    attempts: np.ndarray  # (N,) int, seeds tried

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.success)) if len(self.success) else 1.0


# --------------------------------------------------------------------------------------------------
# Closed-form UR inverse kinematics
# --------------------------------------------------------------------------------------------------


def is_ur_like(model: KinematicModel, tol: float = 0.02) -> bool:
    """True if the model has the UR standard-DH shape (alphas, zero a1/d2/d3/a4/a5/a6) within `tol`."""
    if model.n_joints != 6:
        return False
    a, d = np.asarray(model.a), np.asarray(model.d)
    return bool(
        np.all(np.abs(np.asarray(model.alpha) - UR_ALPHA) < tol)
        and np.all(np.abs(a[[0, 3, 4, 5]]) < tol)
        and np.all(np.abs(d[[1, 2]]) < tol)
        and np.all(np.abs(np.asarray(model.theta)) < tol)
        and np.all(np.abs(np.asarray(model.beta)) < tol)
    )


def _as_transforms(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{what} must be (N, 4, 4) homogeneous transforms, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{what} contains NaN or inf")
    if np.any(np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]) > 1e-9):
        raise ValueError(f"{what}: the last row of a homogeneous transform must be [0, 0, 0, 1]")
    R = T[:, :3, :3]
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((ortho > 1e-6) | (np.linalg.det(R) < 0))
    if bad.size:
        raise ValueError(f"{what}[{bad[0]}] has a rotation part that is not a proper rotation matrix")
    return T


def ur_analytic_ik(
    model: KinematicModel, T_base_flange: np.ndarray, slack: float = 1e-9
) -> tuple[np.ndarray, np.ndarray]:
    """All 8 closed-form IK branches of a UR-shaped arm: (q (N, 8, 6) rad in (-pi, pi], valid (N, 8)).

    Uses d1, a2, a3, d4, d5, d6 and the theta offsets of `model` and ignores its small errors (beta,
    alpha deviations): exact on a nominal UR, approximate (a seed) on a calibrated one.
    Branch index = 4*shoulder + 2*wrist + elbow (each bit picks one of the two solutions).
    Invalid branches (target out of reach of that branch) are NaN. `slack` (dimensionless, on cos q3 and
    on the shoulder offset ratio) is how far beyond reach a target may be and still give the nearest
    (stretched) posture. At a wrist singularity (q5 = 0 or pi) q6 is set to 0 and q4 takes up the rest.
    """
    q, overshoot = _ur_branches(model, T_base_flange)
    valid = overshoot <= slack
    q[~valid] = np.nan
    return q, valid


def _ur_branches(
    model: KinematicModel, T_base_flange: np.ndarray, validate: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form branches, stretched where out of reach: (q (N, 8, 6), overshoot (N, 8) >= 0, 0 = exact)."""
    T = _ur_wrist_frames(model, T_base_flange, validate)
    N = T.shape[0]
    q, overshoot = _ur_branch(model, np.repeat(T, 8, axis=0), np.tile(np.arange(8), N))  # one pass, 8N rows
    return q.reshape(N, 8, 6), overshoot.reshape(N, 8)


def _ur_wrist_frames(model: KinematicModel, T_base_flange: np.ndarray, validate: bool = True) -> np.ndarray:
    if not is_ur_like(model):
        raise ValueError(f"{model.name} is not a UR-shaped arm (standard DH alphas pi/2,0,0,pi/2,-pi/2,0)")
    T = _as_transforms(T_base_flange, "T_base_flange") if validate else np.asarray(T_base_flange, float)
    L = np.asarray(model.T_last_flange, float)
    return T if np.array_equal(L, np.eye(4)) else T @ invert(L)


def _ur_branch(model: KinematicModel, T: np.ndarray, branch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One closed-form branch per target (index 4*shoulder + 2*wrist + elbow, (N,)) of last-link poses T:
    (q (N, 6) in (-pi, pi], overshoot (N,) >= 0, 0 = exact; stretched where out of reach).

    Written on (N,) components: the rotation products below are the few entries the angles need."""
    d1, d4, d5, d6 = model.d[0], model.d[3], model.d[4], model.d[5]
    a2, a3 = model.a[1], model.a[2]
    sh, wr, el = branch // 4, (branch // 2) % 2, branch % 2
    x6, y6, z6 = T[:, :3, 0].T, T[:, :3, 1].T, T[:, :3, 2].T  # (3, N) columns of the last link's rotation
    p5 = T[:, :3, 3].T - d6 * z6  # origin of frame 5, which lies at offset d4 along the joint-2 axis z1
    r2 = p5[0] ** 2 + p5[1] ** 2
    # Shoulder: z1 = (sin q1, -cos q1, 0) and p5 . z1 = d4  =>  r sin(q1 - phi) = d4.
    shoulder_over = np.maximum(1.0 - np.sqrt(r2) / abs(d4), 0.0)
    asin = np.arcsin(np.clip(d4 / np.sqrt(np.maximum(r2, 1e-300)), -1.0, 1.0))
    q1 = np.arctan2(p5[1], p5[0]) + np.where(sh == 0, asin, np.pi - asin)
    c1, s1 = np.cos(q1), np.sin(q1)  # x1 = (c1, s1, 0), y1 = (0, 0, 1), z1 = (s1, -c1, 0)
    # Wrist: z6 . z1 = cos q5; x6 . z1 = cos q6 sin q5 and y6 . z1 = -sin q6 sin q5.
    q5 = np.arccos(np.clip(z6[0] * s1 - z6[1] * c1, -1.0, 1.0)) * np.where(wr == 0, 1.0, -1.0)
    c5, s5 = np.cos(q5), np.sin(q5)
    xz = x6[0] * s1 - x6[1] * c1
    yz = y6[0] * s1 - y6[1] * c1
    singular = np.abs(s5) < 1e-12
    s5_safe = np.where(singular, 1.0, s5)
    q6 = np.where(singular, 0.0, np.arctan2(-yz / s5_safe, xz / s5_safe))
    c6, s6 = np.cos(q6), np.sin(q6)
    # R04 = R06 (Rz(q5) Rx(-pi/2) Rz(q6))^T; its columns 0 and 2 are R06 times rows 0 and 2 of that
    # product, (c5 c6, -c5 s6, -s5) and (-s6, -c6, 0). R04 = R01 Rz(q234) Rx(pi/2) then gives
    # q234 from column 0: x1 . col0 = cos q234, y1 . col0 = sin q234.
    col0 = (c5 * c6) * x6 - (c5 * s6) * y6 - s5 * z6
    col2 = -s6 * x6 - c6 * y6
    q234 = np.arctan2(col0[2], c1 * col0[0] + s1 * col0[1])
    # Planar 2-link problem for joints 2, 3 in the arm plane (x1, y1).
    p4 = p5 - d5 * col2
    u = (p4[0] - d4 * s1) * c1 + (p4[1] + d4 * c1) * s1
    v = p4[2] - d1
    c3 = (u**2 + v**2 - a2**2 - a3**2) / (2.0 * a2 * a3)
    elbow_over = np.maximum(np.abs(c3) - 1.0, 0.0)
    q3 = np.arccos(np.clip(c3, -1.0, 1.0)) * np.where(el == 0, 1.0, -1.0)
    q2 = np.arctan2(v, u) - np.arctan2(a3 * np.sin(q3), a2 + a3 * np.cos(q3))
    q4 = q234 - q2 - q3
    sol = np.stack([q1, q2, q3, q4, q5, q6], 1) - np.asarray(model.theta)
    return _wrap_pi(sol), np.maximum(shoulder_over, elbow_over)


def _wrap_pi(q: np.ndarray) -> np.ndarray:
    """Angles wrapped into (-pi, pi]."""
    return np.pi - np.mod(np.pi - q, TWO_PI)


def nearest_equivalent(
    model: KinematicModel, q: np.ndarray, q_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Shift each joint of q (..., n) by multiples of 2 pi to lie nearest q_ref while inside the limits.

    Returns (q_shifted, ok) where ok (...) is False if some joint has no equivalent inside its limits.
    """
    q = np.asarray(q, dtype=float)
    q_ref = np.broadcast_to(np.asarray(q_ref, dtype=float), q.shape)
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    k0 = np.round((q_ref - q) / TWO_PI)
    nearest = q + TWO_PI * k0  # the equivalent nearest q_ref: the answer wherever it lies inside the limits
    if np.all((nearest >= lo - 1e-12) & (nearest <= hi + 1e-12)):
        return np.clip(nearest, lo, hi), np.ones(q.shape[:-1], bool)
    cands = q[..., None] + TWO_PI * (k0[..., None] + np.array([-1.0, 0.0, 1.0]))  # (..., n, 3)
    inside = (cands >= lo[:, None] - 1e-12) & (cands <= hi[:, None] + 1e-12)
    dist = np.where(inside, np.abs(cands - q_ref[..., None]), np.inf)
    pick = np.argmin(np.nan_to_num(dist, nan=np.inf), axis=-1)
    shifted = np.take_along_axis(cands, pick[..., None], axis=-1)[..., 0]
    ok = np.all(np.any(inside, axis=-1), axis=-1) & np.all(np.isfinite(q), axis=-1)
    return np.clip(shifted, lo, hi), ok


def select_nearest_branch(
    model: KinematicModel, q_branches: np.ndarray, valid: np.ndarray, q_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pick, per target, the valid branch (2 pi-shifted into the limits) nearest q_ref (Euclidean).

    q_branches (N, B, n), valid (N, B), q_ref (n,) or (N, n).
    Returns (q (N, n), branch index (N,), found (N,)); rows without any usable branch are NaN.
    """
    q_branches = np.asarray(q_branches, dtype=float)
    N, B, n = q_branches.shape
    ref = np.broadcast_to(np.asarray(q_ref, dtype=float), (N, n))[:, None, :]
    shifted, in_limits = nearest_equivalent(model, q_branches, np.broadcast_to(ref, (N, B, n)))
    usable = np.asarray(valid, bool) & in_limits
    dist = np.where(usable, np.linalg.norm(np.nan_to_num(shifted - ref, nan=np.inf), axis=2), np.inf)
    idx = np.argmin(dist, axis=1)
    found = np.any(usable, axis=1)
    q = shifted[np.arange(N), idx]
    q[~found] = np.nan
    return q, idx, found


def project_to_limits(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Bring joints (N, n) inside the limits: a joint beyond a limit is first shifted by 2 pi (same
    pose, revolute joint) if that lands inside, else clamped to the limit."""
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    q = np.array(q, dtype=float)
    down = q - TWO_PI
    up = q + TWO_PI
    q = np.where((q > hi) & (down >= lo), down, q)
    q = np.where((q < lo) & (up <= hi), up, q)
    return np.clip(q, lo, hi)


def random_joints(model: KinematicModel, size: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform random joints (size, n) within the limits, each joint drawn from one turn at most
    (a 2 pi window centred in its range), as wider draws only add equivalent postures."""
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    mid = 0.5 * (lo + hi)
    half = np.minimum(0.5 * (hi - lo), np.pi)
    return rng.uniform(mid - half, mid + half, size=(size, model.n_joints))


def default_home(model: KinematicModel) -> np.ndarray:
    """A reasonable reference posture: UR working pose (elbow up, tool down); zeros (clipped) otherwise."""
    if is_ur_like(model):
        home = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])
    else:
        home = np.zeros(model.n_joints)
    return np.clip(home, model.joint_limits[:, 0], model.joint_limits[:, 1])


def reach_bound(model: KinematicModel, tool_offset_m: float = 0.0) -> float:
    """Upper bound on the distance from the base origin to any tool point (triangle inequality)."""
    links = np.hypot(np.asarray(model.a, float), np.asarray(model.d, float)).sum()
    return float(links + np.linalg.norm(np.asarray(model.T_last_flange)[:3, 3]) + tool_offset_m)


# --------------------------------------------------------------------------------------------------
# Levenberg-Marquardt (Sugihara)
# --------------------------------------------------------------------------------------------------


@dataclass
class _Problem:
    model: KinematicModel
    mode: str
    targets: np.ndarray  # (N,4,4) T_base_tool or (N,3)
    T_flange_tool: np.ndarray  # (4,4)
    weights: np.ndarray  # (m,) diagonal of W_E
    wbar: float
    tol_position: float
    tol_rotation: float
    tool_is_flange: bool = field(init=False)  # T_flange_tool is the identity: errors skip the product

    def __post_init__(self) -> None:
        self.tool_is_flange = bool(np.array_equal(self.T_flange_tool, np.eye(4)))

    def residual(self, q: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Error e (k, m) taking the current tool to the target, for targets `rows`."""
        return self._error(forward_kinematics(self.model, q), rows)

    def residual_and_jacobian(self, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The residual at q for `target` (the rows' targets, `targets[rows]`) and the Jacobian, from one
        pass over the chain (the same numbers as `residual` and `jacobian` alone)."""
        T, J = pose_and_jacobian(self.model, q, self.T_flange_tool[:3, 3])
        return self._error_to(T, target), (J if self.mode == "pose" else J[:, :3])

    def _error(self, T_base_flange: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return self._error_to(T_base_flange, self.targets[rows])

    def _error_to(self, T_base_flange: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The error taking the tool at the flange poses `T_base_flange` to `target` (k targets)."""
        T = T_base_flange if self.tool_is_flange else T_base_flange @ self.T_flange_tool
        if self.mode == "pose":
            dp = target[:, :3, 3] - T[:, :3, 3]
            return np.concatenate([dp, rotation_log(target[:, :3, :3] @ np.swapaxes(T[:, :3, :3], 1, 2))], 1)
        return target - T[:, :3, 3]

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        J = geometric_jacobian(self.model, q, self.T_flange_tool[:3, 3])
        return J if self.mode == "pose" else J[:, :3]

    def converged(self, e: np.ndarray) -> np.ndarray:
        # |e| as np.linalg.norm computes it, without its call overhead (LM tests every iteration)
        dp, dr = e[:, :3], e[:, 3:]
        ok = np.sqrt(np.add.reduce(dp * dp, axis=1)) < self.tol_position
        if self.mode == "pose":
            ok &= np.sqrt(np.add.reduce(dr * dr, axis=1)) < self.tol_rotation
        return ok


def _limited_step(model: KinematicModel, q: np.ndarray, A: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Solve A dq = g, then hold joints that would leave their limits (and cannot wrap by 2 pi) at the
    limit and re-solve for the others with that motion accounted for (two active-set passes), so the
    free joints still make the best move instead of a clipped, no longer descending one."""
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    span_ok = (hi - lo) >= TWO_PI  # such a joint can always wrap back inside
    dq = np.linalg.solve(A, g[..., None])[..., 0]
    fixed = np.zeros(q.shape, bool)
    for _ in range(2):
        out = ~span_ok & ((q + dq < lo) | (q + dq > hi))
        if not np.any(out & ~fixed):
            break
        fixed |= out
        c = np.where(fixed, np.clip(q + dq, lo, hi) - q, 0.0)
        free = ~fixed
        M = A * (free[:, :, None] & free[:, None, :]) + fixed[:, :, None] * np.eye(q.shape[1])
        h = np.where(fixed, c, g - np.einsum("kij,kj->ki", A, c))
        dq = np.linalg.solve(M, h[..., None])[..., 0]
    return dq


def _levenberg_marquardt(
    prob: _Problem, q0: np.ndarray, rows: np.ndarray, max_iter: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run LM on targets `rows` from seeds q0 (k, n). Returns (q, e, iterations).

    Step dq = (J^T W_E J + W_N)^-1 J^T W_E e with W_N = (E + lam * wbar) I, E = 1/2 e^T W_E e
    (Sugihara). Safeguard: a step that does not lower E is rejected and lam grows (LAM_UP); accepted
    steps shrink it (LAM_DOWN, floor LAM_MIN), so the bias fades near the solution for fast final
    convergence. Joints that would cross a limit are held there and the others re-solved
    (`_limited_step`); the result is projected onto the limits (wrapped by 2 pi where that lands inside). A target stops when converged, hopelessly stuck (lam > 1e12) or stalled (E not
    reduced by STALL_FACTOR within STALL_WINDOW iterations). Each trial point's error and
    Jacobian come from one pass over the chain; the Jacobian is kept where the step is accepted.
    The rows still iterating live in compact arrays (`_LMRows`), compressed only when some stop: an
    iteration of a few hopeless rows costs its numpy calls, not gathers and scatters of every array.
    """
    q = project_to_limits(prob.model, q0)
    e, J = prob.residual_and_jacobian(q, prob.targets[rows])
    lm = _LMRows.begin(prob, q, e, J, rows)
    lo, hi = prob.model.joint_limits[:, 0], prob.model.joint_limits[:, 1]
    wraps = bool(np.all(hi - lo >= TWO_PI))  # every joint can wrap back inside: no joint is ever held
    W = prob.weights
    eye = np.eye(q.shape[1])
    for it in range(1, max_iter + 1):
        if lm.idx.size == 0:
            break
        JtW = np.swapaxes(lm.J, 1, 2) * W
        A = JtW @ lm.J + (lm.cost + lm.lam * prob.wbar)[:, None, None] * eye
        g = np.einsum("knm,km->kn", JtW, lm.e)
        if wraps:  # what _limited_step's first solve gives
            q_new = lm.q + np.linalg.solve(A, g[..., None])[..., 0]
        else:
            q_new = lm.q + _limited_step(prob.model, lm.q, A, g)
        if not ((q_new >= lo) & (q_new <= hi)).all():
            q_new = project_to_limits(prob.model, q_new)
        e_new, J_new = prob.residual_and_jacobian(q_new, lm.target)
        E_new = 0.5 * np.einsum("km,m,km->k", e_new, W, e_new)
        accept = E_new < lm.cost
        lm.q[accept], lm.e[accept] = q_new[accept], e_new[accept]
        lm.cost[accept], lm.J[accept] = E_new[accept], J_new[accept]
        lm.lam = np.where(accept, np.maximum(lm.lam * LAM_DOWN, LAM_MIN), lm.lam * LAM_UP)
        lm.iters += 1
        done = prob.converged(lm.e) | (lm.lam > 1e12)
        if it % STALL_WINDOW == 0:  # E must fall by STALL_FACTOR every STALL_WINDOW iterations
            done |= lm.cost > STALL_FACTOR * lm.cost_checked
            lm.cost_checked = lm.cost.copy()
        if done.any():
            lm.leave(done, q, e)
    lm.leave(np.ones(lm.idx.size, bool), q, e)
    return q, e, lm.iters_all


@dataclass
class _LMRows:
    """`_levenberg_marquardt`'s rows still iterating: their batch rows `idx` and compact copies of
    their joints, residuals, costs, Jacobians, targets, bias multipliers, iteration counts and the cost
    at the last stall check."""

    idx: np.ndarray
    q: np.ndarray
    e: np.ndarray
    cost: np.ndarray  # E = 1/2 e^T W_E e
    J: np.ndarray
    target: np.ndarray
    lam: np.ndarray
    iters: np.ndarray
    cost_checked: np.ndarray  # E at the last stall check
    iters_all: np.ndarray  # (k,) every row's iterations, written as rows stop

    @classmethod
    def begin(cls, prob: _Problem, q: np.ndarray, e: np.ndarray, J: np.ndarray, rows: np.ndarray) -> _LMRows:
        """The rows not converged at the seeds q (their residuals e, Jacobians J), for targets `rows`."""
        k = len(q)
        live = np.flatnonzero(~prob.converged(e))
        cost = _cost(prob, e[live])
        return cls(
            live, q[live], e[live], cost, J[live], prob.targets[rows[live]], np.ones(live.size),
            np.zeros(live.size, int), cost.copy(), np.zeros(k, int),
        )  # fmt: skip

    def leave(self, mask: np.ndarray, q: np.ndarray, e: np.ndarray) -> None:
        """The rows in `mask` stop: their joints, residuals and iterations are written into the batch's
        q, e and `iters_all`; the others stay."""
        rows = self.idx[mask]
        q[rows], e[rows], self.iters_all[rows] = self.q[mask], self.e[mask], self.iters[mask]
        if mask.all():
            self.idx = self.idx[:0]
            return
        keep = ~mask
        for name in ("idx", "q", "e", "cost", "J", "target", "lam", "iters", "cost_checked"):
            setattr(self, name, getattr(self, name)[keep])


# --------------------------------------------------------------------------------------------------
# Public solver
# --------------------------------------------------------------------------------------------------


def _check_targets(model: KinematicModel, targets: np.ndarray, mode: str) -> np.ndarray:
    if mode == "pose":
        return _as_transforms(targets, "targets (T_base_tool)")
    if mode == "position":
        t = np.asarray(targets, dtype=float)
        if t.ndim == 1:
            t = t[None]
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"position targets must be (N, 3) points in metres, got shape {t.shape}")
        if not np.all(np.isfinite(t)):
            raise ValueError("position targets contain NaN or inf")
        return t
    raise ValueError(f"mode must be 'pose' or 'position', got {mode!r}")


def _tool_frame(T_flange_tool: np.ndarray | None, p_flange_tool: np.ndarray | None) -> np.ndarray:
    if T_flange_tool is not None and p_flange_tool is not None:
        raise ValueError("give either T_flange_tool or p_flange_tool, not both")
    T = np.eye(4)
    if T_flange_tool is not None:
        T = _as_transforms(T_flange_tool, "T_flange_tool")[0]
        if np.asarray(T_flange_tool).ndim != 2:
            raise ValueError("T_flange_tool must be a single (4, 4) transform")
    elif p_flange_tool is not None:
        p = np.asarray(p_flange_tool, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"p_flange_tool must be a finite (3,) point in metres, got {p.shape}")
        T[:3, 3] = p
    return T


def _analytic_flange_targets(model: KinematicModel, prob: _Problem, q_ref: np.ndarray) -> np.ndarray:
    """T_base_flange per target for the closed form; in position mode with the reference tool orientation."""
    if prob.mode == "pose":
        return prob.targets @ invert(prob.T_flange_tool)
    R_ref = (forward_kinematics(model, q_ref) @ prob.T_flange_tool)[:, :3, :3]
    T_base_tool = np.zeros((len(prob.targets), 4, 4))
    T_base_tool[:, :3, :3] = R_ref
    T_base_tool[:, :3, 3] = prob.targets
    T_base_tool[:, 3, 3] = 1.0
    return T_base_tool @ invert(prob.T_flange_tool)


def _analytic_seeds(
    model: KinematicModel, T_base_flange: np.ndarray, q_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All 8 analytic branches as seeds, exact ones first, each group by distance to q_ref.

    Returns (q (N, 8, n), usable (N, 8), out_of_reach (N,)). Out-of-reach branches are kept, stretched:
    on a real arm, or near a wrist singularity where the closed form is ill-conditioned, the nearest
    stretched posture is still a good seed. out_of_reach: see `ur_wrist_out_of_reach`.
    """
    qb, overshoot = _ur_branches(model, T_base_flange)
    N, B, n = qb.shape
    ref = np.broadcast_to(np.asarray(q_ref, dtype=float), (N, n))[:, None, :]
    shifted, usable = nearest_equivalent(model, qb, np.broadcast_to(ref, (N, B, n)))
    dist = np.linalg.norm(shifted - ref, axis=2)
    key = np.where(usable, dist + np.where(overshoot > 1e-9, 1e6, 0.0), np.inf)
    order = np.argsort(key, axis=1, kind="stable")
    ranked, usable = np.take_along_axis(shifted, order[:, :, None], 1), np.take_along_axis(usable, order, 1)
    return ranked, usable, ur_wrist_out_of_reach(model, T_base_flange)


def ur_wrist_out_of_reach(
    model: KinematicModel, T_base_flange: np.ndarray, slack: float = REACH_SLACK
) -> np.ndarray:
    """(N,) True where the wrist centre (frame-5 origin) is provably out of reach of a UR-shaped arm.

    The wrist centre sits at offset d4 along the joint-2 axis, so it needs r_xy >= |d4|, and within
    |a2| + |a3| + |d5| of the shoulder in the arm plane. Both tests only use p - d6 z6, which is
    well-conditioned even at wrist singularities; `slack` (relative) absorbs calibration errors.
    """
    T = T_base_flange @ invert(np.asarray(model.T_last_flange, float))
    p5 = T[:, :3, 3] - model.d[5] * T[:, :3, 2]
    r_xy = np.hypot(p5[:, 0], p5[:, 1])
    d4 = abs(model.d[3])
    planar = abs(model.a[1]) + abs(model.a[2]) + abs(model.d[4])
    dist = np.linalg.norm(p5 - np.array([0.0, 0.0, model.d[0]]), axis=1)
    return (r_xy < d4 * (1.0 - slack)) | (dist > np.hypot(planar, d4) * (1.0 + slack))


def ur_seed(model: KinematicModel, T_base_flange: np.ndarray, q_near: np.ndarray | None = None) -> np.ndarray:
    """The first seed `solve_ik` uses on a UR-shaped model: the exact closed-form branch nearest q_near
    (default `default_home`), else the nearest stretched one; (N, 6) within the joint limits."""
    q_ref = default_home(model) if q_near is None else np.asarray(q_near, dtype=float)
    ranked, usable, _ = _analytic_seeds(model, _as_transforms(T_base_flange, "T_base_flange"), q_ref)
    return np.where(usable[:, 0, None], ranked[:, 0], q_ref)


@dataclass(frozen=True)
class IKOptions:
    """How hard `solve_ik` searches and when it calls a target solved.

    Success only if the final position error < `tol_position` (m) and, in pose mode, the rotation error
    < `tol_rotation` (rad). W_E weighs position (m) against rotation (rad) as 1 rad <-> `length_scale` m;
    `wbar` is LM's bias. Each LM attempt runs at most `max_iter` iterations; after the given and analytic
    seeds (the latter only with `use_analytic`), `restarts` random joint sets within limits (seed `rng`).
    `newton_first=False` skips the Newton steps from the first seed (a caller whose own Newton from
    `q_seed` to a looser tolerance already failed: the same steps cannot succeed).
    """

    max_iter: int = 100
    tol_position: float = 1e-10
    tol_rotation: float = 1e-9
    length_scale: float = 0.3
    wbar: float = 1e-3
    restarts: int = 50
    use_analytic: bool = True
    rng: np.random.Generator | int | None = 0
    newton_first: bool = True


def solve_ik(
    model: KinematicModel,
    targets: np.ndarray,
    q_seed: np.ndarray | None = None,
    mode: str = "pose",
    T_flange_tool: np.ndarray | None = None,
    p_flange_tool: np.ndarray | None = None,
    q_near: np.ndarray | None = None,
    options: IKOptions = IKOptions(),
) -> IKResult:
    """Joints reaching N targets: T_base_tool (N,4,4) in "pose" mode, tool points (N,3) in "position" mode.

    Seeds, tried in order on the targets still unsolved: `q_seed` (N,n) or (n,) if given; on a UR-shaped
    model (and `options.use_analytic`) the analytic branches, nearest to `q_near` (default `default_home`)
    first (the first seed of all is tried with a few Newton steps before LM: most targets end there);
    `q_near` itself when no q_seed is given; then `options.restarts` random joint sets within limits.
    The joints are always within the model's limits; success as `IKOptions` says.
    """
    o = options
    max_iter, restarts, length_scale, wbar = o.max_iter, o.restarts, o.length_scale, o.wbar
    tol_position, tol_rotation = o.tol_position, o.tol_rotation
    if max_iter < 1 or restarts < 0:
        raise ValueError("max_iter must be >= 1 and restarts >= 0")
    if min(tol_position, tol_rotation, length_scale, wbar) <= 0:
        raise ValueError("tol_position, tol_rotation, length_scale and wbar must be positive")
    tgt = _check_targets(model, targets, mode)
    T_ft = _tool_frame(T_flange_tool, p_flange_tool)
    weights = np.array([1.0, 1.0, 1.0] + ([length_scale**2] * 3 if mode == "pose" else []))
    prob = _Problem(model, mode, tgt, T_ft, weights, wbar, tol_position, tol_rotation)
    q_ref = default_home(model) if q_near is None else np.asarray(q_near, dtype=float)
    if q_ref.shape != (model.n_joints,) or not np.all(np.isfinite(q_ref)):
        raise ValueError(f"q_near must be a finite ({model.n_joints},) joint vector, got {q_ref.shape}")
    generator = o.rng if isinstance(o.rng, np.random.Generator) else np.random.default_rng(o.rng)

    seeds = _seeds(prob, q_seed, q_ref, o.use_analytic and is_ur_like(model), restarts)
    best = _Best.from_seed(prob, seeds.q[0])
    beyond = _beyond_reach(prob, seeds.no_branch)
    if o.newton_first and (q_seed is not None or seeds.analytic):
        _newton_from_first_seed(prob, best, seeds.q[0], seeds.ok[0] & ~beyond)
    _levenberg_marquardt_attempts(prob, best, seeds, beyond, generator, max_iter)

    err_pos = np.linalg.norm(best.e[:, :3], axis=1)
    err_rot = np.linalg.norm(best.e[:, 3:], axis=1) if mode == "pose" else np.full(len(tgt), np.nan)
    best.success &= model.within_limits(best.q, tol=1e-12)
    reason = _diagnose(prob, best.q, best.success, beyond, seeds.no_branch)
    return IKResult(best.q, best.success, best.iterations, reason, err_pos, err_rot, best.attempts)


@dataclass
class _Seeds:
    """Candidate seeds per target in the order they are tried (None: random joints, drawn when needed)."""

    q: list[np.ndarray | None]  # (N, n) each
    ok: list[np.ndarray]  # (N,) bool each: where the seed exists
    analytic: bool  # the closed-form branches are among them
    no_branch: np.ndarray | None  # (N,) bool: no closed-form branch, well beyond the nominal reach


def _seeds(
    prob: _Problem, q_seed: np.ndarray | None, q_ref: np.ndarray, analytic: bool, restarts: int
) -> _Seeds:
    """The caller's seed, the analytic branches nearest q_ref, q_ref itself (without a caller's seed),
    then `restarts` random draws."""
    model, N, n = prob.model, len(prob.targets), prob.model.n_joints
    seeds: list[np.ndarray | None] = []
    seed_ok: list[np.ndarray] = []
    no_branch = None
    if q_seed is not None:
        qs = np.asarray(q_seed, dtype=float)
        qs = np.broadcast_to(qs, (N, n)) if qs.shape == (n,) else qs
        if qs.shape != (N, n) or not np.all(np.isfinite(qs)):
            raise ValueError(f"q_seed must be finite ({N}, {n}) or ({n},), got {np.shape(q_seed)}")
        seeds.append(qs)
        seed_ok.append(np.ones(N, bool))
    if analytic:
        T_base_flange = _analytic_flange_targets(model, prob, q_ref)
        ranked, usable, no_branch = _analytic_seeds(model, T_base_flange, q_ref)
        if prob.mode != "pose":
            no_branch = None  # the orientation was made up: no verdict on reach
        for b in range(ranked.shape[1]):
            seeds.append(np.where(usable[:, b, None], ranked[:, b], q_ref))
            seed_ok.append(usable[:, b])
    if q_seed is None:
        seeds.append(np.broadcast_to(q_ref, (N, n)))
        seed_ok.append(np.ones(N, bool))
    seeds.extend([None] * restarts)
    seed_ok.extend([np.ones(N, bool)] * restarts)
    return _Seeds(seeds, seed_ok, analytic, no_branch)


@dataclass
class _Best:
    """The best joints found so far per target, their error and cost, and the work spent on them."""

    q: np.ndarray  # (N, n)
    e: np.ndarray  # (N, m) residual
    E: np.ndarray  # (N,) cost 1/2 e^T W_E e
    iterations: np.ndarray  # (N,) int
    attempts: np.ndarray  # (N,) int
    success: np.ndarray  # (N,) bool

    @classmethod
    def from_seed(cls, prob: _Problem, first: np.ndarray | None) -> _Best:
        """Start from the first seed, projected into the joint limits."""
        assert first is not None  # q_seed, an analytic branch or q_near: never a random draw
        N = len(prob.targets)
        q = project_to_limits(prob.model, np.broadcast_to(first, (N, prob.model.n_joints)))
        e = prob.residual(q, np.arange(N))
        return cls(q, e, _cost(prob, e), np.zeros(N, int), np.zeros(N, int), np.zeros(N, bool))


def _cost(prob: _Problem, e: np.ndarray) -> np.ndarray:
    """1/2 e^T W_E e per row."""
    return 0.5 * np.einsum("km,m,km->k", e, prob.weights, e)


def _beyond_reach(prob: _Problem, no_branch: np.ndarray | None) -> np.ndarray:
    """Targets no joints can reach: farther than the reach bound, or (pose mode) without an analytic branch."""
    tool_len = float(np.linalg.norm(prob.T_flange_tool[:3, 3]))
    point = prob.targets[:, :3, 3] if prob.mode == "pose" else prob.targets
    beyond = np.linalg.norm(point, axis=1) > reach_bound(prob.model, tool_len)
    if no_branch is not None:
        beyond |= no_branch  # well beyond the nominal reach: no small model error makes it reachable
    return beyond


def _newton_from_first_seed(
    prob: _Problem, best: _Best, first: np.ndarray | None, rows_ok: np.ndarray
) -> None:
    """A few Newton steps from the first seed (the caller's, or the nearest closed-form branch): usually
    close, they finish most targets far cheaper than LM; the rest go through the LM attempts."""
    todo = np.flatnonzero(rows_ok)
    if not todo.size:
        return
    model, T_ft, tgt = prob.model, prob.T_flange_tool, prob.targets
    first_seed = np.asarray(first)  # the first seed's ok rows are False where it is missing
    if prob.mode == "pose":
        T_f = tgt[todo] @ invert(T_ft)
        options = NewtonOptions(
            max_steps=NEWTON_STEPS,
            tol_position=0.5 * prob.tol_position,
            tol_rotation=0.5 * prob.tol_rotation,
            validate=False,
        )
        nr = newton_ik(model, T_f, first_seed[todo], options=options)
    else:
        options = NewtonOptions(max_steps=NEWTON_STEPS, tol_position=0.5 * prob.tol_position)
        nr = newton_ik(model, tgt[todo], first_seed[todo], "position", T_ft[:3, 3], options)
    e = prob.residual(nr.q, todo)
    conv = prob.converged(e) & model.within_limits(nr.q, tol=1e-12)
    done = todo[conv]
    best.q[done], best.e[done] = nr.q[conv], e[conv]
    best.E[done] = _cost(prob, e[conv])
    best.iterations[todo] += nr.steps
    best.attempts[done] += 1
    best.success[done] = True


def _levenberg_marquardt_attempts(
    prob: _Problem,
    best: _Best,
    seeds: _Seeds,
    beyond: np.ndarray,
    generator: np.random.Generator,
    max_iter: int,
) -> None:
    """LM from each seed in turn on the targets still unsolved, keeping the best answer per target."""
    for s, ok in zip(seeds.q, seeds.ok, strict=True):
        if np.all(best.success | beyond):
            break
        todo = np.flatnonzero(~best.success & ~beyond & ok)
        if todo.size == 0:
            continue
        q0 = random_joints(prob.model, todo.size, generator) if s is None else s[todo]
        q, e, it = _levenberg_marquardt(prob, q0, todo, max_iter)
        best.iterations[todo] += it
        best.attempts[todo] += 1
        cost = _cost(prob, e)
        conv = prob.converged(e)
        better = conv | (cost < best.E[todo])
        upd = todo[better]
        best.q[upd], best.e[upd], best.E[upd] = q[better], e[better], cost[better]
        best.success[todo[conv]] = True


def _diagnose(
    prob: _Problem,
    q: np.ndarray,
    success: np.ndarray,
    beyond: np.ndarray,
    no_branch: np.ndarray | None,
) -> np.ndarray:
    """Reason string per target (see REASONS)."""
    N = len(q)
    reason = np.full(N, REASON_MAX_ITER, dtype=object)
    reason[success] = REASON_OK
    failed = np.flatnonzero(~success)
    if failed.size == 0:
        return reason.astype(str)
    lo, hi = prob.model.joint_limits[:, 0], prob.model.joint_limits[:, 1]
    qf = q[failed]
    at_limit = np.any((qf <= lo + 1e-9) | (qf >= hi - 1e-9), axis=1)
    sv = np.linalg.svd(prob.jacobian(qf), compute_uv=False)
    singular = sv[:, -1] < 1e-6 * max(sv[:, 0].max(), 1e-12)
    unreach = beyond[failed] | (no_branch[failed] if no_branch is not None else False)
    r = np.where(singular, REASON_SINGULAR, REASON_MAX_ITER).astype(object)
    r[at_limit] = REASON_JOINT_LIMITS
    r[unreach] = REASON_UNREACHABLE
    reason[failed] = r
    return reason.astype(str)


# --------------------------------------------------------------------------------------------------
# Fast path for many nearby targets: closed-form seed + batched Newton
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NewtonResult:
    """Outcome of `newton_ik` per target: joints, final errors, convergence and steps taken, and the
    flange pose and Jacobian at the returned joints (the last evaluation, for a warm `start`)."""

    q: np.ndarray  # (N, n) rad
    error: np.ndarray  # (N,) position error, m (flange in pose mode, tool point in position mode)
    rotation_error: np.ndarray  # (N,) rad, NaN in position mode
    converged: np.ndarray  # (N,) bool
    steps: np.ndarray  # (N,) int
    # (N, 4, 4) T_base_flange and (N, 6, n) geometric Jacobian (at the tool point in position mode) at q;
    # NaN rows where the last step was certified by its bound (see `newton_ik`), not evaluated.
    pose: np.ndarray
    jacobian: np.ndarray


@dataclass(frozen=True)
class NewtonOptions:
    """When `newton_ik` stops: converged below `tol_position` (m) and, in pose mode, `tol_rotation` (rad),
    or after `max_steps` steps. `damping` regularises the normal equations where a Jacobian is exactly
    singular (pose mode) and the minimum-norm step (position mode). `validate=False` skips the input checks
    (hot loops)."""

    max_steps: int = 8
    tol_position: float = 1e-11
    tol_rotation: float = 1e-10
    damping: float = 1e-12
    validate: bool = True


def newton_ik(
    model: KinematicModel,
    targets: np.ndarray,
    q_seed: np.ndarray,
    mode: str = "pose",
    p_flange_tool: np.ndarray | None = None,
    options: NewtonOptions = NewtonOptions(),
    start: tuple[np.ndarray, np.ndarray] | None = None,
) -> NewtonResult:
    """Finish IK from nearby seeds (N, n) with batched Gauss-Newton steps and the analytic Jacobian.

    targets: flange poses T_base_flange (N, 4, 4) in "pose" mode; tool points (N, 3) in "position" mode
    (tool point `p_flange_tool` in the flange), where the step is the minimum-norm one, so the seed's
    orientation is kept to first order. For seeds already close to the answer (a closed-form branch of
    a slightly different model, the previous solution of a nearby target) convergence is quadratic,
    typically 2-3 steps; targets leave the batch as they converge. No globalisation: a target that
    does not converge is reported, for the caller to fall back to `solve_ik`. Joints stay within the
    limits (wrapped by 2 pi or clamped).

    A step that solves the linearised error exactly leaves only the chain's second-order term, which
    the Jacobian bounds: |dp| <= V (sum |dq_i|)^2 / 2 with V the largest norm of a linear column along
    the step, and |d angle| <= (sum |dq_i|)^2 (rotations compose, the error's log map bends). A row
    whose step makes twice that bound (plus what it leaves of the linear error) fall below half the tolerances,
    inside the limits, has converged without another evaluation (the cheap convergence test): its
    error is reported as that bound and its `pose` and `jacobian` rows are NaN.
    `start`: (pose, jacobian) already evaluated at the seeds (within the limits), e.g. a previous
    result's `pose` and `jacobian` when the targets moved: the first evaluation is then skipped for
    every row that is not NaN there.
    """
    pose = mode == "pose"
    if options.validate:
        targets = _check_targets(model, targets, mode)
        q_seed = model.check_joints(q_seed)
        if len(q_seed) != len(targets):
            raise ValueError(f"{len(q_seed)} seeds for {len(targets)} targets")
    q = project_to_limits(model, q_seed)
    N, n = q.shape
    tool = None if pose else (np.zeros(3) if p_flange_tool is None else np.asarray(p_flange_tool, float))
    if start is not None and (np.shape(start[0]) != (N, 4, 4) or np.shape(start[1]) != (N, 6, n)):
        raise ValueError(f"start must be poses ({N}, 4, 4) and Jacobians ({N}, 6, {n}) at the seeds")
    step_rule = _NewtonStep(model, tool, options)
    rows = _NewtonRows.begin(q, np.asarray(targets, float), pose)
    for step in range(options.max_steps + 1):
        if step == 0 and start is not None:
            end, J = _evaluate_from_start(model, rows.qa, tool, start)
        else:
            end, J = pose_and_jacobian(model, rows.qa, tool)
        e, p2, r2, done = step_rule.error(rows.tgt, end)
        if step == options.max_steps:
            done[:] = True
        if done.any() or not done.size:
            whole = done.all() and rows.all_active()
            if whole and step == 0 and start is not None:  # the answers must not alias the caller's start
                end, J = end.copy(), J.copy()
            keep = rows.leave(done, step, np.sqrt(p2), None if r2 is None else np.sqrt(r2), end, J)
            if keep is None:
                break
            J, e = J[keep], e[keep]
        dq = step_rule.solve(J, e)
        q_step = rows.qa + dq
        inside = np.all((q_step >= step_rule.lo) & (q_step <= step_rule.hi), axis=1)
        rows.qa = q_step if inside.all() else project_to_limits(model, q_step)
        bound_p, bound_r = step_rule.bounds(J, e, dq)
        cert = (bound_p < step_rule.cert_p) & inside
        if bound_r is not None:
            cert &= bound_r < step_rule.cert_r
        if cert.any() and rows.leave(cert, step + 1, bound_p, bound_r, None, None) is None:
            break
    conv = (rows.pos_err < options.tol_position) & ((rows.rot_err < options.tol_rotation) if pose else True)
    rot_err = rows.rot_err if pose else np.full(N, np.nan)
    return NewtonResult(rows.q, rows.pos_err, rot_err, conv, rows.steps, rows.pose, rows.jacobian)


def _evaluate_from_start(
    model: KinematicModel, q: np.ndarray, tool: np.ndarray | None, start: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The flange poses and Jacobians at the seeds: the caller's `start`, evaluated only where it is NaN
    (all of them again when most rows are: evaluating everything is cheaper than gathering)."""
    end, J = np.asarray(start[0], float), np.asarray(start[1], float)
    missing = np.flatnonzero(np.isnan(end[:, 0, 0]) | np.isnan(J[:, 0, 0]))
    if 2 * missing.size > len(q):  # most rows were certified without an evaluation last time
        return pose_and_jacobian(model, q, tool)
    if missing.size:
        end, J = end.copy(), J.copy()
        end[missing], J[missing] = pose_and_jacobian(model, q[missing], tool)
    return end, J


class _NewtonStep:
    """One Gauss-Newton step of `newton_ik`: the error at the current joints, the step that solves its
    linearisation, and the bound on what the step leaves (the certificate that saves an evaluation)."""

    def __init__(self, model: KinematicModel, tool: np.ndarray | None, options: NewtonOptions) -> None:
        self.tool, self.options = tool, options
        self.pose = tool is None
        self.lo, self.hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
        # L bounds every second derivative of the tip, |z_i x (z_j x (p - o_j))| <= |p - o_j|: the joint
        # axes and the tip lie within the reach of the base.
        self.L = 2.0 * reach_bound(model, 0.0 if tool is None else float(np.linalg.norm(tool)))
        self.cert_p, self.cert_r = 0.5 * options.tol_position, 0.5 * options.tol_rotation
        self.eye = np.eye(3 if not self.pose else model.n_joints)

    def error(
        self, target: np.ndarray, end: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
        """The error e (k, 6 or 3) taking the current flange poses `end` to the targets, its squared
        position and rotation norms (rotation None in position mode), and which rows are within tolerance."""
        tol_p, tol_r = self.options.tol_position, self.options.tol_rotation
        if self.pose:
            e = _frame_error(target, end)
            e2 = e * e
            p2, r2 = e2[:, :3].sum(1), e2[:, 3:].sum(1)
            return e, p2, r2, (p2 < tol_p**2) & (r2 < tol_r**2)
        assert self.tool is not None
        e = target - (end[:, :3, :3] @ self.tool + end[:, :3, 3])
        p2 = np.einsum("ki,ki->k", e, e)
        return e, p2, None, p2 < tol_p**2

    def solve(self, J: np.ndarray, e: np.ndarray) -> np.ndarray:
        """The step dq (k, n) that solves the linearised error."""
        damping = self.options.damping
        if self.pose:  # square: solve J dq = e; damped normal equations only if a J is exactly singular
            try:
                return np.linalg.solve(J, e[..., None])[..., 0]
            except np.linalg.LinAlgError:
                Jt = np.swapaxes(J, 1, 2)
                normal = Jt @ J + damping * self.eye
                return np.linalg.solve(normal, np.einsum("kim,km->ki", Jt, e)[..., None])[..., 0]
        # minimum norm: dq = J^T (J J^T)^-1 e
        Jv = J[:, :3]
        A = Jv @ np.swapaxes(Jv, 1, 2) + damping * self.eye
        return np.einsum("kmi,km->ki", Jv, np.linalg.solve(A, e[..., None])[..., 0])

    def bounds(self, J: np.ndarray, e: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Bounds on the position (m) and rotation (rad; None in position mode) errors the step leaves.

        The tip's second derivatives z_i x v_j are bounded by the largest |v_j| (the Jacobian's linear
        columns here), which moves by at most L sum |dq| along the step. What the step leaves of the
        linearised error itself (rounding; damping at a singularity, where a tiny step may leave most of
        the error) adds to the bound as it is.
        """
        s1 = np.abs(dq).sum(1)
        s2 = s1 * s1
        v_max = np.sqrt((J[:, :3] ** 2).sum(1).max(1))
        left = e - ((J if self.pose else J[:, :3]) @ dq[..., None])[..., 0]
        bound_p = (v_max + self.L * s1) * s2 + np.sqrt((left[:, :3] ** 2).sum(1))
        if not self.pose:
            return bound_p, None
        return bound_p, 2.0 * s2 + np.sqrt((left[:, 3:] ** 2).sum(1))


@dataclass
class _NewtonRows:
    """`newton_ik`'s answers for the N rows of the batch, and the rows still iterating.

    The active rows live in their own compact arrays (`idx`: their rows in the batch); they are
    compressed only when some rows leave, and written back when they do.
    """

    q: np.ndarray  # (N, n) answers
    pos_err: np.ndarray  # (N,)
    rot_err: np.ndarray  # (N,) NaN in position mode
    steps: np.ndarray  # (N,) int
    pose: np.ndarray  # (N, 4, 4) at the answers, NaN where certified
    jacobian: np.ndarray  # (N, 6, n)
    idx: np.ndarray  # (k,) the active rows in the batch
    qa: np.ndarray  # (k, n) their joints
    tgt: np.ndarray  # (k, ...) their targets

    @classmethod
    def begin(cls, q: np.ndarray, target: np.ndarray, pose: bool) -> _NewtonRows:
        """Every row active, at the seeds q (N, n)."""
        N, n = q.shape
        return cls(
            q, np.zeros(N), np.full(N, np.nan), np.zeros(N, int), np.empty((N, 4, 4)), np.empty((N, 6, n)),
            np.arange(N), q.copy(), target,
        )  # fmt: skip

    def all_active(self) -> bool:
        return len(self.idx) == len(self.q)

    def leave(
        self,
        mask: np.ndarray,
        step: int,
        pos_err: np.ndarray,
        rot_err: np.ndarray | None,
        end: np.ndarray | None,
        J: np.ndarray | None,
    ) -> np.ndarray | None:
        """The active rows in `mask` leave with their joints, errors, step count and pose and Jacobian
        (None: certified, NaN). Returns the mask of the rows kept, None when no row is left."""
        if mask.all() and self.all_active():  # every row leaves at once: no gathers
            self.q, self.steps[:], self.pos_err = self.qa, step, pos_err
            if rot_err is not None:
                self.rot_err = rot_err
            if end is None or J is None:
                self.pose[:], self.jacobian[:] = np.nan, np.nan
            else:
                self.pose, self.jacobian = end, J
            return None
        rows = self.idx[mask]
        self.q[rows], self.steps[rows], self.pos_err[rows] = self.qa[mask], step, pos_err[mask]
        if rot_err is not None:
            self.rot_err[rows] = rot_err[mask]
        if end is None or J is None:
            self.pose[rows], self.jacobian[rows] = np.nan, np.nan
        else:
            self.pose[rows], self.jacobian[rows] = end[mask], J[mask]
        if mask.all():
            return None
        keep = ~mask
        self.idx, self.qa, self.tgt = self.idx[keep], self.qa[keep], self.tgt[keep]
        return keep


def _frame_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """[dp; rotation vector] (k, 6) taking `current` (k, 4, 4) to `target`, base frame."""
    dp = target[:, :3, 3] - current[:, :3, 3]
    return np.concatenate([dp, rotation_log(target[:, :3, :3] @ np.swapaxes(current[:, :3, :3], 1, 2))], 1)


def nearest_branch_seed(
    model: KinematicModel, T_base_flange: np.ndarray, q_ref: np.ndarray, validate: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Per target, the closed-form branch (within the limits, 2 pi-shifted) nearest q_ref (N, n) or (n,).

    Exact branches are preferred; a stretched one is taken only if no exact one exists. Returns
    (q (N, n), reachable (N,)): reachable is False where no branch is exact within REACH_SLACK.
    `validate=False` skips the checks of T_base_flange (callers that checked them already).
    """
    qb, overshoot = _ur_branches(model, T_base_flange, validate)
    N, B, n = qb.shape
    ref = np.broadcast_to(np.asarray(q_ref, dtype=float), (N, n))
    # Rank by the 2 pi-wrapped distance first (cheap), then shift only the pick into the limits.
    dist = np.linalg.norm(np.nan_to_num(_wrap_pi(qb - ref[:, None, :]), nan=1e9), axis=2)
    key = dist + np.where(overshoot > 1e-9, 1e6, 0.0)
    pick = np.argmin(key, axis=1)
    q, ok = nearest_equivalent(model, qb[np.arange(N), pick], ref)
    slow = np.flatnonzero(~ok)
    if slow.size:  # the nearest branch has no equivalent inside the limits: rank the shifted ones
        shifted, usable = nearest_equivalent(
            model, qb[slow], np.broadcast_to(ref[slow, None], qb[slow].shape)
        )
        d = np.linalg.norm(np.nan_to_num(shifted - ref[slow, None], nan=1e9), axis=2)
        k = np.where(usable, d + np.where(overshoot[slow] > 1e-9, 1e6, 0.0), np.inf)
        best = np.argmin(k, axis=1)
        found = np.isfinite(k[np.arange(slow.size), best])
        q[slow] = np.where(found[:, None], shifted[np.arange(slow.size), best], ref[slow])
    reachable = np.any(overshoot <= REACH_SLACK, axis=1)
    return q, reachable


def same_branch_seed(
    model: KinematicModel, T_base_flange: np.ndarray, q_ref: np.ndarray, validate: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Per target, the closed-form solution on the branch (shoulder, wrist, elbow) of the reference
    posture q_ref ((n,) or (N, n)), 2 pi-shifted nearest it: one branch instead of eight. Targets where
    that branch is out of reach or outside the limits get `nearest_branch_seed`. Same returns as it.
    `validate=False` skips the checks of T_base_flange (callers that checked them already)."""
    T = _ur_wrist_frames(model, T_base_flange, validate)
    N, n = T.shape[0], model.n_joints
    q_ref = np.asarray(q_ref, dtype=float)
    branch = ur_branch_index(model, q_ref[None] if q_ref.ndim == 1 else q_ref)
    ref = np.broadcast_to(q_ref, (N, n))
    q, over = _ur_branch(model, T, np.broadcast_to(branch, (N,)))
    q, ok = nearest_equivalent(model, q, ref)
    reachable = np.ones(N, bool)
    other = np.flatnonzero(~ok | (over > 1e-9))
    if other.size:
        q[other], reachable[other] = nearest_branch_seed(model, T_base_flange[other], ref[other], False)
    return q, reachable


def ur_branch_index(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """(N,) closed-form branch (4*shoulder + 2*wrist + elbow) a UR-shaped arm's joints q (N, 6) lie on."""
    q = model.check_joints(q)
    if not is_ur_like(model):
        raise ValueError(f"{model.name} is not a UR-shaped arm (standard DH alphas pi/2,0,0,pi/2,-pi/2,0)")
    # The bits of `_ur_branch`: shoulder 1 where cos(q1 - phi) < 0 (wrist centre behind the arm plane's
    # x axis), wrist 1 where sin q5 < 0, elbow 1 where sin q3 < 0.
    th = q + np.asarray(model.theta)
    T = forward_kinematics(model, q) @ invert(np.asarray(model.T_last_flange, float))
    p5 = T[:, :3, 3] - model.d[5] * T[:, :3, 2]
    shoulder = p5[:, 0] * np.cos(th[:, 0]) + p5[:, 1] * np.sin(th[:, 0]) < 0
    return 4 * shoulder + 2 * (np.sin(th[:, 4]) < 0) + (np.sin(th[:, 2]) < 0)


def branches_along_path(
    model: KinematicModel,
    T_base_flange: np.ndarray,
    q_start: np.ndarray,
    q_refs: np.ndarray | None = None,
) -> np.ndarray:
    """Closed-form seeds (N, 6) for an ordered path of flange poses, each the branch (2 pi-shifted into the
    limits) nearest the previous one's, the first nearest q_start: continuity instead of a fixed posture.

    `q_refs` (N, 6): where a row is finite, that target's branch is nearest it instead of the previous seed
    (a program's get_inverse_kin qnear, or a taught joint position moved to just before). Exact branches are
    preferred over stretched ones; a target without any usable branch repeats its reference. The branches of
    every target are solved in one batch, then one small step per target (8 candidates) picks them in order.
    """
    qb, overshoot = _ur_branches(model, _as_transforms(T_base_flange, "T_base_flange"))
    seeds = np.empty((len(qb), model.n_joints))
    given = None if q_refs is None else np.all(np.isfinite(q_refs), axis=1)
    prev = np.asarray(q_start, dtype=float)
    penalty = np.where(overshoot > 1e-9, 1e6, 0.0)
    for k in range(len(qb)):
        if given is not None and given[k]:
            prev = np.asarray(q_refs[k], dtype=float)  # type: ignore[index]
        shifted, usable = nearest_equivalent(model, qb[k], np.broadcast_to(prev, qb[k].shape))
        d = np.where(
            usable, np.linalg.norm(np.nan_to_num(shifted - prev, nan=1e9), axis=1) + penalty[k], np.inf
        )
        pick = int(np.argmin(d))
        seeds[k] = shifted[pick] if np.isfinite(d[pick]) else prev
        prev = seeds[k]
    return seeds
