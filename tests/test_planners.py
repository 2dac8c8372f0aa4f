"""Pose planners: grids and facing poses in the box, reasons for unusable poses, visiting order."""

from __future__ import annotations

import numpy as np
import pytest

from hil.geometry.robots import get_robot
from hil.runner.planners import (
    Box,
    facing_poses,
    grid_points,
    plan_joints,
    random_order,
    sequence_duration_s,
    travel_order,
    workspace_box,
)

UR10 = get_robot("ur10")
TRACKER = np.array([1.0, 2.3, 0.2])
NEST = np.array([0.03, -0.02, 0.11])


def test_grid_covers_the_box_at_the_step():
    box = Box.from_limits(np.array([0.2, 0.2, 0.1]), np.array([0.6, 0.8, 0.5]))
    points = grid_points(box, 0.2)
    assert points.shape == (3 * 4 * 3, 3)  # 0.4/0.2+1, ticks centred in 0.6 -> 4 (0.1 margin), 3
    lo, hi = box.bounds()
    assert np.all(points >= lo - 1e-9) and np.all(points <= hi + 1e-9)
    spacing = np.diff(np.unique(points[:, 0]))
    assert np.allclose(spacing, 0.2)
    with pytest.raises(ValueError, match="20..500 mm"):
        grid_points(box, 0.01)


def test_facing_poses_keep_the_smr_inside_its_acceptance_cone():
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3)) + [0.5, 0.5, 0.5]
    T = facing_poses(points, TRACKER, np.random.default_rng(1), tilt_deg=20.0)
    to_tracker = TRACKER - points
    to_tracker /= np.linalg.norm(to_tracker, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", T[:, :3, 2], to_tracker), -1, 1)))
    assert angle.max() <= 20.0 + 1e-6 and angle.mean() > 5.0
    assert np.allclose(T[:, :3, 3], points)


def test_plan_joints_reaches_the_targets_and_names_unreachable_ones():
    box = workspace_box(UR10, TRACKER)
    points = np.vstack([grid_points(box, 0.2), [[3.0, 0.0, 0.5]]])  # the last one is out of reach
    T = facing_poses(points, TRACKER, np.random.default_rng(0))
    plan = plan_joints(UR10, T, NEST)
    assert plan.reason[-1] == "unreachable" and not plan.usable[-1]
    assert plan.usable.mean() > 0.9
    from hil.geometry.kinematics import tool_points

    reached = tool_points(UR10, plan.q[plan.usable], NEST)
    assert np.max(np.linalg.norm(reached - points[plan.usable], axis=1)) < 1e-6
    assert sum(plan.counts().values()) == len(points)


def test_travel_order_is_a_permutation_that_shortens_the_tour():
    box = workspace_box(UR10, TRACKER)
    T = facing_poses(grid_points(box, 0.15), TRACKER, np.random.default_rng(0))
    plan = plan_joints(UR10, T, NEST)
    q = plan.q[plan.usable]
    start = q[0]
    order = travel_order(q, start)
    assert sorted(order) == list(range(len(q)))
    shuffled = random_order(len(q), np.random.default_rng(3))
    t_travel = sequence_duration_s(q[order], start, 1.05, 1.4, 0.0)
    t_random = sequence_duration_s(q[shuffled], start, 1.05, 1.4, 0.0)
    assert t_travel < 0.6 * t_random
