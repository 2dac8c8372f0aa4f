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
(the table lists each measured axis against the nominal axis through the registration). The reference
pose is searched for (the one with the longest arcs) unless `q_ref` is given. The recorded sweeps export
as a dataset (`hil campaign export --procedure joint_axes`) that `hil axes` reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.analysis.joint_axes import MIN_ARC_RAD, AxesResult, identify_axes, robot_file_text
from hil.analysis.noise_floor import tracker_sigma_m
from hil.data.store import campaign_dataset
from hil.geometry.kinematics import forward_kinematics, link_frames
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


def arc_spans(config: CellConfig, q_ref: np.ndarray, span_rad: float, p_nest: np.ndarray) -> np.ndarray:
    """Per candidate reference pose (K, 6) and joint: the longest arc (rad, centred on the reference, at most
    `span_rad`) whose poses stay in the envelope and keep the SMR facing the tracker."""
    q_ref = np.atleast_2d(q_ref)
    half = np.arange(0.0, span_rad / 2 + 1e-9, SPAN_STEP_RAD / 2)
    offsets = np.concatenate([-half[::-1], half[1:]])  # symmetric, from -span/2 to +span/2
    K, n = q_ref.shape
    q = np.repeat(q_ref[:, None, None, :], n, axis=1).repeat(len(offsets), axis=2)  # (K, n, M, n)
    for j in range(n):
        q[:, j, :, j] += offsets
    flat = q.reshape(-1, n)
    ok = ~config.envelope.outside(config.nominal, flat, config.nests_flange_m)
    ok &= facing_angles(config, flat, p_nest) < FACING_LIMIT_RAD
    ok = ok.reshape(K, n, len(offsets))
    # symmetric reach: the largest k with every offset in -half[k]..half[k] usable
    mid = len(half) - 1
    good = np.logical_and(ok[..., mid:], ok[..., mid::-1])  # (K, n, len(half))
    reach = np.where(np.all(good, axis=-1), len(half) - 1, np.argmin(good, axis=-1) - 1)
    return 2 * half[np.clip(reach, 0, None)] * (reach >= 0)


def reference_pose(config: CellConfig, span_rad: float, p_nest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference pose with the longest arcs (the product of the arcs) among candidates: the home pose
    turned about joint 1 and at the wrist, and poses with the SMR facing the tracker straight at random points
    of the sampled volume; refused when no candidate lets every joint turn 30 deg."""
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
    score = np.where(
        np.all(spans >= MIN_ARC_RAD, axis=1), np.sum(np.log(np.maximum(spans, 1e-9)), axis=1), -np.inf
    )
    best = int(np.argmax(score))
    if not np.isfinite(score[best]):
        raise ValueError(
            "no reference pose found from which every joint turns 30 deg inside the envelope with the SMR "
            "facing the tracker; give one with --q-ref-deg or widen [envelope]"
        )
    return Q[best], spans[best]


def plan(
    config: CellConfig, *, span_rad: float, points: int, q_ref_rad: tuple[float, ...] | None, smrs: int | None
) -> Plan:
    """The sweeps: each joint alone, `points` poses over its arc, from the reference pose; every SMR read at
    every pose."""
    nests = smr_count(config, smrs)
    p_nest = config.nests_flange_m[:nests]
    if q_ref_rad is None:
        q_ref, spans = reference_pose(config, span_rad, p_nest)
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
    setup = tuple(
        OperatorStep(f"Put SMR {k} in tool nest {k}.", "place_smr", smr=k, location=f"nest{k}")
        for k in range(1, nests + 1)
    )
    poses = []
    for j, s in enumerate(spans):
        for k, offset in enumerate(np.linspace(-s / 2, s / 2, points)):
            q = q_ref.copy()
            q[j] += offset
            approach = None
            if k == 0:
                approach = q.copy()
                approach[j] -= APPROACH_RAD
            for nest in range(1, nests + 1):
                poses.append(PlannedPose(f"j{j + 1}/{k + 1:02d}/n{nest}", NAME, STEP, q, f"nest{nest}", smr=nest,
                                         approach_q_rad=approach if nest == 1 else None, setup=setup))  # fmt: skip
    return Plan(NAME, poses, config, operator_steps=nests)


def smr_count(config: CellConfig, smrs: int | None) -> int:
    """How many nests (1..k) hold an SMR: the given count, checked against the tool, else all of them."""
    available = len(config.nests_flange_m)
    if smrs is None:
        return available
    if not 1 <= smrs <= available:
        raise ValueError(f"--smrs {smrs}: the tool has {available} nest(s); give 1..{available}")
    return smrs


def identify(
    session: Session,
    *,
    span_rad: float,
    points: int,
    q_ref_rad: tuple[float, ...] | None,
    smrs: int | None,
    output: str | None,
    shots: int | None,
) -> AxesProcedureResult:
    """Measure the sweeps (resumable), fit the axes, write the robot file, compare with the nominal axes."""
    reg = session.require_registration()
    config = session.config
    the_plan = plan(config, span_rad=span_rad, points=points, q_ref_rad=q_ref_rad, smrs=smrs)
    session.visit(the_plan, shots=shots, pin=True)
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
        Parameter("points", "poses measured along each arc", 25, int, minimum=5, maximum=200),
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
)
