"""Tool fit: where are the SMR nests of the tool in the flange frame? (tool paper, methods.md section 1)

Shop-floor instruction: with the tool mounted, bring the flange to face the tracker. Seat the SMR in each
flange hole in turn (holes 1-6 on the circle, hole 7 off it on +x), then rest it on the flange face, then put
it in each tool nest; the tracker measures each. Repeat at two or more robot poses. From the hole balls the
flange frame follows (circle centre and normal, face height, +x from hole 7) in the tracker frame only, so the
robot's own error stays out of the result; each nest is then expressed in that frame. As a cross-check, the
robot moves the SMR in nest 1 through a few more poses and the distance-constraint method gives nest 1
again; it carries the robot's own error (about a millimetre), so it catches gross mistakes (a wrong nest
number, a wrong drawing), not tenths. The fit is refused, with the reason, when the hole balls do not lie on
a circle, the circle's radius is not the drawing's, the poses disagree, or the two methods disagree.

Hole layout (flange frame): holes 1-6 at angles (k - 3.5) * 60 deg on the hole circle, hole 7 on +x at its own
radius; a seated SMR's centre sits sqrt(R^2 - (d/2)^2) above the face.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.analysis.flange_geometry import fit_flange_frame, tool_point_by_distances, tool_point_in_flange
from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import Box, facing_poses, plan_joints, workspace_box
from hil.runner.procedure import Limit, Parameter, Procedure
from hil.runner.session import CampaignStopped, RecordedPoints, Session

NAME = "tool_fit"
HOLES = tuple(range(1, 8))


class ToolFitRejected(CampaignStopped):  # noqa: N818 - reads as what happened
    """The quality gate refused the fit; the message says which check failed."""


@dataclass(frozen=True)
class ToolFitResult:
    nests_flange_m: dict[int, np.ndarray]
    uncertainty_m: dict[int, float]  # 1-sigma of each nest's position (spread over poses / sqrt(poses))
    circle_residual_m: float  # worst pose
    circle_radius_m: float
    distance_check_m: float  # |nest 1 by holes - nest 1 by distances|
    result: dict
    limits: _Limits | None = None  # what the figures were judged against


def hole_points_flange(config: CellConfig) -> dict[str, np.ndarray]:
    """Nominal SMR centres (flange frame) for every location of the procedure: hole1..hole7 and face."""
    k = np.arange(1, 7)
    angles = np.deg2rad((k - 3.5) * 60.0)
    seat = np.sqrt(config.smr_radius_m**2 - (config.hole_diameter_m / 2) ** 2)
    points = {
        f"hole{i}": np.array(
            [config.hole_circle_radius_m * np.cos(a), config.hole_circle_radius_m * np.sin(a), seat]
        )
        for i, a in zip(k, angles, strict=True)
    }
    points["hole7"] = np.array([config.hole7_radius_m, 0.0, seat])
    points["face"] = np.array([*face_point(config), config.smr_radius_m])
    return points


def face_point(config: CellConfig) -> tuple[float, float]:
    """Where the SMR rests on the face: opposite hole 7, clear of the holes."""
    return (-config.hole7_radius_m, 0.0)


def plan(config: CellConfig, *, poses: int, check_poses: int, seed: int) -> Plan:
    """Flange poses facing the tracker (rolled differently), then distance-check poses with the SMR in nest 1."""
    rng = np.random.default_rng(seed)
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    inner = Box(box.centre_m, 0.3 * box.axes_m)
    points = inner.centre_m + rng.uniform(-1, 1, (4 * poses, 3)) @ inner.axes_m.T
    T = facing_poses(points, config.p_base_tracker_m, rng, tilt_deg=8.0, roll_deg=90.0)
    joints = plan_joints(config.nominal, T, np.zeros(3), q_near=config.q_home_rad)
    ok = joints.usable & ~config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)
    q_fit = joints.q[ok][:poses]
    check_box = Box(box.centre_m, 0.7 * box.axes_m)
    points = check_box.centre_m + rng.uniform(-1, 1, (4 * check_poses, 3)) @ check_box.axes_m.T
    T = facing_poses(points, config.p_base_tracker_m, rng, tilt_deg=25.0, roll_deg=180.0)
    joints = plan_joints(config.nominal, T, config.nests_flange_m[0], q_near=config.q_home_rad)
    ok = joints.usable & ~config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)
    q_check = joints.q[ok][:check_poses]
    if len(q_fit) < poses or len(q_check) < check_poses:
        raise ValueError("not enough reachable tool-fit poses inside the envelope; widen [envelope]")
    seat = _seating_steps(config)
    nominal = nominal_points(config)
    steps: list[PlannedPose] = []
    nests = [f"nest{j}" for j in range(1, len(config.nests_flange_m) + 1)]
    for k, q in enumerate(q_fit, start=1):
        for location in [*(f"hole{h}" for h in HOLES), "face", *nests]:
            steps.append(
                PlannedPose(
                    f"p{k}/{location}",
                    NAME,
                    f"pose{k}",
                    q,
                    location,
                    p_flange_m=nominal[location],
                    setup=seat[location],
                )
            )
    for k, q in enumerate(q_check, start=1):
        steps.append(
            PlannedPose(
                f"c{k:02d}",
                NAME,
                "distance_check",
                q,
                "nest1",
                p_flange_m=nominal["nest1"],
                setup=seat["nest1"],
            )
        )
    operator = poses * (len(HOLES) + 1 + len(nests)) + 1
    return Plan(NAME, steps, config, operator_steps=operator)


def nominal_points(config: CellConfig) -> dict[str, np.ndarray]:
    """Nominal SMR centres (flange frame) at every location: the holes and the face, and the nests (drawing)."""
    points = hole_points_flange(config)
    for j in range(1, len(config.nests_flange_m) + 1):
        points[f"nest{j}"] = np.asarray(config.nests_flange_m[j - 1], float)
    return points


def _seating_steps(config: CellConfig) -> dict[str, tuple[OperatorStep, ...]]:
    """The operator's instruction for each location: seat SMR 1 in a hole or a nest, or rest it on the face."""
    steps: dict[str, tuple[OperatorStep, ...]] = {}
    for location in nominal_points(config):
        where = location.replace("nest", "tool nest ").replace("hole", "flange hole ")
        text = (
            "Rest SMR 1 on the flange face, opposite hole 7."
            if location == "face"
            else f"Seat SMR 1 in {where}."
        )
        steps[location] = (
            OperatorStep(text, "place_smr", smr=1, location=location, face_point_m=face_point(config)),
        )
    return steps


