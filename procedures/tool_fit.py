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
from typing import Any

import numpy as np

from hil.analysis.flange_geometry import fit_flange_frame, tool_point_by_distances, tool_point_in_flange
from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import Box, facing_poses, plan_joints, workspace_box
from hil.runner.session import CampaignStopped, Session

PROCEDURE = "tool_fit"
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


def hole_points_flange(config: CellConfig) -> dict[str, np.ndarray]:
    """Nominal SMR centres (flange frame) for every location of the procedure: hole1..hole7 and face."""
    k = np.arange(1, 7)
    angles = np.deg2rad((k - 3.5) * 60.0)
    seat = np.sqrt(config.smr_radius_m**2 - (config.hole_diameter_m / 2) ** 2)
    points = {f"hole{i}": np.array([config.hole_circle_radius_m * np.cos(a), config.hole_circle_radius_m * np.sin(a), seat]) for i, a in zip(k, angles, strict=True)}
    points["hole7"] = np.array([config.hole7_radius_m, 0.0, seat])
    points["face"] = np.array([*face_point(config), config.smr_radius_m])
    return points


def face_point(config: CellConfig) -> tuple[float, float]:
    """Where the SMR rests on the face: opposite hole 7, clear of the holes."""
    return (-config.hole7_radius_m, 0.0)


def plan(config: CellConfig, *, poses: int = 3, check_poses: int = 12, seed: int = 0) -> Plan:
    """Flange poses facing the tracker (rolled differently), then distance-check poses with the SMR in nest 1."""
    if poses < 2:
        raise ValueError("the tool fit needs at least 2 poses (--poses)")
    if check_poses < 4:
        raise ValueError("the distance cross-check needs at least 4 poses (--check-poses)")
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
    steps: list[PlannedPose] = []
    nests = [f"nest{j}" for j in range(1, len(config.nests_flange_m) + 1)]
    for k, q in enumerate(q_fit, start=1):
        for location in [*(f"hole{h}" for h in HOLES), "face", *nests]:
            steps.append(PlannedPose(f"p{k}/{location}", PROCEDURE, f"pose{k}", q, location))
    for k, q in enumerate(q_check, start=1):
        steps.append(PlannedPose(f"c{k:02d}", PROCEDURE, "distance_check", q, "nest1"))
    operator = poses * (len(HOLES) + 1 + len(nests)) + 1
    return Plan(PROCEDURE, steps, config, operator_steps=operator)


def run(
    session: Session,
    *,
    poses: int = 3,
    check_poses: int = 12,
    shots: int = 10,
    seed: int = 0,
    max_circle_residual_mm: float = 0.03,
    max_radius_error_mm: float = 0.2,
    max_pose_spread_mm: float = 0.1,
    max_method_disagreement_mm: float = 3.0,
) -> ToolFitResult:
    """Fit the tool's SMR nests in the flange frame (see the module docstring for the shop-floor steps)."""
    config = session.config
    the_plan = plan(config, poses=poses, check_poses=check_poses, seed=seed)
    session.check_poses(the_plan.joints(), [p.point_id for p in the_plan.poses])
    session.require_registration()
    nominal_points = hole_points_flange(config)
    for j in range(1, len(config.nests_flange_m) + 1):
        nominal_points[f"nest{j}"] = np.asarray(config.nests_flange_m[j - 1], float)
    pending = [p for p in the_plan.poses if not session.recorded(PROCEDURE, p.step, p.point_id)]
    done = len(the_plan.poses) - len(pending)
    current_location = None
    with session.progress.task("tool fit", total=len(the_plan.poses), done=done) as advance:
        for pose in pending:
            if pose.location != current_location:
                where = pose.location.replace("nest", "tool nest ").replace("hole", "flange hole ")
                text = "Rest SMR 1 on the flange face, opposite hole 7." if pose.location == "face" else f"Seat SMR 1 in {where}."
                session.ask(OperatorStep(text, "place_smr", smr=1, location=pose.location, face_point_m=face_point(config)))
                current_location = pose.location
            session.measure_point(
                PROCEDURE, pose.step, pose.point_id, pose.q_rad, smr=1, location=pose.location,
                p_flange_m=nominal_points[pose.location], shots=shots,
            )
            advance()
    return _fit(session, the_plan, max_circle_residual_mm, max_radius_error_mm, max_pose_spread_mm, max_method_disagreement_mm)


