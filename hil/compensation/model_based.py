"""Model-based pseudo-target compensation (methods.md section 4): joints that put the SMR where asked.

The calibrated model (geometry, base, tool, effects, residual map) predicts the pose actually reached
for commanded joints; the loop asks the IK of the controller-side model (the calibrated geometry
without effects, or the nominal one) for a pseudo target that it moves by what the prediction missed,
until the predicted error is below a threshold. Batched over all targets: one closed-form seed, then
a few Newton steps per iteration, each seeded with the previous joints. Poses are T_tracker_tool: the
SMR centre and the flange's orientation in the tracker frame, metres.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from hil.compensation.target_update import (
    GENERATORS,
    check_generator,
    ik_pose,
    pose_errors,
    update_pseudo_position,
    update_pseudo_target,
)
from hil.geometry.ik import (
    REASON_MAX_ITER,
    REASON_OK,
    REASON_UNREACHABLE,
    IKOptions,
    NewtonOptions,
    branches_along_path,
    default_home,
    is_ur_like,
    newton_ik,
    same_branch_seed,
    solve_ik,
    ur_branch_index,
)
from hil.geometry.kinematics import KinematicModel, forward_kinematics, pose_and_jacobian
from hil.geometry.se3 import invert
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import EffectContext, temperature_driven
from hil.model.residual_maps import map_from_dict

STATUS_OK = "ok"  # predicted error below the threshold
STATUS_MAX_ITER = "max_iter"  # iteration cap reached above the threshold (best joints kept)
STATUS_STALLED = "stalled"  # no improvement for `patience` iterations (best joints kept)
STATUS_NO_IK = "no_ik_solution"  # the IK found no joints for the (pseudo) target, cause not proven
# The IK reasons of hil.geometry.ik (unreachable, singular, joint_limits; its max_iter becomes no_ik_solution)
# mark targets whose first IK failed: their joints are NaN. A later IK failure keeps the best joints
# found and that reason.
STATUSES: tuple[str, ...] = (
    STATUS_OK,
    STATUS_MAX_ITER,
    STATUS_STALLED,
    "unreachable",
    "singular",
    "joint_limits",
    STATUS_NO_IK,
)
STATUS_DTYPE = "<U16"  # fixed-width strings hold every status (object arrays cost a conversion each time)
ENSEMBLE = "ensemble"
IK_TOL_FRACTION = 1e-3  # pseudo targets are solved to this fraction of the threshold (m; rad: / length scale)
NEWTON_STEPS = 16  # Newton steps before a target goes to solve_ik (slow seeds converge linearly at first)
# An IK to plug into the loop: (targets, seeds (k, n)) -> (joints (k, n), converged (k,)).
# Targets per block: compensate runs larger batches block by block, each block's arrays staying in the
# CPU cache (10 000 targets in one batch cost ~20 % more per target than in blocks of 2 000).
BLOCK_TARGETS = 2048
# What Newton leaves goes to solve_ik. For a target's first IK: the seed, the closed-form branches and a few
# random joint sets. For a pseudo-target update: LM from the previous joints only. The pseudo target moved by
# about the predicted error, so a solution near them exists unless the arm is at a singularity or a limit,
# where the other seeds find only another posture (or nothing, at ~50 LM iterations each: 14 attempts made
# the few such rows of a batch cost more than all its other targets together). Neither repeats Newton from
# the seed Newton just failed from (newton_first=False: the same steps to a tighter tolerance cannot succeed).
FIRST_FALLBACK = IKOptions(restarts=5, newton_first=False)
UPDATE_FALLBACK = IKOptions(restarts=0, use_analytic=False, newton_first=False)
IKSolver = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
POINT_GENERATOR = "point"  # point targets: P_p <- P_p + P_d - P_a, orientation free


class PosePredictor:
    """Actual pose T_tracker_tool (N, 4, 4) the calibrated model predicts for commanded joints.

    Position: `CalibratedModel.predict_ctx` (geometry, base, tool, every effect) plus the residual map
    when the model has one; orientation: the flange's, through the joint effects, in the tracker frame.
    Drivers the effects need (time, temperature, approach signs) are per target and follow `rows`.
    """

    def __init__(
        self,
        model: CalibratedModel,
        smr: int | None = None,
        t_s: np.ndarray | None = None,
        temperature_c: np.ndarray | None = None,
        approach: np.ndarray | None = None,
        use_map: bool = True,
        payload_kg: np.ndarray | None = None,
    ) -> None:
        self.model = model
        self.smr = sorted(model.tools)[0] if smr is None else int(smr)
        if self.smr not in model.tools:
            raise ValueError(f"the model has tool points for SMR nests {sorted(model.tools)}, not {self.smr}")
        self.tool = np.asarray(model.tools[self.smr], float)
        self.t_s, self.temperature_c, self.approach = t_s, temperature_c, approach
        self.payload_kg = payload_kg
        self.map = map_from_dict(model.residual_map) if use_map and model.residual_map is not None else None
        self.joint_effects_only = all(e.kind == "joint" for e in model.effects)

    def rows(self, sl: slice) -> PosePredictor:
        """The predictor of a block of consecutive targets: the per-target drivers sliced to it."""
        out = copy.copy(self)

        def take(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else np.asarray(x)[sl]

        out.t_s, out.temperature_c, out.approach, out.payload_kg = (
            take(self.t_s),
            take(self.temperature_c),
            take(self.approach),
            take(self.payload_kg),
        )
        return out

    def __call__(self, q: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        m = self.model
        rows = np.arange(len(q)) if rows is None else rows

        def take(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else np.asarray(x)[rows]

        tools = np.broadcast_to(self.tool, (len(q), 3))
        ctx = EffectContext(
            q, take(self.t_s), take(self.temperature_c), take(self.payload_kg), tools, take(self.approach)
        )
        T_flange = forward_kinematics(m.kinematic, q + m.joint_offsets(ctx))
        p_base = T_flange[:, :3, :3] @ self.tool + T_flange[:, :3, 3]
        if self.joint_effects_only:  # what predict_ctx computes, without a second chain
            p = p_base @ m.T_tracker_base[:3, :3].T + m.T_tracker_base[:3, 3]
        else:
            p = m.predict_ctx(ctx)
        if self.map is not None:
            p = p + self.map.predict_raw(q, p_base)
        T = np.zeros((len(q), 4, 4))
        T[:, :3, :3] = m.T_tracker_base[:3, :3] @ T_flange[:, :3, :3]
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return T

    def outside_volume(self, p_tracker: np.ndarray) -> np.ndarray:
        """(N,) True where a target lies outside the calibrated volume (residual map's, or info['volume'])."""
        p_base = (p_tracker - self.model.T_tracker_base[:3, 3]) @ self.model.T_tracker_base[:3, :3]
        if self.map is not None and "volume" in self.map.state:
            return self.map.outside(p_base)
        vol = self.model.info.get("volume")
        if vol and "lo" in vol and "hi" in vol:
            return np.any((p_base < np.asarray(vol["lo"])) | (p_base > np.asarray(vol["hi"])), axis=1)
        return np.zeros(len(p_tracker), bool)


@dataclass
class CompensationResult:
    """Per target: joints to command and what the model predicts they leave. Errors in m / rad.

    q of a target whose first IK failed is NaN (status says why); otherwise the best joints found.
    history: (iterations + 1, N) error measure at each iteration, NaN once a target stopped.
    """

    q: np.ndarray
    error_m: np.ndarray  # predicted remaining position error
    rotation_error_rad: np.ndarray  # predicted remaining orientation error
    cost_m: np.ndarray  # the error measure the loop minimised (position, or mm-equivalent pose error)
    iterations: np.ndarray  # pseudo-target updates made
    status: np.ndarray  # see STATUSES
    generator: np.ndarray  # generator that produced the joints (differs per target in an ensemble)
    initial_error_m: np.ndarray  # position error of the plain IK of the target (iteration 0)
    initial_rotation_error_rad: np.ndarray
    outside_volume: np.ndarray  # bool: the target lies outside the calibrated volume
    history: np.ndarray
    full_pose: bool
    branch_jump: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # paths only

    @property
    def ok(self) -> np.ndarray:
        return self.status == STATUS_OK

    def summary(self) -> dict:
        ok = np.isfinite(self.error_m)
        return {
            "targets": len(self.q),
            "ok": int(self.ok.sum()),
            "statuses": {str(s): int(np.sum(self.status == s)) for s in np.unique(self.status)},
            "mean_error_mm_before": float(np.mean(self.initial_error_m[ok]) * 1e3) if ok.any() else np.nan,
            "mean_error_mm": float(np.mean(self.error_m[ok]) * 1e3) if ok.any() else np.nan,
            "max_error_mm": float(np.max(self.error_m[ok]) * 1e3) if ok.any() else np.nan,
            "mean_rotation_deg": float(np.rad2deg(np.mean(self.rotation_error_rad[ok])))
            if ok.any()
            else np.nan,
            "outside_volume": int(self.outside_volume.sum()),
        }


def pose_cost(
    T_reached: np.ndarray, T_target: np.ndarray, full_pose: bool, length_scale_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cost, position error, rotation error): cost = position error (rotation NaN: points leave it
    free), or in full-pose mode the mm-equivalent sqrt(dp^2 + (length_scale * angle)^2)."""
    if not full_pose:
        dp = np.linalg.norm(T_reached[:, :3, 3] - T_target[:, :3, 3], axis=1)
        return dp, dp, np.full_like(dp, np.nan)
    dp, dr = pose_errors(T_reached, T_target)
    return np.hypot(dp, length_scale_m * dr), dp, dr


# A temperature this far beyond the training data's range is extrapolation of the model's thermal terms.
TEMPERATURE_MARGIN_K = 0.5


def outside_fitted_temperatures(model: CalibratedModel, temperature_c: np.ndarray) -> str | None:
    """Why temperatures lie outside the range the model's temperature-driven effects were fitted on (the
    run record diagnose / calibrate keep), or None: inside, no such effect, or no record (older models)."""
    if not any(temperature_driven(e) for e in model.effects):
        return None
    fitted = model.info.get("run", {}).get("inputs", {}).get("training", {}).get("temperature_c_range")
    at = np.asarray(temperature_c, float)
    at = at[np.isfinite(at)]
    if not fitted or not len(at):
        return None
    lo, hi = fitted
    outside = (at < lo - TEMPERATURE_MARGIN_K) | (at > hi + TEMPERATURE_MARGIN_K)
    if not outside.any():
        return None
    return (
        f"{int(outside.sum())} of {len(at)} targets at {at[outside].min():.1f}..{at[outside].max():.1f} degC lie "
        f"outside the {lo:.1f}..{hi:.1f} degC the model's thermal effect was fitted on: it extrapolates there"
    )


@dataclass(frozen=True)
class CompensationOptions:
    """How `compensate` runs its loop: the pseudo-target generator, when to stop, which model the IK solves.

    `generator`: one of `hil.compensation.target_update.GENERATORS` (default "yin" for poses) or "ensemble"
    (all of them, best joints per target; `generators` picks the ensemble's subset). Stops per target below
    `threshold_m` of the error measure (position, or the mm-equivalent pose error with `length_scale_m` per
    radian), after `max_iter` updates, or after `patience` updates without improvement. `ik_model`:
    "kinematic" (the calibrated geometry) or "nominal": the model the pseudo targets are solved with.
    `use_map`: the model's residual map joins its prediction. `ik_solver` replaces hil's IK (closed-form
    seed, Newton, `solve_ik` fallback) after the seed: f(targets, q_seed) -> (q, ok) with targets the
    flange poses T_base_flange (k, 4, 4), or tool points (k, 3) in the base frame for point targets.
    """

    generator: str | None = None
    generators: Sequence[str] | None = None
    threshold_m: float = 1e-5
    max_iter: int = 10
    patience: int = 2
    length_scale_m: float = 0.1
    ik_model: str = "kinematic"
    use_map: bool = True
    ik_solver: IKSolver | None = None


@dataclass(frozen=True)
class TargetConditions:
    """What the model's effects read besides the joints: the SMR nest the targets are for (default the
    model's lowest) and, per target (N,), the time t_s, the temperature and the approach signs (N, n)."""

    smr: int | None = None
    t_s: np.ndarray | None = None
    temperature_c: np.ndarray | None = None
    approach: np.ndarray | None = None
    payload_kg: np.ndarray | None = None  # (N,) the payload at the tool, which the gravity yield carries


def compensate(
    model: CalibratedModel,
    targets: np.ndarray,
    options: CompensationOptions = CompensationOptions(),
    q_seed: np.ndarray | None = None,
    q_near: np.ndarray | None = None,
    conditions: TargetConditions = TargetConditions(),
) -> CompensationResult:
    """Joints that make the model put the SMR on the targets (tracker frame, m): points (N, 3) or poses.

    Full-pose targets are T_tracker_tool (N, 4, 4): SMR centre and flange orientation, updated by the
    generator of `options`. Point targets (N, 3) leave the orientation free: the pseudo target is a point
    (P_p <- P_p + P_d - P_a, the part all generators share). The first IK starts from `q_seed` (per
    target) if given, else from the closed-form solution on the branch of `q_near` (default
    `hil.geometry.ik.default_home`), for points in that posture's tool orientation. The model predicts
    the pose under `conditions`.
    """
    threshold_m, length_scale_m = options.threshold_m, options.length_scale_m
    if options.max_iter < 0 or options.patience < 1 or threshold_m <= 0 or length_scale_m <= 0:
        raise ValueError("max_iter must be >= 0, patience >= 1, threshold_m and length_scale_m > 0")
    full_pose, T_d_in = _check_targets(targets)
    gen = options.generator or ("yin" if full_pose else "fixed")
    names = ensemble_names(options.generators) if gen == ENSEMBLE else [check_generator(gen)]
    if not full_pose:  # the generators differ only in the orientation, which points leave free
        names = [POINT_GENERATOR]
    c = conditions
    predictor = PosePredictor(model, c.smr, c.t_s, c.temperature_c, c.approach, options.use_map, c.payload_kg)
    N = len(T_d_in)
    if q_seed is not None:
        q_seed = np.asarray(q_seed, float)
        n = model.kinematic.n_joints
        if q_seed.shape not in ((n,), (N, n)) or not np.all(np.isfinite(q_seed)):
            raise ValueError(f"q_seed must be finite ({N}, {n}) or ({n},) joints, got {q_seed.shape}")
    outside = predictor.outside_volume(T_d_in[:, :3, 3] if full_pose else T_d_in)
    if outside.any():
        warnings.warn(
            f"{int(outside.sum())} target(s) lie outside the calibrated volume: the model extrapolates there",
            stacklevel=2,
        )
    tol_m = IK_TOL_FRACTION * threshold_m
    blocks: list[tuple[np.ndarray, CompensationResult]] = []
    # Every block's loops (one per generator), kept until the end: their pending rows are searched at once.
    loops: list[tuple[np.ndarray, list[_Loop]]] = []
    n_blocks = -(-N // BLOCK_TARGETS)
    for rows in np.array_split(np.arange(N), n_blocks):
        sl = slice(int(rows[0]), int(rows[-1]) + 1)
        ctx = _Setup(
            model,
            predictor.rows(sl),
            options.ik_model,
            full_pose,
            T_d_in[sl],
            q_seed if q_seed is None or q_seed.ndim == 1 else q_seed[sl],
            q_near,
            options.ik_solver,
            tol_m,
            tol_m / length_scale_m,
        )
        block_loops = [
            _Loop(ctx, name, threshold_m, options.max_iter, options.patience, length_scale_m)
            for name in names
        ]
        if not block_loops:
            raise ValueError("no pseudo-target generator to run")
        for loop in block_loops:
            loop.run(np.flatnonzero(loop.ok0))
        loops.append((rows, block_loops))
    _rescue([loop for _, block_loops in loops for loop in block_loops])
    for rows, block_loops in loops:
        results = [loop.result() for loop in block_loops]
        best = results[0]
        for res in results[1:]:
            best = _pick_better(best, res)
        blocks.append((rows, best))
    best = blocks[0][1] if len(blocks) == 1 else merge_results(blocks, N)
    best.outside_volume = outside
    return best


def ensemble_names(generators: Sequence[str] | None = None) -> list[str]:
    """The ensemble's generators: all of them, or the subset given (each checked, at least one)."""
    names = list(GENERATORS) if generators is None else [check_generator(g) for g in generators]
    if not names:
        raise ValueError(f"the ensemble needs at least one generator of {', '.join(GENERATORS)}")
    return names


def compensate_path(
    model: CalibratedModel,
    targets: np.ndarray,
    q_start: np.ndarray | None = None,
    jump_rad: float = 0.2,
    options: CompensationOptions = CompensationOptions(),
    conditions: TargetConditions = TargetConditions(),
) -> CompensationResult:
    """`compensate` for an ordered path of targets, with continuity.

    Each target's seed is the closed-form branch nearest the seed of its neighbour before it (the first
    one nearest `q_start`, default `default_home`), so the path stays on one branch where it can;
    `branch_jump` flags targets whose joints leave the previous target's branch or move a joint by more
    than `jump_rad`. Needs a UR-shaped model for the branch bookkeeping.
    """
    full_pose, T_d_in = _check_targets(targets)
    kin = model.kinematic if options.ik_model == "kinematic" else model.nominal
    if not is_ur_like(kin):
        raise ValueError(f"compensate_path needs a UR-shaped arm, {kin.name} is not")
    q0 = default_home(kin) if q_start is None else np.asarray(q_start, float)
    frames = PseudoTargetIK(model, options.ik_model, conditions.smr)
    if full_pose:
        T_d = T_d_in
    else:  # points: the start posture's orientation, only to pick the branches
        T_d = np.repeat(frames.from_flange(forward_kinematics(kin, q0[None])), len(T_d_in), axis=0)
        T_d[:, :3, 3] = T_d_in
    seeds = branches_along_path(kin, frames.to_flange(T_d), q0)
    res = compensate(model, targets, options, q_seed=seeds, q_near=q0, conditions=conditions)
    q = res.q
    good = np.all(np.isfinite(q), axis=1)
    jump = np.zeros(len(q), bool)
    if good.sum() > 1:
        idx = np.flatnonzero(good)
        branch = ur_branch_index(kin, q[idx])
        step = np.abs(np.diff(q[idx], axis=0)).max(axis=1)
        jump[idx[1:]] = (branch[1:] != branch[:-1]) | (step > jump_rad)
    res.branch_jump = jump
    return res


# --------------------------------------------------------------------------------------------------


def _check_targets(targets: np.ndarray) -> tuple[bool, np.ndarray]:
    t = np.asarray(targets, dtype=float)
    if t.ndim == 1:
        t = t[None]
    if not np.all(np.isfinite(t)):
        raise ValueError("targets contain NaN or inf")
    if t.ndim == 2 and t.shape[1] == 3:
        return False, t
    if t.ndim == 3 and t.shape[1:] == (4, 4):
        R = t[:, :3, :3]
        # Orthonormal columns, right-handed: z . (x cross y) = det R > 0.
        handed = np.einsum("ni,ni->n", np.cross(R[:, :, 0], R[:, :, 1]), R[:, :, 2])
        if np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(initial=0) > 1e-6 or np.any(handed < 0):
            raise ValueError("target poses must have proper rotation matrices")
        return True, t
    raise ValueError(f"targets must be points (N, 3) or poses (N, 4, 4) in metres, got shape {t.shape}")


class PseudoTargetIK:
    """The IK side of the loop: joints for pseudo targets (tracker frame), seeded with the previous joints.

    Pose targets: the IK solves flange poses. Point targets: the orientation is free, the IK solves the
    tool point with minimum-norm steps from the previous joints (the orientation drifts only as needed).
    The measured loop uses it with `hil.compensation.target_update.update_pseudo_target` on measured poses:
    T_p = update_pseudo_target(gen, T_d, T_measured, T_p); q, reason = ik.solve(T_p, q).
    """

    def __init__(
        self,
        model: CalibratedModel,
        ik_model: str = "kinematic",
        smr: int | None = None,
        full_pose: bool = True,
        ik_solver: IKSolver | None = None,
        tol_m: float = 1e-8,
        tol_rad: float = 1e-7,
    ) -> None:
        if ik_model not in ("kinematic", "nominal"):
            raise ValueError(f"ik_model must be 'kinematic' or 'nominal', got {ik_model!r}")
        sid = sorted(model.tools)[0] if smr is None else int(smr)
        if sid not in model.tools:
            raise ValueError(f"the model has tool points for SMR nests {sorted(model.tools)}, not {sid}")
        self.ik_solver = ik_solver
        self.tol_m, self.tol_rad = tol_m, tol_rad
        self.full_pose = full_pose
        self.kin: KinematicModel = model.kinematic if ik_model == "kinematic" else model.nominal
        self.T_tb = np.asarray(model.T_tracker_base, float)
        self.T_bt = invert(self.T_tb)
        self.tool = np.asarray(model.tools[sid], float)
        self.T_ft = np.eye(4)
        self.T_ft[:3, 3] = self.tool
        self.T_tf = invert(self.T_ft)

    def to_flange(self, T_tracker_tool: np.ndarray) -> np.ndarray:
        return self.T_bt @ T_tracker_tool @ self.T_tf

    def from_flange(self, T_base_flange: np.ndarray) -> np.ndarray:
        return self.T_tb @ T_base_flange @ self.T_ft

    def solve(
        self, T_pseudo: np.ndarray, q_prev: np.ndarray, project: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """IK of pseudo targets T_tracker_tool (N, 4, 4) seeded with q_prev (N, n): Newton, then `solve_ik`
        on what Newton left (or `ik_solver`). `project`: rotation blocks are not rotations ("add").
        Returns (q, reason (N,) str: 'ok', hil.geometry.ik's failure reason, or no_ik_solution)."""
        q, reason, _ = self._solve(T_pseudo, q_prev, project)
        return q, reason

    def _solve(
        self,
        T_pseudo: np.ndarray,
        q_prev: np.ndarray,
        project: bool = False,
        start: tuple[np.ndarray, np.ndarray] | None = None,
        T_flange: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """`solve`, warm-started with the flange pose and Jacobian at q_prev when given (hil's Newton
        only); also returns them at the answer (None with an `ik_solver`) for the next call.
        `T_flange`: the full-pose targets already as flange poses (`to_flange`). What Newton leaves is
        searched with `FIRST_FALLBACK` (a target's first IK: the seed, the closed-form branches, random
        joints); the loop's updates search theirs later, all at once (`_Loop`, `_rescue`)."""
        target = self._ik_target(T_pseudo, project, T_flange)
        q, ok, state = self._newton(target, q_prev, start)
        reason = np.where(ok, REASON_OK, STATUS_NO_IK).astype(STATUS_DTYPE)
        bad = np.flatnonzero(~ok)
        if bad.size and self.ik_solver is None:
            q[bad], reason[bad], rescued, got = self._fallback(target[bad], q_prev[bad], FIRST_FALLBACK)
            if state is not None and got is not None:  # the state at the joints solve_ik found
                state[0][bad[rescued]], state[1][bad[rescued]] = got
        return q, reason, state

    def _ik_target(self, T_pseudo: np.ndarray, project: bool, T_flange: np.ndarray | None) -> np.ndarray:
        """What the IK solves for pseudo targets T_tracker_tool: flange poses T_base_flange (full poses;
        `T_flange` when the caller has them already), or tool points in the base frame."""
        if T_flange is not None:
            return T_flange
        if self.full_pose:
            return self.to_flange(ik_pose(T_pseudo) if project else T_pseudo)
        return T_pseudo[:, :3, 3] @ self.T_bt[:3, :3].T + self.T_bt[:3, 3]

    def _newton(
        self, target: np.ndarray, q_prev: np.ndarray, start: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """Newton from q_prev (or `ik_solver`): (joints, converged (N,), flange poses and Jacobians at
        them, None with an `ik_solver`)."""
        if self.ik_solver is not None:
            q, ok = self.ik_solver(target, q_prev)
            return np.array(q, float), np.asarray(ok, bool), None
        res = newton_ik(
            self.kin,
            target,
            q_prev,
            "pose" if self.full_pose else "position",
            None if self.full_pose else self.tool,
            NewtonOptions(
                max_steps=NEWTON_STEPS, tol_position=self.tol_m, tol_rotation=self.tol_rad, validate=False
            ),
            start=start,
        )
        return res.q, res.converged, (res.pose, res.jacobian)

    def _fallback(
        self, target: np.ndarray, q_seed: np.ndarray, options: IKOptions
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """`solve_ik` on targets Newton left, seeded with q_seed: (joints, reason, rescued (k,) bool, the
        flange poses and Jacobians at the rescued rows' joints or None)."""
        kw = {"mode": "pose"} if self.full_pose else {"mode": "position", "p_flange_tool": self.tool}
        slow = solve_ik(self.kin, target, q_seed=q_seed, q_near=q_seed[0], options=options, **kw)
        reason = np.where(slow.reason == REASON_MAX_ITER, STATUS_NO_IK, slow.reason).astype(STATUS_DTYPE)
        rescued = slow.reason == REASON_OK
        got = None
        if rescued.any():
            got = pose_and_jacobian(self.kin, slow.q[rescued], None if self.full_pose else self.tool)
        return slow.q, reason, rescued, got


class _Setup(PseudoTargetIK):
    """What every generator's run shares: the IK, the predictor, the targets as poses and the first joints."""

    def __init__(
        self, model, predictor, ik_model, full_pose, targets, q_seed, q_near, ik_solver, tol_m, tol_rad
    ):
        super().__init__(model, ik_model, predictor.smr, full_pose, ik_solver, tol_m, tol_rad)
        self.predictor = predictor
        n = self.kin.n_joints
        N = len(targets)
        q_ref = default_home(self.kin) if q_near is None else np.asarray(q_near, float)
        if q_ref.shape != (n,) or not np.all(np.isfinite(q_ref)):
            raise ValueError(f"q_near must be finite ({n},) joints, got {q_ref.shape}")
        if q_seed is not None:
            q_seed = np.asarray(q_seed, float)
            if q_seed.shape not in ((n,), (N, n)) or not np.all(np.isfinite(q_seed)):
                raise ValueError(f"q_seed must be finite ({N}, {n}) or ({n},) joints, got {q_seed.shape}")
            q_seed = np.array(np.broadcast_to(q_seed, (N, n)))
        if full_pose:
            self.T_d = np.array(targets)
        else:  # orientation of the reference posture: only used to pick the closed-form seed
            ref = q_seed if q_seed is not None else np.broadcast_to(q_ref, (N, n))
            self.T_d = self.from_flange(forward_kinematics(self.kin, ref))
            self.T_d[:, :3, 3] = targets
        # state0: flange poses and Jacobians at q0 (hil's Newton), the warm start of the first update.
        self.state0: tuple[np.ndarray, np.ndarray] | None = None
        self.q0, self.reason0 = self._first_ik(q_seed, q_ref)

    def _first_ik(self, q_seed, q_ref) -> tuple[np.ndarray, np.ndarray]:
        T_f = self.to_flange(self.T_d)
        if q_seed is not None:
            q, reason, self.state0 = self._solve(self.T_d, q_seed)
        elif is_ur_like(self.kin):
            seed, reachable = same_branch_seed(self.kin, T_f, q_ref, validate=False)  # checked targets
            q, reason, self.state0 = self._solve(self.T_d, seed, T_flange=T_f if self.full_pose else None)
            if self.full_pose:
                reason = np.where(~reachable & (reason != REASON_OK), REASON_UNREACHABLE, reason)
        else:
            kw = {"mode": "pose"} if self.full_pose else {"mode": "position", "p_flange_tool": self.tool}
            target = T_f if self.full_pose else T_f[:, :3, :3] @ self.tool + T_f[:, :3, 3]
            res = solve_ik(self.kin, target, q_near=q_ref, **kw)
            q, reason = res.q, np.where(res.reason == REASON_MAX_ITER, STATUS_NO_IK, res.reason)
        q = np.array(q, dtype=float)
        q[reason != REASON_OK] = np.nan
        return q, np.asarray(reason).astype(str)


@dataclass
class _Pending:
    """Rows of one `_Loop` whose update Newton left unsolved, waiting for `_rescue`: their rows in the
    block, the iteration they stopped in, their IK targets and the joints of the previous iteration."""

    rows: np.ndarray
    k: np.ndarray
    target: np.ndarray
    q_prev: np.ndarray


class _Loop:
    """The pseudo-target loop of one generator over one block's targets, inactive targets dropping out.

    Resumable: a row whose update Newton leaves unsolved stops in `pending` with its IK target and the
    previous joints instead of going to `solve_ik` at once, so that `_rescue` searches the rows of every
    block and generator in one `UPDATE_FALLBACK` call: its cost is its ~50 LM iterations of Python,
    whatever the number of rows (on the benchmark's large-compliance arm, 19 hopeless rows of 10 000 took
    one call per iteration of each block, 10 calls, a third of the time). A row it rescues resumes from
    the iteration after the one it stopped in (`resume`); one it cannot keeps its best joints so far.
    """

    def __init__(
        self, s: _Setup, generator: str, threshold: float, max_iter: int, patience: int, length_scale: float
    ) -> None:
        N = len(s.T_d)
        self.s, self.generator, self.threshold = s, generator, threshold
        self.max_iter, self.patience, self.length_scale = max_iter, patience, length_scale
        self.ok0 = s.reason0 == REASON_OK
        self.q = s.q0.copy()
        self.T_p = s.T_d.copy()
        self.status = np.array(s.reason0, dtype=STATUS_DTYPE)
        self.q_best = np.full_like(self.q, np.nan)
        self.cost_best = np.full(N, np.inf)
        self.pos_best, self.rot_best = np.full(N, np.nan), np.full(N, np.nan)
        self.pos0, self.rot0 = np.full(N, np.nan), np.full(N, np.nan)
        self.since_best = np.zeros(N, int)
        self.iters = np.zeros(N, int)
        self.history = np.full((max_iter + 1, N), np.nan)
        self.state = s.state0  # never modified in place: the ensemble's generators all start from it
        self.pending: list[_Pending] = []

    def run(self, active: np.ndarray, k0: int = 0) -> None:
        """Iterations k0.. of the rows `active` (sorted block rows), each at joints `self.q` scored in
        iteration k0 (0: the first IK's joints)."""
        s, N = self.s, len(self.q)
        q, status, cost_best, since_best = self.q, self.status, self.cost_best, self.since_best
        for k in range(k0, self.max_iter + 1):
            if active.size == 0:
                break
            # While every row is active (active is sorted), index with a slice: views, not gathered copies.
            sel = slice(None) if active.size == N else active
            T_a = s.predictor(q[sel], active)
            cost, dp, dr = pose_cost(T_a, s.T_d[sel], s.full_pose, self.length_scale)
            self.history[k, sel] = cost
            if k == 0:
                self.pos0[sel], self.rot0[sel] = dp, dr
            better = cost < cost_best[sel]
            b = active[better]
            self.q_best[b], cost_best[b] = q[b], cost[better]
            self.pos_best[b], self.rot_best[b] = dp[better], dr[better]
            since_best[sel] = np.where(better, 0, since_best[sel] + 1)
            done = cost_best[sel] < self.threshold
            status[active[done]] = STATUS_OK
            stalled = ~done & (since_best[sel] >= self.patience)
            status[active[stalled]] = STATUS_STALLED
            if k == self.max_iter:
                status[active[~done & ~stalled]] = STATUS_MAX_ITER
                break
            keep = ~done & ~stalled
            if not keep.all():
                active, T_a = active[keep], T_a[keep]
            if active.size:
                active = self._update(active, T_a, k)

    def _update(self, active: np.ndarray, T_a: np.ndarray, k: int) -> np.ndarray:
        """Iteration k's pseudo-target update and IK for the rows `active` (T_a: their predicted poses);
        returns the rows that go on (those whose IK failed leave: finally, or pending a rescue)."""
        s, N, q, state = self.s, len(self.q), self.q, self.state
        sel = slice(None) if active.size == N else active
        if s.full_pose:
            self.T_p[sel] = update_pseudo_target(self.generator, s.T_d[sel], T_a, self.T_p[sel])
        else:
            self.T_p[sel, :3, 3] = update_pseudo_position(
                s.T_d[sel, :3, 3], T_a[:, :3, 3], self.T_p[sel, :3, 3]
            )
        start = state if state is None or active.size == N else (state[0][active], state[1][active])
        target = s._ik_target(self.T_p[sel], self.generator == "add", None)
        q_new, ok, got = s._newton(target, q[sel], start)
        if state is not None and got is not None:
            if active.size == N:
                self.state = got
            else:
                self.state = (state[0].copy(), state[1].copy())
                self.state[0][active], self.state[1][active] = got
        self.iters[sel] += 1
        failed = ~ok
        if failed.any():
            if s.ik_solver is None:  # hil's Newton: solve_ik searches from the previous joints later
                self.pending.append(
                    _Pending(active[failed], np.full(failed.sum(), k), target[failed], q[active[failed]])
                )
            else:  # the plugged-in IK's answer is final
                self.status[active[failed]] = STATUS_NO_IK  # best joints so far stay
        q[sel] = q_new
        return active[ok] if failed.any() else active

    def take_pending(self) -> _Pending | None:
        """The rows waiting for a rescue (None: none), handed over once."""
        if not self.pending:
            return None
        p = self.pending
        self.pending = []
        return _Pending(*(np.concatenate([getattr(x, f.name) for x in p]) for f in fields(_Pending)))

    def resume(
        self, p: _Pending, q: np.ndarray, reason: np.ndarray, got: tuple[np.ndarray, np.ndarray] | None
    ) -> None:
        """`_rescue`'s answer for the rows `take_pending` handed over: the rescued ones (reason ok) go on from
        the iteration after the one they stopped in, the others keep their best joints and the reason."""
        rescued = reason == REASON_OK
        self.status[p.rows[~rescued]] = reason[~rescued]
        if not rescued.any():
            return
        rows, ks = p.rows[rescued], p.k[rescued]
        self.q[rows] = q[rescued]
        if self.state is not None and got is not None:  # the state at the joints solve_ik found
            self.state = (self.state[0].copy(), self.state[1].copy())
            self.state[0][rows], self.state[1][rows] = got
        for k in np.unique(ks):
            self.run(np.sort(rows[ks == k]), int(k) + 1)

    def result(self) -> CompensationResult:
        N, ok0, threshold = len(self.q), self.ok0, self.threshold
        status, cost_best = self.status, self.cost_best
        status[(status != STATUS_OK) & ok0 & (cost_best < threshold)] = STATUS_OK
        return CompensationResult(
            q=self.q_best,
            error_m=self.pos_best,
            rotation_error_rad=self.rot_best,
            cost_m=np.where(np.isfinite(cost_best), cost_best, np.nan),
            iterations=self.iters,
            status=status,
            generator=np.full(N, self.generator),
            initial_error_m=self.pos0,
            initial_rotation_error_rad=self.rot0,
            outside_volume=np.zeros(N, bool),
            history=self.history,
            full_pose=self.s.full_pose,
        )


def _rescue(loops: list[_Loop]) -> None:
    """One `solve_ik` (`UPDATE_FALLBACK`: LM from the previous joints) for the pending rows of every loop,
    each loop then resuming its rescued rows; again while resumed rows leave new ones."""
    while True:
        taken = [(loop, p) for loop in loops if (p := loop.take_pending()) is not None]
        if not taken:
            return
        sizes = np.cumsum([0] + [len(p.rows) for _, p in taken])
        target = np.concatenate([p.target for _, p in taken])
        q_prev = np.concatenate([p.q_prev for _, p in taken])
        q, reason, rescued, got = taken[0][0].s._fallback(target, q_prev, UPDATE_FALLBACK)
        at = np.cumsum(rescued) - 1  # row of `got` for each rescued row
        for (loop, p), a, b in zip(taken, sizes[:-1], sizes[1:], strict=True):
            r = rescued[a:b]
            mine = None if got is None or not r.any() else (got[0][at[a:b][r]], got[1][at[a:b][r]])
            loop.resume(p, q[a:b], reason[a:b], mine)


def merge_results(parts: list[tuple[np.ndarray, CompensationResult]], n: int) -> CompensationResult:
    """One result for `n` targets from results of disjoint groups of them, each given with its target rows
    (blocks of consecutive targets, or the targets of one SMR nest): per-target arrays are scattered back
    into target order, histories NaN-padded to the deepest."""
    out: dict = {}
    for f in fields(CompensationResult):
        values = [getattr(r, f.name) for _, r in parts]
        if f.name == "history":
            merged = np.full((max(v.shape[0] for v in values), n), np.nan)
            for (rows, _), v in zip(parts, values, strict=True):
                merged[: v.shape[0], rows] = v
        elif isinstance(values[0], np.ndarray) and all(
            len(v) == len(rows) for (rows, _), v in zip(parts, values, strict=True)
        ):
            merged = np.empty((n, *values[0].shape[1:]), dtype=np.result_type(*values))
            for (rows, _), v in zip(parts, values, strict=True):
                merged[rows] = v
        else:  # the same for every part (full_pose), or not per target (branch_jump outside paths)
            merged = values[0]
        out[f.name] = merged
    return CompensationResult(**out)


def _pick_better(a: CompensationResult, b: CompensationResult) -> CompensationResult:
    """Per target, the result with the lower remaining error measure (ties and NaN keep `a`)."""
    take_b = np.nan_to_num(b.cost_m, nan=np.inf) < np.nan_to_num(a.cost_m, nan=np.inf)
    out = {}
    for name in a.__dataclass_fields__:
        va, vb = getattr(a, name), getattr(b, name)
        if name == "history":
            out[name] = np.where(take_b[None, :], vb, va)
        elif isinstance(va, np.ndarray) and va.shape[:1] == take_b.shape:
            mask = take_b.reshape(-1, *([1] * (va.ndim - 1)))
            out[name] = np.where(mask, vb, va)
        else:
            out[name] = va
    return CompensationResult(**out)
