"""Joint-axis identification (circle point analysis): each joint turned alone, its SMR arc fitted, the axis
lines chained into a robot file (iso9283_and_axes.md; Mooring, Roth, Driels 1991).

Shop-floor instruction: the cell is registered (`hil run registration`); put SMRs 1..k in tool nests 1..k
(`smrs` = k, default every nest of the tool: each SMR draws its own arc about every axis, and more arcs fix
the axes better). From one reference pose the robot turns each joint in turn, alone, over as
large an arc as the joint limits, the envelope and the SMR's view of the tracker allow (at most `span`),
measuring `points` poses along it, always in the positive direction; then returns the joint to the
reference before the next. Each arc is fitted to a circle, each joint's axis to its arcs; the lines give a
standard DH model (Hayati's beta between parallel axes) written as a robot file (`output`) that
`hil calibrate --robot FILE` starts from: for an arm with no nominal model, or to check the nominal one
(the table lists each measured axis against the nominal axis through the registration).

Gravity sag: while a joint turns, the load on the other joints changes, they yield by changing amounts and
the arc is no circle; a radius change along it looks like a moved centre (0.1-0.2 mm on a UR10's shoulder,
where the elbow's load follows the shoulder's angle). So joint 2, whose axis no load moves (only the
vertical joint 1 stands before it), is swept from its own pose: joint 1 as at the reference, the others
where their yield moves the SMRs along the arc, not off it (on a UR the arm stretched along the upper arm).
The reference pose is searched for (unless `q_ref` is given): among the candidates with long arcs, the one
whose sweeps a generic sag model (1 kg at every link origin) distorts least. The fit itself stays pure
geometry: no mass or stiffness enters it. The recorded sweeps export
as a dataset (`hil campaign export --procedure joint_axes`) that `hil axes` reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.analysis.calibration.noise_floor import tracker_sigma_m
from hil.analysis.standards.joint_axes import (
    MIN_ARC_RAD,
    AxesResult,
    expected_line_sigmas,
    fit_circle,
    identify_axes,
    robot_file_text,
)
from hil.data.store import campaign_dataset
from hil.geometry.kinematics import KinematicModel, chain_axes, forward_kinematics, link_frames, tool_points
from hil.model.effects import GRAVITY_DIRECTION_BASE
from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import facing_poses, plan_joints, random_points, workspace_box
from hil.runner.procedure import SHOTS, Parameter, Procedure
from hil.runner.session import Session

NAME = "joint_axes"
STEP = "sweeps"
FACING_LIMIT_RAD = math.radians(28.0)  # the SMR's opening (30 deg) less a margin for the model's errors
APPROACH_RAD = math.radians(2.0)  # each sweep starts from below its first pose: one approach direction
SPAN_STEP_RAD = math.radians(4.0)  # resolution of the arc search
FACING_CANDIDATES = 120  # reference poses tried with the SMR facing the tracker, at random points
# Gravity sag while a joint turns: the load on the other joints changes, they yield by different amounts along
# the sweep and the SMR's arc is no circle; a first-harmonic radius change along the arc is indistinguishable
# from a shifted centre (0.1-0.2 mm on a UR10's shoulder). The fit stays pure geometry; the plan avoids it.
LONG_ARC_RAD = math.radians(60.0)  # arcs this long fix an axis far better than the tracker's noise needs
VERTICAL_RAD = math.radians(1.0)  # an axis within this of gravity carries no gravity torque
SAG_MASS_KG = 1.0  # planning's generic load: this mass at every link origin beyond a joint, and at the flange
SAG_STIFFNESS_NM_PER_RAD = 1.0e5  # planning's generic joint stiffness (a UR10-class arm, in its magnitude)
SAG_POINTS = 9  # poses per predicted arc (noise-free: a few fix the circle)
SAG_TIE_M = 5e-6  # predicted sag biases closer than this count as equal; the longer arcs then decide
SWEEP_GRID_DEG = (15.0, 15.0, 30.0)  # steps of the swept joint's centre, the next joint, the others
SWEEP_CANDIDATES = 1500  # the least sag-sensitive sweep poses whose arcs are searched
REFERENCE_TRIALS = 8  # reference poses (best first) tried for a free joint's sweep pose before settling
SENSITIVITY_GAIN = 0.5  # a free joint's sweep pose must halve the yield sensitivity of the reference
# Each axis to a 1-sigma (by default half of what a calibration start needs, 0.01 deg and 0.06 mm, so that
# two sigma stay within it): a short arc gets more points, at most this many times `points`. The position's
# goal follows the direction's at this ratio (0.03 mm for 0.005 deg).
AXIS_SIGMA_DEG = 0.005
POSITION_PER_DIRECTION_M_PER_RAD = 0.03e-3 / math.radians(AXIS_SIGMA_DEG)
MAX_POINTS_FACTOR = 4


@dataclass(frozen=True)
class AxesOptions:
    """The declared parameters, SI (None: absent, the procedure picks)."""

    span_rad: float
    points: int
    q_ref_rad: tuple[float, ...] | None
    smrs: int | None
    output: str | None
    shots: int | None
    axis_sigma_rad: float = 0.0


@dataclass
class AxesProcedureResult:
    """The identified axes, each against the nominal axis (angle deg, offset mm), and where the file went."""

    axes: AxesResult
    nominal_angle_deg: np.ndarray
    nominal_offset_mm: np.ndarray
    output: str | None

    def table(self) -> str:
        lines = [
            "joint axes (circle point analysis), tracker frame:",
            f"  {'joint':<6}{'swept':>7}{'resid':>9}{'radius':>9}{'vs nominal':>12}{'':>10}",
            f"  {'':<6}{'deg':>7}{'mm':>9}{'mm':>9}{'deg':>12}{'mm':>10}",
        ]
        for a, ang, off in zip(self.axes.axes, self.nominal_angle_deg, self.nominal_offset_mm, strict=True):
            radius = min(a.radii_m.values()) * 1e3
            lines.append(
                f"  {a.joint + 1:<6}{math.degrees(a.swept_rad):7.1f}{a.residual_rms_m * 1e3:9.4f}{radius:9.2f}"
                f"{ang:12.4f}{off:10.4f}"
            )
        if self.output:
            lines.append(
                f"robot file written to {self.output} (start calibration from it: hil calibrate --robot ...)"
            )
        return "\n".join(lines)


def facing_angles(config: CellConfig, q: np.ndarray, p_nests: np.ndarray) -> np.ndarray:
    """The largest angle (N,) between an SMR's opening (flange +z) and its line to the tracker, over the
    nests (K, 3), nominal model."""
    T = forward_kinematics(config.nominal, q)
    p = np.einsum("nij,kj->nki", T[:, :3, :3], np.atleast_2d(p_nests)) + T[:, None, :3, 3]
    to_tracker = config.p_base_tracker_m - p
    to_tracker /= np.linalg.norm(to_tracker, axis=2, keepdims=True)
    cos = np.einsum("ni,nki->nk", T[:, :3, 2], to_tracker)
    return np.arccos(np.clip(cos, -1.0, 1.0)).max(axis=1)


def arc_spans(
    config: CellConfig,
    q_ref: np.ndarray,
    span_rad: float,
    p_nest: np.ndarray,
    joints: list[int] | None = None,
) -> np.ndarray:
    """Per candidate reference pose (K, 6) and joint (every joint, or those in `joints`): the longest arc (rad,
    centred on the reference, at most `span_rad`) whose poses stay in the envelope and keep the SMR facing
    the tracker, its approach pose (APPROACH_RAD before the first) inside the envelope too."""
    q_ref = np.atleast_2d(q_ref)
    half = np.arange(0.0, span_rad / 2 + 1e-9, SPAN_STEP_RAD / 2)
    # symmetric, from -span/2 to +span/2, then the approach poses below each start
    offsets = np.concatenate([-half[::-1], half[1:], -half - APPROACH_RAD])
    K, n = q_ref.shape
    swept = list(range(n)) if joints is None else list(joints)
    q = np.repeat(q_ref[:, None, None, :], len(swept), axis=1).repeat(len(offsets), axis=2)  # (K, J, M, n)
    for i, j in enumerate(swept):
        q[:, i, :, j] += offsets
    flat = q.reshape(-1, n)
    mid, m = len(half) - 1, len(half)
    facing = (facing_angles(config, flat, p_nest) < FACING_LIMIT_RAD).reshape(K, len(swept), -1)
    # the envelope (with its collision checks, the costly part) only where it decides: the arc's poses that
    # face the tracker and every approach pose
    needed = facing.copy()
    needed[..., 2 * m - 1 :] = True
    inside = np.zeros(needed.shape, bool)
    inside[needed] = ~config.envelope.outside(config.nominal, flat[needed.ravel()], config.nests_flange_m)
    ok = inside & facing
    # symmetric reach: the largest k with every offset in -half[k]..half[k] usable and its approach inside
    good = np.logical_and(ok[..., mid : mid + m], ok[..., mid::-1])  # (K, J, len(half))
    usable = np.logical_and.accumulate(good, axis=-1) & inside[..., 2 * m - 1 :]
    reach = np.where(usable.any(axis=-1), m - 1 - np.argmax(usable[..., ::-1], axis=-1), -1)
    return 2 * half[np.clip(reach, 0, None)] * (reach >= 0)


def reference_pose(
    config: CellConfig, span_rad: float, p_nest: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference pose, the pose each joint's sweep stands at (n, n) and the arcs (n,). Candidates: the home
    pose turned about joint 1 and at the wrist, and poses with the SMR facing the tracker straight at random
    points of the sampled volume; refused when no candidate lets every joint turn 30 deg. Those whose arcs at
    the reference are not short (`LONG_ARC_RAD`, or nearly as long as any candidate allows) first, the least
    predicted sag bias of the joints swept there (`sag_bias`), ties to the longest arcs, whose free joints
    (`free_joints`) also find a sweep pose with a long arc and half the reference's yield sensitivity
    (`sweep_poses`); the first candidate when none of the best REFERENCE_TRIALS does."""
    home = np.asarray(config.q_home_rad, float)
    candidates = []
    for d1 in np.deg2rad(np.arange(-180.0, 180.0, 30.0)):
        for d4 in np.deg2rad([0.0, -45.0, 45.0]):
            for d5 in np.deg2rad([0.0, 45.0, -45.0, 90.0, -90.0]):
                q = home.copy()
                q[[0, 3, 4]] += (d1, d4, d5)
                candidates.append(q)
    rng = np.random.default_rng(0)
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    T = facing_poses(random_points(box, FACING_CANDIDATES, rng), config.p_base_tracker_m, rng, tilt_deg=0.0,
                     roll_deg=180.0)  # fmt: skip
    facing = plan_joints(config.nominal, T, p_nest[0], q_near=home)
    candidates += list(facing.q[facing.usable])
    Q = np.array(candidates)
    spans = arc_spans(config, Q, span_rad, p_nest)
    valid = np.all(spans >= MIN_ARC_RAD, axis=1)
    if not valid.any():
        raise ValueError(
            "no reference pose found from which every joint turns 30 deg inside the envelope with the SMR "
            "facing the tracker; give one with --q-ref-deg or widen [envelope]"
        )
    free = free_joints(config.nominal, home)
    at_ref = [j for j in range(len(home)) if j not in free]
    need = np.maximum(
        MIN_ARC_RAD, np.minimum(LONG_ARC_RAD, spans[valid][:, at_ref].max(axis=0)) - 2 * SPAN_STEP_RAD
    )
    long = np.all(spans[:, at_ref] >= need, axis=1)
    eligible = np.flatnonzero(valid)
    bias = np.max(
        [sag_bias(config.nominal, Q[eligible], j, spans[eligible, j], p_nest) for j in at_ref], axis=0
    )
    score = np.sum(np.log(np.maximum(spans[eligible][:, at_ref], 1e-9)), axis=1)
    # long arcs first, then the least bias (in steps of SAG_TIE_M), then the longest arcs
    order = np.lexsort((-score, np.round(bias / SAG_TIE_M), ~long[eligible]))
    fallback = None
    for k in eligible[order][:REFERENCE_TRIALS]:
        centres, arcs = sweep_poses(config, Q[k], spans[k], span_rad, p_nest)
        gain = [yield_sensitivity(config.nominal, np.array([centres[j], Q[k]]), p_nest, j) for j in free]
        if all(g[0] <= SENSITIVITY_GAIN * g[1] for g in gain) and np.all(arcs[free] >= LONG_ARC_RAD - 1e-9):
            return Q[k], centres, arcs
        fallback = fallback or (Q[k], centres, arcs)
    assert fallback is not None
    return fallback


