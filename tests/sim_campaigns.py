"""Campaigns on the simulated cell for tests, planned with hil.runner.planners as a procedure plans them.

The planners see what an engineer knows of a cell: the nominal model, where the tracker stands (here the
simulated cell's own placement), the tool drawing and the home posture; `fakes.campaign.simulate_campaign`
then visits the joints on the cell.
"""

from __future__ import annotations

import numpy as np

from fakes.cell import SimulatedCell
from hil.runner.planners import Box, facing_poses, grid_points, plan_joints, random_points, workspace_box


def tracker_position_base_m(cell: SimulatedCell) -> np.ndarray:
    """Where the tracker stands in the robot base frame (3,)."""
    return np.linalg.inv(cell.T_tracker_base)[:3, 3]


def sampling_box(cell: SimulatedCell) -> Box:
    """The default sampling box: reachable, in front of the tracker."""
    return workspace_box(cell.nominal, tracker_position_base_m(cell))


def facing_joints(
    cell: SimulatedCell,
    points_base_m: np.ndarray,
    rng: np.random.Generator,
    nest: int = 1,
    keep_singular: bool = True,
) -> np.ndarray:
    """Nominal-IK joints (M, 6) reaching the points with the SMR in `nest` facing the tracker. Near-singular
    poses are kept by default (singular_sigma_m=0): the simulated cell is safe to drive there, and the
    calibration tests' campaigns have always held them; a procedure on a real arm drops them, as
    `keep_singular=False` does."""
    T_base_tool = facing_poses(points_base_m, tracker_position_base_m(cell), rng, tilt_deg=20.0)
    p_nest = np.asarray(cell.config.tool_nests_flange_m[nest - 1])  # the drawing, not the truth
    sigma = {} if not keep_singular else {"singular_sigma_m": 0.0}  # else the planner's own threshold
    plan = plan_joints(cell.nominal, T_base_tool, p_nest, q_near=np.asarray(cell.config.q_home_rad), **sigma)
    return plan.q[plan.usable]


def grid_joints(
    cell: SimulatedCell, step_m: float = 0.2, seed: int = 0, keep_singular: bool = True
) -> np.ndarray:
    """Joints for every usable vertex of a grid of `step_m` in the default box (raster order)."""
    points = grid_points(sampling_box(cell), step_m)
    return facing_joints(cell, points, np.random.default_rng(seed), keep_singular=keep_singular)


def held_out_joints(cell: SimulatedCell, count: int, seed: int = 1) -> np.ndarray:
    """Joints for `count` usable random points in the same box (held-out validation poses)."""
    rng = np.random.default_rng(seed)
    box = sampling_box(cell)
    found = [np.zeros((0, 6))]
    while sum(len(q) for q in found) < count:
        found.append(facing_joints(cell, random_points(box, 2 * count, rng), rng))
    return np.vstack(found)[:count]