def fit_tool(
    session: Session,
    *,
    poses: int,
    check_poses: int,
    shots: int,
    seed: int,
    max_circle_residual_m: float,
    max_radius_error_m: float,
    max_pose_spread_m: float,
    max_method_disagreement_m: float,
) -> ToolFitResult:
    """Measure the holes, the face and the nests at each pose on a registered cell, then fit and judge."""
    session.require_registration()
    the_plan = plan(session.config, poses=poses, check_poses=check_poses, seed=seed)
    session.visit(the_plan, shots=shots)
    limits = _Limits(max_circle_residual_m, max_radius_error_m, max_pose_spread_m, max_method_disagreement_m)
    return _fit(session, the_plan, limits)


@dataclass(frozen=True)
class _Limits:
    circle_residual_m: float
    radius_error_m: float
    pose_spread_m: float
    method_disagreement_m: float


@dataclass
class _PoseFit:
    """One flange pose's fit: its figures for the step result, its nests (flange frame) and what failed."""

    figures: dict
    nests_m: dict[int, np.ndarray]
    problems: list[str]


def _fit_pose(config: CellConfig, data: RecordedPoints, k: str, limits: _Limits) -> _PoseFit:
    """Fit the flange frame of pose k from its hole balls and face, express every nest in it, judge the circle."""
    by_id = {pid: i for i, pid in enumerate(data.point_id)}

    def point(location: str) -> np.ndarray:
        return data.p_tracker_m[by_id[f"p{k}/{location}"]]

    fit = fit_flange_frame(
        {h: point(f"hole{h}") for h in HOLES}, point("face"), smr_radius_m=config.smr_radius_m
    )
    nests = {
        j: tool_point_in_flange(fit.T_tracker_flange, point(f"nest{j}"))
        for j in range(1, len(config.nests_flange_m) + 1)
    }
    figures = {
        "pose": int(k),
        "circle_residual_mm": fit.circle_residual_rms_m * 1e3,
        "circle_radius_mm": fit.circle_radius_m * 1e3,
        "face_height_mm": fit.face_height_m * 1e3,
        "nests_flange_mm": {str(j): (p * 1e3).tolist() for j, p in nests.items()},
    }
    problems = []
    if fit.circle_residual_rms_m > limits.circle_residual_m:
        problems.append(
            f"pose {k}: the hole balls lie {fit.circle_residual_rms_m * 1e3:.3f} mm RMS off a circle (limit "
            f"{limits.circle_residual_m * 1e3:g} mm): an SMR not seated, dirt in a hole, or a wrong lock"
        )
    if abs(fit.circle_radius_m - config.hole_circle_radius_m) > limits.radius_error_m:
        problems.append(
            f"pose {k}: the hole circle's radius is {fit.circle_radius_m * 1e3:.3f} mm, the drawing says "
            f"{config.hole_circle_radius_m * 1e3:.3f} mm: check tool.hole_circle_radius_mm and the SMR size"
        )
    return _PoseFit(figures, nests, problems)