def sweep_poses(
    config: CellConfig, q_ref: np.ndarray, spans: np.ndarray, span_rad: float, p_nest: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where each joint's sweep stands (n, n) and its arc (n,): at the reference, bar the free joints
    (`sweep_pose`)."""
    q_ref = np.asarray(q_ref, float)
    centres = np.repeat(q_ref[None], len(q_ref), axis=0)
    arcs = np.array(spans, float)
    for j in free_joints(config.nominal, q_ref):
        centres[j], arcs[j] = sweep_pose(config, q_ref, j, span_rad, p_nest, float(arcs[j]))
    return centres, arcs


def gravity_sag(nominal: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Planning's generic gravity yield of every joint (N, n), rad: SAG_MASS_KG at each link origin beyond the
    joint and at the flange, over SAG_STIFFNESS_NM_PER_RAD, the robot upright. Only its variation along a sweep
    matters, and only to rank poses: the real masses and stiffnesses never enter the fit."""
    T_flange, Z, O = chain_axes(nominal, q)  # Z (n, 3, N), O (n + 1, 3, N)
    n = nominal.n_joints
    weight = SAG_MASS_KG * 9.81 * GRAVITY_DIRECTION_BASE
    points = np.concatenate([O, T_flange[:, :3, 3].T[None]])  # (n + 2, 3, N)
    tau = np.empty((np.shape(q)[0], n))
    for k in range(n):
        lever = np.sum(points[k + 1 :] - O[k], axis=0)  # (3, N): the summed arms of the unit masses beyond
        tau[:, k] = np.einsum(
            "in,in->n", np.cross(weight[:, None], Z[k], axis=0), lever
        )  # z.(r x F) = (F x z).r
    return tau / SAG_STIFFNESS_NM_PER_RAD


def sag_bias(
    nominal: KinematicModel, q_centre: np.ndarray, joint: int, span_rad: np.ndarray, p_nest: np.ndarray
) -> np.ndarray:
    """Predicted position error (K,), m, of joint `joint`'s axis when swept over `span_rad` (K,) about each pose
    of `q_centre` (K, n), from the generic sag (`gravity_sag`): the arcs' circles against the sagged axis at
    the centre pose. For ranking poses only."""
    Q = np.atleast_2d(np.asarray(q_centre, float))
    K, n = Q.shape
    steps = np.linspace(-0.5, 0.5, SAG_POINTS)[None, :] * np.asarray(span_rad, float)[:, None]  # (K, M)
    sweep = np.repeat(Q[:, None, :], SAG_POINTS, axis=1)
    sweep[..., joint] += steps
    flat = sweep.reshape(-1, n)
    T = forward_kinematics(nominal, flat + gravity_sag(nominal, flat))
    p = np.einsum("nij,kj->nki", T[:, :3, :3], p_nest) + T[:, None, :3, 3]
    p = p.reshape(K, SAG_POINTS, len(p_nest), 3)
    F = link_frames(nominal, Q + gravity_sag(nominal, Q))[:, joint]
    z, o = F[:, :3, 2], F[:, :3, 3]
    bias = np.zeros(K)
    for k in np.flatnonzero(np.asarray(span_rad) >= MIN_ARC_RAD):
        d = np.mean([fit_circle(p[k, :, i])[0] for i in range(len(p_nest))], axis=0) - o[k]
        bias[k] = np.linalg.norm(d - (d @ z[k]) * z[k])
    return bias


def free_joints(nominal: KinematicModel, q: np.ndarray) -> list[int]:
    """Joints (0-based, not the first) whose every upstream axis stands along gravity: no joint before them
    carries a gravity torque, so their axis does not move with the pose of the joints beyond, and their sweep
    may stand elsewhere than the reference (on an upright arm: joint 2)."""
    _, Z, _ = chain_axes(nominal, np.atleast_2d(np.asarray(q, float)))
    vertical = np.abs(Z[:, :, 0] @ GRAVITY_DIRECTION_BASE) > math.cos(VERTICAL_RAD)
    out = []
    for j in range(1, nominal.n_joints):
        if not vertical[:j].all():
            break
        out.append(j)
    return out


def yield_sensitivity(nominal: KinematicModel, q: np.ndarray, p_nest: np.ndarray, joint: int) -> np.ndarray:
    """Per pose (N,), m/rad: the RMS, over the SMRs and the joints beyond `joint`, of how far an SMR leaves
    `joint`'s circle (radially or along the axis) when that joint yields. Zero when every yield moves the
    SMRs along the arc, which a circle fit ignores: no mass or stiffness needed."""
    T, Z, O = chain_axes(nominal, q)
    p = np.einsum("nij,kj->nki", T[:, :3, :3], p_nest) + T[:, None, :3, 3]  # (N, K, 3)
    z, o = Z[joint].T[:, None], O[joint].T[:, None]
    d = p - o
    tangent = np.cross(z, d)
    tangent /= np.linalg.norm(tangent, axis=2, keepdims=True)
    total = np.zeros(len(p))
    for k in range(joint + 1, nominal.n_joints):
        J = np.cross(Z[k].T[:, None], p - O[k].T[:, None])  # the SMRs' motion per rad of joint k
        total += np.sum((J - np.sum(J * tangent, axis=2, keepdims=True) * tangent) ** 2, axis=(1, 2))
    return np.sqrt(total / (len(p_nest) * max(nominal.n_joints - joint - 1, 1)))


def sweep_pose(
    config: CellConfig, q_ref: np.ndarray, joint: int, span_rad: float, p_nest: np.ndarray, span_at_ref: float
) -> tuple[np.ndarray, float]:
    """Where a free joint (see `free_joints`) is swept and over which arc: the joints before it as at the
    reference, those beyond (bar the last) on a grid, the pose whose SMRs the other joints' gravity yield
    moves least off the arc (`yield_sensitivity`), among those with an arc as long as the reference's or
    LONG_ARC_RAD; the reference itself when nothing beats it. On a UR: the arm stretched along the upper arm."""
    n = len(q_ref)
    lo, hi = config.nominal.joint_limits[:, 0], config.nominal.joint_limits[:, 1]
    axes = []
    for i, j in enumerate(range(joint, n - 1)):
        values = np.deg2rad(np.arange(-180.0, 180.0, SWEEP_GRID_DEG[min(i, 2)]))
        axes.append(values[(values >= lo[j]) & (values <= hi[j])])
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    Q = np.repeat(np.asarray(q_ref, float)[None], len(grid) + 1, axis=0)
    Q[1:, joint : n - 1] = grid  # row 0: the reference
    sensitivity = yield_sensitivity(config.nominal, Q, p_nest, joint)
    top = np.concatenate([[0], 1 + np.argsort(sensitivity[1:])[:SWEEP_CANDIDATES]])
    spans = arc_spans(config, Q[top], span_rad, p_nest, [joint])[:, 0]
    spans[0] = span_at_ref
    ok = spans >= max(MIN_ARC_RAD, min(LONG_ARC_RAD, span_at_ref))
    ok[0] = True
    least = sensitivity[top][ok].min()
    tied = np.flatnonzero(ok & (sensitivity[top] <= least * 1.05))
    best = int(tied[np.argmax(spans[tied])])
    return Q[top[best]], float(spans[best])


def plan(config: CellConfig, options: AxesOptions) -> Plan:
    """The sweeps: each joint alone, `points` poses over its arc, from the reference pose (a free joint, see
    `free_joints`, from the pose its gravity sag distorts least: `sweep_pose`); every SMR read at every pose."""
    span_rad, points, q_ref_rad, smrs = options.span_rad, options.points, options.q_ref_rad, options.smrs
    # refused before anything moves: a measured model is never lost
    if options.output and Path(options.output).exists():
        raise ValueError(
            f"--output: {options.output} exists; choose another file, or move that one away to write it again"
        )
    nests = smr_count(config, smrs)
    p_nest = config.nests_flange_m[:nests]
    if q_ref_rad is None:
        q_ref, centres, spans = reference_pose(config, span_rad, p_nest)
    else:
        q_ref = np.asarray(q_ref_rad, float)
        spans = arc_spans(config, q_ref, span_rad, p_nest)[0]
        short = np.flatnonzero(spans < MIN_ARC_RAD)
        if short.size:
            j = int(short[0])
            raise ValueError(
                f"from --q-ref-deg joint {j + 1} can turn only {math.degrees(spans[j]):.0f} deg inside the envelope "
                "with the SMR facing the tracker (30 needed); choose another reference pose or leave it out"
            )
        centres, spans = sweep_poses(config, q_ref, spans, span_rad, p_nest)
    setup = tuple(
        OperatorStep(f"Put SMR {k} in tool nest {k}.", "place_smr", smr=k, location=f"nest{k}")
        for k in range(1, nests + 1)
    )
    poses = []
    counts = points_per_arc(config, centres, spans, points, p_nest, options.shots, options.axis_sigma_rad)
    for j, s in enumerate(spans):
        for k, offset in enumerate(np.linspace(-s / 2, s / 2, counts[j])):
            q = centres[j].copy()
            q[j] += offset
            approach = None
            if k == 0:
                approach = q.copy()
                approach[j] -= APPROACH_RAD
            for nest in range(1, nests + 1):
                poses.append(PlannedPose(f"j{j + 1}/{k + 1:02d}/n{nest}", NAME, STEP, q, f"nest{nest}", smr=nest,
                                         approach_q_rad=approach if nest == 1 else None, setup=setup))  # fmt: skip
    return Plan(NAME, poses, config, operator_steps=nests)


def points_per_arc(
    config: CellConfig,
    centres: np.ndarray,
    spans: np.ndarray,
    points: int,
    p_nest: np.ndarray,
    shots: int | None,
    axis_sigma_rad: float = math.radians(AXIS_SIGMA_DEG),
) -> list[int]:
    """How many poses each joint's arc is measured at: `points`, more (up to MAX_POINTS_FACTOR times) where
    the arc, its SMRs and the tracker's noise would fix the axis to worse than `axis_sigma_rad` in direction
    or its POSITION_PER_DIRECTION_M_PER_RAD share in position (1 sigma, the nominal model's arcs; the fit's
    sigma falls as one over the root of the points); 0 keeps `points` on every arc. A short arc fixes its
    circle's centre poorly: on a UR10 joints 1 and 5 turn 40-48 deg."""
    if axis_sigma_rad <= 0:
        return [points] * len(spans)
    goal_m = axis_sigma_rad * POSITION_PER_DIRECTION_M_PER_RAD
    counts = []
    for j, s in enumerate(spans):
        q = np.repeat(centres[j][None], points, axis=0)
        q[:, j] += np.linspace(-s / 2, s / 2, points)
        arcs = [tool_points(config.nominal, q, nest) for nest in p_nest]
        distance = float(np.median(np.linalg.norm(np.concatenate(arcs) - config.p_base_tracker_m, axis=1)))
        sigma = float(tracker_sigma_m(distance)) / math.sqrt(shots or config.shots_per_point)
        direction, position = expected_line_sigmas(arcs, sigma)
        factor = max(1.0, (direction / axis_sigma_rad) ** 2, (position / goal_m) ** 2)
        counts.append(int(min(math.ceil(points * factor), MAX_POINTS_FACTOR * points)))
    return counts


def smr_count(config: CellConfig, smrs: int | None) -> int:
    """How many nests (1..k) hold an SMR: the given count, checked against the tool, else all of them."""
    available = len(config.nests_flange_m)
    if smrs is None:
        return available
    if not 1 <= smrs <= available:
        raise ValueError(f"--smrs {smrs}: the tool has {available} nest(s); give 1..{available}")
    return smrs


def identify(session: Session, options: AxesOptions, the_plan: Plan) -> AxesProcedureResult:
    """Measure the sweeps (resumable), fit the axes, write the robot file, compare with the nominal axes."""
    reg = session.require_registration()
    config = session.config
    shots, output = options.shots, options.output
    session.engine.visit(the_plan, shots=shots, pin=True)
    df = campaign_dataset(session.store, NAME, STEP)
    df["sweep"] = [p.split("/")[0] for p in df["point_id"]]
    distance = float(np.median(np.linalg.norm(df[["x_mm", "y_mm", "z_mm"]].to_numpy(float), axis=1))) / 1e3
    sigma = float(tracker_sigma_m(distance)) / math.sqrt(shots or config.shots_per_point)
    name = Path(output).stem if output else f"{config.nominal.name}-measured"
    result = identify_axes(df, config.nominal.n_joints, sigma_m=sigma, source=f"{NAME} sweeps", name=name)
    F = reg.T_tracker_base @ link_frames(config.nominal, result.q_ref_rad[None])[0]
    angles, offsets = [], []
    for a in result.axes:
        z, o = F[a.joint, :3, 2], F[a.joint, :3, 3]
        angles.append(math.degrees(math.acos(min(1.0, abs(float(a.direction @ z))))))
        d = a.point_m - o
        offsets.append(float(np.linalg.norm(d - (d @ z) * z)) * 1e3)
    if output:
        Path(output).write_text(
            robot_file_text(
                result.model, f"Measured by circle point analysis (hil run {NAME}) on {config.nominal.name}."
            )
        )
    session.finish_step(
        NAME, "axes", {**result.to_dict(), "nominal_angle_deg": angles, "nominal_offset_mm": offsets}
    )
    return AxesProcedureResult(result, np.array(angles), np.array(offsets), output)


def summary(result: AxesProcedureResult) -> str:
    return result.table()


PROCEDURE = Procedure(
    name=NAME,
    purpose="identify every joint's axis by turning it alone (circle point analysis) and write a robot file",
    instruction=__doc__ or "",
    parameters=(
        Parameter("span", "largest arc per joint", 120.0, float, unit="deg", minimum=30.0, maximum=340.0),
        Parameter("points", "poses measured along each arc (at least)", 25, int, minimum=5, maximum=200),
        Parameter(
            "axis_sigma",
            f"1-sigma each axis direction is planned to (its position to {POSITION_PER_DIRECTION_M_PER_RAD * 1e3 * math.pi / 180:g} "
            f"mm per deg): a short arc gets up to {MAX_POINTS_FACTOR}x the points; 0 keeps `points` on every arc",
            AXIS_SIGMA_DEG,
            float,
            unit="deg",
            minimum=0.0,
            maximum=1.0,
        ),
        Parameter("q_ref", "reference pose q1..q6 (default: searched)", None, float, unit="deg", count=6),
        Parameter(
            "smrs",
            "SMRs in tool nests 1..k, each read at every pose (default: every nest)",
            None,
            int,
            minimum=1,
        ),  # fmt: skip
        Parameter("output", "robot file (.toml) to write the measured model to", None, str),
        SHOTS,
    ),
    plan=plan,
    body=identify,
    steps=("sweeps", "axes"),
    summary=summary,
    options=AxesOptions,
)
