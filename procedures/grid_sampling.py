"""Grid sampling: measure the robot over its working volume (grid paper, SVR paper; methods.md sections 2-3).

Shop-floor instruction: put the SMR in the tool nest. The robot visits every reachable vertex of a
Cartesian grid (100-200 mm step) in a box of the working volume, with the SMR facing the tracker, in one or
more tool orientations; at each it settles and the tracker takes several shots (outliers rejected). If the
beam breaks, the tracker is re-aimed at where the SMR should be from the robot's pose and the point is
measured again. Then a random set of held-out poses in the same box is measured for validation. The export
(`hil campaign export`) is the dataset `hil calibrate` and `hil diagnose` read.

Order: "travel" keeps moves short; "random" makes consecutive moves of different joints independent, which
separates the backlash of different joints. `both_directions` measures each vertex twice, approached once
from below and once from above on every joint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import (
    Box,
    facing_poses,
    grid_points,
    plan_joints,
    random_order,
    random_points,
    travel_order,
    workspace_box,
)
from hil.runner.session import Session

PROCEDURE = "grid_sampling"
APPROACH_RAD = np.deg2rad(2.0)  # pre-position offset on every joint for a known approach direction
ORDERS = ("travel", "random")


@dataclass(frozen=True)
class GridResult:
    planned: int
    recorded: int
    dropped: dict[str, int]
    validation_planned: int
    validation_recorded: int


def sampling_box(config: CellConfig, box_min_mm: tuple[float, float, float] | None, box_max_mm: tuple[float, float, float] | None) -> Box:
    """The box to sample (robot base frame): the one given, else a reachable box in front of the tracker."""
    if (box_min_mm is None) != (box_max_mm is None):
        raise ValueError("give both --box-min-mm and --box-max-mm, or neither (default box in front of the tracker)")
    if box_min_mm is None:
        return workspace_box(config.nominal, config.p_base_tracker_m)
    return Box.from_limits(np.asarray(box_min_mm, float) / 1e3, np.asarray(box_max_mm, float) / 1e3)


def plan(
    config: CellConfig,
    *,
    step_mm: float = 100.0,
    box_min_mm: tuple[float, float, float] | None = None,
    box_max_mm: tuple[float, float, float] | None = None,
    orientations: int = 1,
    order: str = "travel",
    both_directions: bool = False,
    validation: int = 50,
    nest: int = 1,
    tilt_deg: float = 20.0,
    seed: int = 0,
) -> Plan:
    """The grid and validation poses, filtered for reachability, singularity and the envelope, in order."""
    if not 20.0 <= step_mm <= 500.0:
        raise ValueError(f"--step-mm {step_mm:g} is outside 20..500 mm (the papers use 100-200 mm)")
    if order not in ORDERS:
        raise ValueError(f"--order {order!r}: choose one of {', '.join(ORDERS)}")
    if orientations < 1 or validation < 0:
        raise ValueError("--orientations must be >= 1 and --validation >= 0")
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"--nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    if not 0.0 <= tilt_deg <= 30.0:
        raise ValueError("--tilt-deg must lie in 0..30: beyond 30 deg the SMR turns out of the beam")
    rng = np.random.default_rng(seed)
    box = sampling_box(config, box_min_mm, box_max_mm)
    p_nest = config.nests_flange_m[nest - 1]
    dropped: dict[str, int] = {}

    def usable_joints(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = facing_poses(points, config.p_base_tracker_m, rng, tilt_deg=tilt_deg)
        joints = plan_joints(config.nominal, T, p_nest, q_near=config.q_home_rad)
        reason = joints.reason.copy()
        reason[joints.usable & config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)] = "envelope"
        for r in reason[reason != "ok"]:
            dropped[str(r)] = dropped.get(str(r), 0) + 1
        keep = reason == "ok"
        return joints.q[keep], np.flatnonzero(keep)

    grid = grid_points(box, step_mm / 1e3)
    q_list, ids = [], []
    for k in range(orientations):
        q, kept = usable_joints(grid)
        q_list.append(q)
        ids += [f"g{k + 1}-{i:04d}" for i in kept]
    q_grid = np.vstack(q_list) if q_list else np.zeros((0, 6))
    visit = travel_order(q_grid, config.q_home_rad) if order == "travel" else random_order(len(q_grid), rng)
    poses = []
    for i in visit:
        if both_directions:
            poses.append(PlannedPose(ids[i] + "+", PROCEDURE, "grid", q_grid[i], f"nest{nest}"))
            poses.append(PlannedPose(ids[i] + "-", PROCEDURE, "grid", q_grid[i], f"nest{nest}"))
        else:
            poses.append(PlannedPose(ids[i], PROCEDURE, "grid", q_grid[i], f"nest{nest}"))
    if validation:
        q_val, _ = usable_joints(random_points(box, 3 * validation, rng))
        for k, q in enumerate(q_val[:validation]):
            poses.append(PlannedPose(f"v{k + 1:04d}", PROCEDURE, "validation", q, f"nest{nest}"))
    if not poses:
        raise ValueError("no grid vertex is reachable inside the envelope: move the box or widen [envelope]")
    return Plan(PROCEDURE, poses, config, operator_steps=1, dropped=dropped)


def approach_pose(point_id: str, q: np.ndarray) -> np.ndarray | None:
    """The pre-position of a both-directions visit: below every joint for '+', above for '-'."""
    if point_id.endswith("+"):
        return q - APPROACH_RAD
    if point_id.endswith("-"):
        return q + APPROACH_RAD
    return None


def run(session: Session, *, nest: int = 1, shots: int | None = None, **options) -> GridResult:
    """Measure the grid and the held-out validation poses (see the module docstring); resumable."""
    the_plan = plan(session.config, nest=nest, **options)
    session.check_poses(the_plan.joints(), [p.point_id for p in the_plan.poses])
    approaches = [approach_pose(p.point_id, p.q_rad) for p in the_plan.poses]
    if any(a is not None for a in approaches):
        session.check_poses(np.array([a for a in approaches if a is not None]))
    session.require_registration()
    session.pin_plan(the_plan)
    p_nest = session.nest_flange_m(nest)
    pending = [(p, a) for p, a in zip(the_plan.poses, approaches, strict=True) if not session.recorded(PROCEDURE, p.step, p.point_id)]
    if pending:
        session.ask(OperatorStep(f"Put SMR 1 in tool nest {nest}.", "place_smr", smr=1, location=f"nest{nest}"))
    with session.progress.task("grid sampling", total=len(the_plan.poses), done=len(the_plan.poses) - len(pending)) as advance:
        for pose, approach in pending:
            if approach is not None:
                session.move_joints(approach, label=pose.point_id + " approach")
            session.measure_point(
                PROCEDURE, pose.step, pose.point_id, pose.q_rad, smr=nest, location=pose.location,
                p_flange_m=p_nest, shots=shots, extra={"order": options.get("order", "travel")},
            )
            advance()
    steps = [p.step for p in the_plan.poses]
    recorded = session.store.measurements(PROCEDURE)
    counts = recorded["step"].value_counts().to_dict() if len(recorded) else {}
    return GridResult(
        planned=steps.count("grid"),
        recorded=int(counts.get("grid", 0)),
        dropped=the_plan.dropped,
        validation_planned=steps.count("validation"),
        validation_recorded=int(counts.get("validation", 0)),
    )