def _pose_agreement(
    nest_values: dict[int, list[np.ndarray]], limits: _Limits
) -> tuple[dict, dict, dict, list[str]]:
    """Each nest's mean over the poses, its 1-sigma, its worst spread, and the nests whose poses disagree."""
    nests_m = {j: np.mean(v, axis=0) for j, v in nest_values.items()}
    spread_m = {
        j: float(np.max(np.linalg.norm(np.asarray(v) - nests_m[j], axis=1))) for j, v in nest_values.items()
    }
    sigma_m = {
        j: float(np.sqrt(np.sum(np.var(np.asarray(v), axis=0, ddof=1)) / len(v)))
        for j, v in nest_values.items()
    }
    problems = [
        f"nest {j}: the poses disagree by up to {s * 1e3:.3f} mm (limit {limits.pose_spread_m * 1e3:g} mm)"
        for j, s in spread_m.items()
        if s > limits.pose_spread_m
    ]
    return nests_m, sigma_m, spread_m, problems


def _distance_check(
    config: CellConfig, data: RecordedPoints, nest1_m: np.ndarray, limits: _Limits
) -> tuple[dict, float, list[str]]:
    """Nest 1 again by the distance-constraint method; how far it is from the flange-hole fit."""
    check = [k for k, s in enumerate(data.step) if s == "distance_check"]
    p_dist, misfit = tool_point_by_distances(
        data.T_base_flange[check], data.p_tracker_m[check], config.nests_flange_m[0]
    )
    disagreement = float(np.linalg.norm(p_dist - nest1_m))
    problems = []
    if disagreement > limits.method_disagreement_m:
        problems.append(
            f"nest 1: the flange-hole fit and the distance-constraint check disagree by {disagreement * 1e3:.3f} mm "
            f"(limit {limits.method_disagreement_m * 1e3:g} mm): check tool.nests_flange_mm and the nest seats"
        )
    figures = {
        "nest1_flange_mm": (p_dist * 1e3).tolist(),
        "misfit_rms_mm": misfit * 1e3,
        "disagreement_mm": disagreement * 1e3,
    }
    return figures, disagreement, problems