def _fit(
    session: Session,
    the_plan: Plan,
    max_circle_residual_mm: float,
    max_radius_error_mm: float,
    max_pose_spread_mm: float,
    max_method_disagreement_mm: float,
) -> ToolFitResult:
    config = session.config
    data = session.recorded_points(PROCEDURE)
    by_id = {pid: k for k, pid in enumerate(data.point_id)}
    steps = sorted({p.step for p in the_plan.poses if p.step.startswith("pose")})
    n_nests = len(config.nests_flange_m)
    per_pose: list[dict[str, Any]] = []
    nest_values: dict[int, list[np.ndarray]] = {j: [] for j in range(1, n_nests + 1)}
    problems: list[str] = []
    for step in steps:
        k = step.removeprefix("pose")

        def point(location: str, k: str = k) -> np.ndarray:
            return data.p_tracker_m[by_id[f"p{k}/{location}"]]

        holes = {h: point(f"hole{h}") for h in HOLES}
        try:
            fit = fit_flange_frame(holes, point("face"), smr_radius_m=config.smr_radius_m)
        except ValueError as exc:
            problems.append(f"pose {k}: {exc}")
            continue
        nests = {j: tool_point_in_flange(fit.T_tracker_flange, point(f"nest{j}")) for j in range(1, n_nests + 1)}
        for j, p in nests.items():
            nest_values[j].append(p)
        per_pose.append(
            {
                "pose": int(k),
                "circle_residual_mm": fit.circle_residual_rms_m * 1e3,
                "circle_radius_mm": fit.circle_radius_m * 1e3,
                "face_height_mm": fit.face_height_m * 1e3,
                "nests_flange_mm": {str(j): (p * 1e3).tolist() for j, p in nests.items()},
            }
        )
        if fit.circle_residual_rms_m * 1e3 > max_circle_residual_mm:
            problems.append(
                f"pose {k}: the hole balls lie {fit.circle_residual_rms_m * 1e3:.3f} mm RMS off a circle (limit "
                f"{max_circle_residual_mm} mm): an SMR not seated, dirt in a hole, or a wrong lock"
            )
        radius_error = abs(fit.circle_radius_m - config.hole_circle_radius_m) * 1e3
        if radius_error > max_radius_error_mm:
            problems.append(
                f"pose {k}: the hole circle's radius is {fit.circle_radius_m * 1e3:.3f} mm, the drawing says "
                f"{config.hole_circle_radius_m * 1e3:.3f} mm: check tool.hole_circle_radius_mm and the SMR size"
            )
    if len(per_pose) < 2:
        raise ToolFitRejected("the tool fit needs two good poses: " + "; ".join(problems), "re-seat the SMR carefully and run tool_fit on a new campaign step")
    nests_m = {j: np.mean(v, axis=0) for j, v in nest_values.items()}
    spread_m = {j: float(np.max(np.linalg.norm(np.asarray(v) - nests_m[j], axis=1))) for j, v in nest_values.items()}
    sigma_m = {j: float(np.sqrt(np.sum(np.var(np.asarray(v), axis=0, ddof=1)) / len(v))) for j, v in nest_values.items()}
    for j, s in spread_m.items():
        if s * 1e3 > max_pose_spread_mm:
            problems.append(f"nest {j}: the poses disagree by up to {s * 1e3:.3f} mm (limit {max_pose_spread_mm} mm)")
    check = [k for k, s in enumerate(data.step) if s == "distance_check"]
    p_dist, misfit = tool_point_by_distances(data.T_base_flange[check], data.p_tracker_m[check], config.nests_flange_m[0])
    disagreement = float(np.linalg.norm(p_dist - nests_m[1]))
    if disagreement * 1e3 > max_method_disagreement_mm:
        problems.append(
            f"nest 1: the flange-hole fit and the distance-constraint check disagree by {disagreement * 1e3:.3f} mm "
            f"(limit {max_method_disagreement_mm} mm): check tool.nests_flange_mm and the nest seats"
        )
    result = {
        "nests_flange_mm": {str(j): (p * 1e3).tolist() for j, p in nests_m.items()},
        "uncertainty_mm": {str(j): s * 1e3 for j, s in sigma_m.items()},
        "pose_spread_mm": {str(j): s * 1e3 for j, s in spread_m.items()},
        "per_pose": per_pose,
        "distance_check": {"nest1_flange_mm": (p_dist * 1e3).tolist(), "misfit_rms_mm": misfit * 1e3, "disagreement_mm": disagreement * 1e3},
    }
    if problems:
        session.event("tool_fit_rejected", "; ".join(problems), procedure=PROCEDURE)
        raise ToolFitRejected("the tool fit failed its quality gate: " + "; ".join(problems), "fix the cause named, then run tool_fit on a new campaign")
    session.finish_step(PROCEDURE, "fit", result)
    worst = max(p["circle_residual_mm"] for p in per_pose) / 1e3
    radius = float(np.mean([p["circle_radius_mm"] for p in per_pose])) / 1e3
    return ToolFitResult(nests_m, sigma_m, worst, radius, disagreement, result)
