"""Grid sampling: measure the robot over its working volume (grid paper, SVR paper; docs/loop/papers.md).

Shop-floor instruction: put the SMR in the tool nest. The robot visits every reachable vertex of a
Cartesian grid (100-200 mm step) in a box of the working volume, with the SMR facing the tracker, in one or
more tool orientations; at each it settles and the tracker takes several shots (outliers rejected). If the
beam breaks, the tracker is re-aimed at where the SMR should be from the robot's pose and the point is
measured again. Then a random set of held-out poses in the same box is measured for validation. The export
(`hil campaign export`) is the dataset `hil calibrate` and `hil diagnose` read.

Orientation (cell.toml `[grid] orientation`, or the `orientation` parameter): "varied" (the default, what a
calibration wants: every vertex in its own orientation, so the wrist joints move) or "fixed" (the grid
paper: one tool orientation at every vertex, `fixed_rpy_deg` or facing the tracker from the box centre).

Order: "travel" keeps moves short; "random" makes consecutive moves of different joints independent, which
separates the backlash of different joints. `both_directions` measures each vertex twice, approached once
from below and once from above on every joint.

Drift monitor (cell.toml `[drift_monitor] poses = 3, every_points = 25`): a few grid poses, spread over the
grid, are measured again as step `reference` before the grid, after every `every_points` grid points and at
its end, so every campaign carries the evidence for drift and thermal growth (their time and temperature).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hil.runner.cell_config import GRID_ORIENTATIONS, CellConfig
from hil.runner.clear_joints import clear_travel_order, plan_clear_joints
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import (
    Box,
    facing_poses,
    facing_rotations,
    fixed_poses,
    grid_points,
    random_order,
    random_points,
    rpy_rotation,
    workspace_box,
)
from hil.runner.procedure import SHOTS, Parameter, Procedure, Role
from hil.runner.session import Session

NAME = "grid_sampling"
APPROACH_RAD = np.deg2rad(2.0)  # pre-position offset on every joint for a known approach direction
ORDERS = ("travel", "random")


@dataclass(frozen=True)
class GridOptions:
    """The declared parameters, SI (None: absent, the procedure picks)."""

    step_m: float
    box_min_m: tuple[float, float, float] | None
    box_max_m: tuple[float, float, float] | None
    orientations: int
    order: str
    both_directions: bool
    validation: int
    nest: int
    tilt_rad: float
    orientation: str | None
    fixed_rpy_rad: tuple[float, float, float] | None
    seed: int
    shots: int | None


@dataclass(frozen=True)
class GridResult:
    planned: int
    recorded: int
    dropped: dict[str, int]
    validation_planned: int
    validation_recorded: int


def sampling_box(
    config: CellConfig, box_min_m: Sequence[float] | None, box_max_m: Sequence[float] | None
) -> Box:
    """The box to sample (robot base frame): the one given, else a reachable box in front of the tracker."""
    if (box_min_m is None) != (box_max_m is None):
        raise ValueError(
            "give both --box-min-mm and --box-max-mm, or neither (default box in front of the tracker)"
        )
    if box_min_m is None or box_max_m is None:
        return workspace_box(config.nominal, config.p_base_tracker_m)
    return Box.from_limits(np.asarray(box_min_m, float), np.asarray(box_max_m, float))


def plan(config: CellConfig, options: GridOptions) -> Plan:
    """The grid and validation poses, filtered for reachability, singularity and the envelope, in order."""
    nest, orientations, validation = options.nest, options.orientations, options.validation
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"--nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    rng = np.random.default_rng(options.seed)
    box = sampling_box(config, options.box_min_m, options.box_max_m)
    p_nest = config.nests_flange_m[nest - 1]
    dropped: dict[str, int] = {}
    R_fixed = fixed_orientation(config, box, options.orientation, options.fixed_rpy_rad, orientations)

    def usable_joints(points: np.ndarray, like: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if R_fixed is None:
            T = facing_poses(
                points, config.p_base_tracker_m, rng, tilt_deg=float(np.rad2deg(options.tilt_rad))
            )
        else:
            T = fixed_poses(points, R_fixed)
        joints = plan_clear_joints(
            config.nominal, config.envelope, T, p_nest, config.nests_flange_m, config.q_home_rad, like=like
        )
        reason = joints.reason
        for r in reason[reason != "ok"]:
            dropped[str(r)] = dropped.get(str(r), 0) + 1
        keep = reason == "ok"
        return joints.q[keep], np.flatnonzero(keep)

    grid = grid_points(box, options.step_m)
    q_list, ids = [], []
    for k in range(orientations):
        q, kept = usable_joints(grid)
        q_list.append(q)
        ids += [f"g{k + 1}-{i:04d}" for i in kept]
    q_grid = np.vstack(q_list) if q_list else np.zeros((0, 6))
    visit = (
        clear_travel_order(config.nominal, config.envelope, q_grid, config.q_home_rad)
        if options.order == "travel"
        else random_order(len(q_grid), rng)
    )
    location = f"nest{nest}"
    setup = (OperatorStep(f"Put SMR 1 in tool nest {nest}.", "place_smr", smr=1, location=location),)

    def pose(point_id: str, step: str, q: np.ndarray) -> PlannedPose:
        return PlannedPose(
            point_id,
            NAME,
            step,
            q,
            location,
            smr=nest,
            approach_q_rad=approach_pose(point_id, q),
            setup=setup,
        )

    suffixes = ("+", "-") if options.both_directions else ("",)
    poses = [pose(ids[i] + s, "grid", q_grid[i]) for i in visit for s in suffixes]
    poses = with_reference_rounds(poses, config.drift_poses, config.drift_every_points, pose)
    if validation:
        # in the grid's configuration: validation poses where the grid was measured
        q_val, _ = usable_joints(random_points(box, 3 * validation, rng), like=q_grid)
        poses += [pose(f"v{k + 1:04d}", "validation", q) for k, q in enumerate(q_val[:validation])]
    if not poses:
        raise ValueError("no grid vertex is reachable inside the envelope: move the box or widen [envelope]")
    return Plan(NAME, poses, config, operator_steps=1, dropped=dropped).without_unsafe_moves()


def fixed_orientation(
    config: CellConfig,
    box: Box,
    orientation: str | None,
    fixed_rpy_rad: Sequence[float] | None,
    orientations: int,
) -> np.ndarray | None:
    """R_base_tool of a fixed-orientation grid, None for a varied one. The parameter wins over cell.toml's
    [grid]; a fixed grid without a given orientation faces the tracker from the box centre (SMR visible)."""
    chosen = orientation or config.grid_orientation
    if chosen not in GRID_ORIENTATIONS:
        raise ValueError(f"--orientation {chosen}: use one of {', '.join(GRID_ORIENTATIONS)}")
    if chosen == "varied":
        if fixed_rpy_rad is not None:
            raise ValueError("--fixed-rpy-deg is only used with --orientation fixed; give both or neither")
        return None
    if orientations > 1:
        raise ValueError(
            f"--orientations {orientations} with a fixed orientation measures each vertex {orientations} times "
            "in the same pose; use --orientations 1, or --orientation varied"
        )
    rpy = fixed_rpy_rad if fixed_rpy_rad is not None else config.grid_fixed_rpy_rad
    if rpy is not None:
        return rpy_rotation(np.asarray(rpy, float))
    return facing_rotations(box.centre_m[None], config.p_base_tracker_m)[0]


def with_reference_rounds(
    grid: list[PlannedPose], n_poses: int, every: int, pose: Callable[[str, str, np.ndarray], PlannedPose]
) -> list[PlannedPose]:
    """The grid with rounds of `n_poses` reference poses (spread over the grid) before it, after every
    `every` grid points and after it; the grid unchanged when the monitor is off or the grid empty."""
    if n_poses < 1 or every < 1 or not grid:
        return grid
    picks = np.unique(np.linspace(0, len(grid) - 1, min(n_poses, len(grid))).round().astype(int))
    refs = [(f"r{k + 1}", grid[i].q_rad) for k, i in enumerate(picks)]

    def round_(r: int) -> list[PlannedPose]:
        return [pose(f"{name}-{r:03d}", "reference", q) for name, q in refs]

    out, r = round_(0), 1
    for start in range(0, len(grid), every):
        out += grid[start : start + every] + round_(r)
        r += 1
    return out


def approach_pose(point_id: str, q: np.ndarray) -> np.ndarray | None:
    """The pre-position of a both-directions visit: below every joint for '+', above for '-'."""
    if point_id.endswith("+"):
        return q - APPROACH_RAD
    if point_id.endswith("-"):
        return q + APPROACH_RAD
    return None


def sample(session: Session, options: GridOptions, the_plan: Plan) -> GridResult:
    """Measure the grid, then the held-out validation poses, on a registered cell; resumable."""
    session.require_registration()
    session.engine.visit(the_plan, shots=options.shots, extra={"order": options.order}, pin=True)
    steps = [p.step for p in the_plan.poses]
    recorded = session.store.measurements(NAME)
    counts = recorded["step"].value_counts().to_dict() if len(recorded) else {}
    return GridResult(
        planned=steps.count("grid"),
        recorded=int(counts.get("grid", 0)),
        dropped=the_plan.dropped,
        validation_planned=steps.count("validation"),
        validation_recorded=int(counts.get("validation", 0)),
    )


def summary(result: GridResult) -> str:
    dropped = ", ".join(f"{n} {r}" for r, n in sorted(result.dropped.items())) or "none"
    return (
        f"grid sampling: {result.recorded}/{result.planned} grid points and {result.validation_recorded}/"
        f"{result.validation_planned} validation points recorded; left out when planning: {dropped}"
    )


PROCEDURE = Procedure(
    name=NAME,
    purpose="measure the robot over its working volume: a grid (100-200 mm step) and held-out validation poses",
    instruction=__doc__ or "",
    parameters=(
        Parameter(
            "step", "grid step (the papers use 100-200)", 100.0, float, unit="mm", minimum=20.0, maximum=500.0
        ),
        Parameter(
            "box_min",
            "sampling box corner x y z, base frame (default: a box facing the tracker)",
            None,
            float,
            unit="mm",
            count=3,
        ),
        Parameter("box_max", "opposite box corner x y z", None, float, unit="mm", count=3),
        Parameter("orientations", "tool orientations per grid vertex", 1, int, minimum=1),
        Parameter("order", "visiting order", "travel", str, choices=ORDERS),
        Parameter("both_directions", "approach each vertex from below and from above", False, bool),
        Parameter("validation", "random held-out validation poses", 50, int, minimum=0),
        Parameter("nest", "tool nest holding the SMR", 1, int, minimum=1),
        Parameter(
            "tilt",
            "max tilt of the SMR from the tracker line (beyond 30 the SMR turns out of the beam)",
            20.0,
            float,
            unit="deg",
            minimum=0.0,
            maximum=30.0,
        ),
        Parameter(
            "orientation",
            "varied: each vertex its own tool orientation facing the tracker (calibration); fixed: one "
            "orientation everywhere (the grid paper); default: cell.toml [grid] orientation, else varied",
            None,
            str,
            choices=GRID_ORIENTATIONS,
        ),
        Parameter(
            "fixed_rpy",
            "the fixed tool orientation: roll, pitch, yaw about the base x, y, z (default: cell.toml [grid] "
            "fixed_rpy_deg, else facing the tracker from the box centre)",
            None,
            float,
            unit="deg",
            count=3,
        ),
        Parameter("seed", "seed of the orientations and validation poses", 0, int, minimum=0),
        SHOTS,
    ),
    plan=plan,
    body=sample,
    steps=("plan", "grid", "reference", "validation"),
    summary=summary,
    publishes=((Role.GRID, "grid"), (Role.VALIDATION, "validation")),
    options=GridOptions,
)