def _fit(session: Session, the_plan: Plan, limits: _Limits) -> ToolFitResult:
    """Fit each pose, average the nests over the poses, cross-check nest 1, and refuse a fit beyond a limit."""
    config = session.config
    data = session.recorded_points(NAME)
    per_pose: list[dict] = []
    nest_values: dict[int, list[np.ndarray]] = {j: [] for j in range(1, len(config.nests_flange_m) + 1)}
    problems: list[str] = []
    for step in sorted({p.step for p in the_plan.poses if p.step.startswith("pose")}):
        k = step.removeprefix("pose")
        try:
            pose = _fit_pose(config, data, k, limits)
        except ValueError as exc:
            problems.append(f"pose {k}: {exc}")
            continue
        per_pose.append(pose.figures)
        problems += pose.problems
        for j, p in pose.nests_m.items():
            nest_values[j].append(p)
    if len(per_pose) < 2:
        raise ToolFitRejected(
            "the tool fit needs two good poses: " + "; ".join(problems),
            "re-seat the SMR carefully and run tool_fit on a new campaign step",
        )
    nests_m, sigma_m, spread_m, disagreeing = _pose_agreement(nest_values, limits)
    check, disagreement, mismatch = _distance_check(config, data, nests_m[1], limits)
    problems += disagreeing + mismatch
    result = {
        "nests_flange_mm": {str(j): (p * 1e3).tolist() for j, p in nests_m.items()},
        "uncertainty_mm": {str(j): s * 1e3 for j, s in sigma_m.items()},
        "pose_spread_mm": {str(j): s * 1e3 for j, s in spread_m.items()},
        "per_pose": per_pose,
        "distance_check": check,
    }
    if problems:
        session.event("tool_fit_rejected", "; ".join(problems), procedure=NAME)
        raise ToolFitRejected(
            "the tool fit failed its quality gate: " + "; ".join(problems),
            "fix the cause named, then run tool_fit on a new campaign",
        )
    session.finish_step(NAME, "fit", result)
    worst = max(p["circle_residual_mm"] for p in per_pose) / 1e3
    radius = float(np.mean([p["circle_radius_mm"] for p in per_pose])) / 1e3
    return ToolFitResult(nests_m, sigma_m, worst, radius, disagreement, result, limits)


def summary(result: ToolFitResult) -> str:
    lines = ["tool fit (flange frame, mm):"]
    for j, p in result.nests_flange_m.items():
        lines.append(
            f"  nest {j}: {p[0] * 1e3:9.4f} {p[1] * 1e3:9.4f} {p[2] * 1e3:9.4f}  +- {result.uncertainty_m[j] * 1e3:.4f}"
        )
    lim = result.limits
    circle = f" (limit {lim.circle_residual_m * 1e3:g} mm)" if lim else ""
    check = f" (limit {lim.method_disagreement_m * 1e3:g} mm)" if lim else ""
    lines.append(
        f"  worst circle residual {result.circle_residual_m * 1e3:.4f} mm{circle}; "
        f"distance-method check {result.distance_check_m * 1e3:.3f} mm{check}"
    )
    return "\n".join(lines)


PROCEDURE = Procedure(
    name=NAME,
    purpose="where are the tool's SMR nests in the flange frame (flange holes, face and nests at several poses)",
    instruction=__doc__ or "",
    parameters=(
        Parameter("poses", "flange poses, each with all holes, the face and the nests", 3, int, minimum=2),
        Parameter("check_poses", "poses of the distance-constraint cross-check", 12, int, minimum=4),
        Parameter("shots", "tracker shots per point", 10, int, minimum=1),
        Parameter("seed", "seed of the poses", 0, int, minimum=0),
    ),
    plan=plan,
    body=fit_tool,
    limits=(
        Limit("max_circle_residual", "hole balls off their circle, RMS, at any pose", 0.03, "mm"),
        Limit("max_radius_error", "hole circle's radius against the drawing", 0.2, "mm"),
        Limit("max_pose_spread", "a nest's spread over the poses", 0.1, "mm"),
        Limit("max_method_disagreement", "nest 1 by flange holes against nest 1 by distances", 3.0, "mm"),
    ),
    steps=("pose1..poseN", "distance_check", "fit"),
    summary=summary,
)
