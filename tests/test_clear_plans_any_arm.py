"""Clear plans on an arm that is not UR-shaped: the simulated LR Mate (a FANUC-like arm whose elbow turns
-160..190 deg, its body 50 mm capsules along the DH table). The nominal IK nearest home often bends its
elbow the other way, past the fold at 90 deg where the forearm lies in the upper arm, so no move from home's
side reaches it; the planner keeps the elbow and joint 5 within the range they turn from home unfolded."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hil.geometry.arm_configurations import (
    WRIST_CENTRE_FRAME,
    arm_configuration_seeds,
    has_parallel_shoulder_and_elbow,
)
from hil.geometry.collision import clear_range_rad
from hil.geometry.kinematics import forward_kinematics, link_frames
from hil.runner.cell_config import parse_cell_config
from hil.runner.clear_joints import NO_CLEAR, plan_clear_joints
from hil.runner.plan import NO_SAFE_PATH
from hil.runner.planners import facing_poses, grid_points, plan_joints, workspace_box
from procedures import grid_sampling
from tests.cell_fixtures import sim_cell_toml


@pytest.fixture(scope="module")
def config():
    return parse_cell_config(tomllib.loads(sim_cell_toml(seed=3, time_scale=100.0, robot="lrmate200id")))


@pytest.fixture(scope="module")
def elbow_range(config):
    return clear_range_rad(config.bodies, config.nominal, config.q_home_rad, 2)


def test_the_default_grid_keeps_most_of_its_poses_each_reached_by_a_safe_move(config, elbow_range):
    """The default box (36 vertices, behind the arm towards the tracker) and 20 validation poses: before, the
    nominal IK's folded elbows left all but 10 poses without a safe path."""
    grid = grid_sampling.PROCEDURE.make_plan(config, step_m=0.1, validation=20)
    ids = [p.point_id for p in grid.poses]
    assert sum(i.startswith("g") for i in ids) >= 20
    assert sum(i.startswith("v") for i in ids) == 20
    assert NO_SAFE_PATH not in grid.dropped
    assert grid.path_check()[1] == []
    assert config.bodies.pair_slack_m(config.nominal, grid.joints()).min() >= 0.0
    lo, hi = elbow_range
    assert hi < np.deg2rad(90.0)  # the fold: the forearm onto the upper arm
    assert np.all((grid.joints()[:, 2] >= lo) & (grid.joints()[:, 2] <= hi))


def test_the_arm_configurations_put_the_wrist_centre_where_the_joints_do(config):
    """Four arms (shoulder, elbow) and two wrists; the LR Mate has no sideways offset, so all are exact."""
    assert has_parallel_shoulder_and_elbow(config.nominal)
    q = np.random.default_rng(1).uniform(-1.0, 1.0, (30, 6)) + np.array([0.0, 0.0, 0.6, 0.0, 1.0, 0.0])
    seeds = arm_configuration_seeds(config.nominal, q)
    assert seeds.shape == (8, 30, 6)
    off = np.abs(np.angle(np.exp(1j * (seeds - q))))  # (8, 30, 6), 2 pi turns aside
    mine = np.argmin(off.max(axis=2), axis=0)
    assert set(mine) <= {0, 1} and off[mine, np.arange(30)].max() < 1e-9  # q itself, its base unturned
    centre = link_frames(config.nominal, seeds.reshape(-1, 6))[:, WRIST_CENTRE_FRAME, :3, 3]
    np.testing.assert_allclose(centre.reshape(8, 30, 3), np.broadcast_to(centre[:30], (8, 30, 3)), atol=1e-9)
    other = off[1 - mine, np.arange(30)]
    assert np.all(other[:, 2] > 1e-3)  # the other side of the elbow is another joint 3
    T = forward_kinematics(config.nominal, seeds[[0, 4]].reshape(-1, 6)).reshape(2, 30, 4, 4)
    np.testing.assert_allclose(T[1], T[0], atol=1e-9)  # the flipped wrist: the same flange


def test_a_pose_the_nominal_ik_folds_is_solved_unfolded_or_left_out_as_not_clear(config, elbow_range):
    lo, hi = elbow_range
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    T = facing_poses(grid_points(box, 0.1), config.p_base_tracker_m, np.random.default_rng(0))
    p_nest = config.nests_flange_m[0]
    nearest = plan_joints(config.nominal, T, p_nest, q_near=config.q_home_rad)
    folded = nearest.usable & (nearest.q[:, 2] > hi)
    assert folded.sum() >= 10  # what the planner must avoid
    clear = plan_clear_joints(
        config.nominal, config.envelope, T, p_nest, config.nests_flange_m, config.q_home_rad
    )
    solved = folded & clear.usable
    assert solved.sum() >= 5 and set(clear.reason[folded & ~clear.usable]) <= {NO_CLEAR, "envelope"}
    assert np.all(clear.q[solved, 2] <= hi)
    # the same tool pose, with the elbow on home's side
    T_flange_tool = np.eye(4)
    T_flange_tool[:3, 3] = p_nest
    reached = forward_kinematics(config.nominal, clear.q[solved]) @ T_flange_tool
    np.testing.assert_allclose(reached, T[solved], atol=1e-6)
    # answers the nominal IK gave unfolded are kept as they were
    kept = nearest.usable & ~folded & clear.usable
    np.testing.assert_array_equal(clear.q[kept], nearest.q[kept])
