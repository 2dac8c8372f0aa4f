"""The fake controller stops a move into the arm's own body with a protective stop, as a real one does on
contact, and it agrees with the planner's check: what the planner refuses for folding the arm the fake stops,
what the planner plans the fake runs."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from fakes.ur_controller import UrController
from fakes.ur_modes import NORMAL, PROTECTIVE_STOP
from fakes.ur_motion import JointMove, LinearMove, Motion, PathMove
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import transform_to_pose
from hil.runner.cell_config import parse_cell_config
from hil.runner.envelope import EnvelopeError
from hil.runner.planners import linear_path_joints
from procedures import grid_sampling, iso9283
from tests.cell_fixtures import sim_cell_toml


@pytest.fixture(scope="module")
def config():
    return parse_cell_config(tomllib.loads(sim_cell_toml()))  # collisions checked: the default


def _controller_at(q: np.ndarray) -> UrController:
    controller = UrController(SimulatedCell(SimCellConfig(robot="ur10", seed=0)))
    controller.q_cmd = np.asarray(q, float).copy()
    return controller


def _run(controller: UrController, q_target: np.ndarray, max_s: float = 30.0) -> None:
    """A moveJ at the default speeds, ticked until it ends or the controller stops it."""
    _run_motion(controller, JointMove(controller.q_cmd, q_target, 1.05, 1.4), max_s)


def _run_motion(controller: UrController, motion: Motion, max_s: float = 30.0) -> None:
    """A motion started on the controller, ticked until it ends or the controller stops it."""
    controller._start_motion(motion, is_async=False)
    for _ in range(int(max_s / controller.period_s)):
        controller.tick(controller.period_s)
        if controller.motion is None:
            return
    raise AssertionError("the move neither ended nor stopped")


def test_a_folded_elbow_move_is_refused_by_the_planner_and_stopped_by_the_fake(config):
    home = config.q_home_rad
    folded = home.copy()
    folded[2] = np.deg2rad(178.0)  # the forearm laid back onto the upper arm
    with pytest.raises(EnvelopeError, match="collide|within"):
        config.envelope.check_joint_move(config.nominal, home, folded, config.nests_flange_m)
    controller = _controller_at(home)
    _run(controller, folded)
    assert controller.safety_mode == PROTECTIVE_STOP
    contact = controller.arm_body.clearances(config.nominal, controller.q_cmd[None]).self_m[0]
    assert abs(contact) < 0.005  # stopped where the arm touches itself, short of the target
    assert home[2] < controller.q_cmd[2] < folded[2]


def test_a_planned_sequence_is_accepted_by_the_planner_and_run_by_the_fake(config):
    plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0)
    q = plan.joints()[:4]
    controller = _controller_at(config.q_home_rad)
    previous = config.q_home_rad
    for target in q:
        config.envelope.check_joint_move(config.nominal, previous, target, config.nests_flange_m)
        _run(controller, target)
        assert controller.safety_mode == NORMAL
        np.testing.assert_allclose(controller.q_cmd, target, atol=1e-12)
        previous = target


def _planner_refuses_linear(config, T_base_flange: np.ndarray, q_start: np.ndarray) -> bool:
    """What the session checks before a path run (every 5 mm of the flange's line): reachable, away from
    singularities, inside the envelope and clear of the arm itself and the cell."""
    _, joints = linear_path_joints(config.nominal, T_base_flange, config.nests_flange_m[0], q_start)
    outside = config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)
    return bool(not joints.usable.all() or outside.any())


def test_a_movel_that_folds_the_arm_is_refused_by_the_planner_and_stopped_by_the_fake(config):
    home = config.q_home_rad
    folded = home.copy()
    folded[2] = np.deg2rad(172.0)  # the flange straight to where the elbow lays the forearm onto the arm
    T = forward_kinematics(config.nominal, np.stack([home, folded]))
    assert _planner_refuses_linear(config, T, home)
    controller = _controller_at(home)
    _run_motion(controller, LinearMove(controller.model, home, T[1], 0.25, 1.2))
    assert controller.safety_mode == PROTECTIVE_STOP
    stopped = controller.q_cmd[None]
    contact = controller.arm_body.clearances(config.nominal, stopped)
    assert abs(contact.self_m[0]) < 0.005  # where the arm touches itself, short of the target
    flange = forward_kinematics(config.nominal, stopped)[0, :3, 3]
    assert np.linalg.norm(flange - T[1, :3, 3]) > 0.01
    # the links that touch are the arm's own (the fake knows no tool), and the planner refuses that pose too
    assert contact.self_between[0] == "shoulder and wrist 3"
    assert config.envelope.outside(config.nominal, stopped, config.nests_flange_m)[0]


def test_the_iso_paths_are_accepted_by_the_planner_and_run_by_the_fake(config):
    cube = iso9283.choose_cube(config, None, None, nest=1)
    runs = iso9283.plan_paths(config, cube, nest=1, model=None, speed_m_s=0.1)["before"]
    controller = _controller_at(config.q_home_rad)
    for run in runs:  # checked by the planner (plan_paths raises otherwise), then run as the driver sends it
        assert not _planner_refuses_linear(config, run.T_base_flange, run.q_start)
        _run(controller, run.q_start)
        segments = [
            ("movel", transform_to_pose(T), 0.1, 1.0, 0.0, k) for k, T in enumerate(run.T_base_flange)
        ]
        _run_motion(controller, PathMove(segments, controller.q_cmd, controller._path_segment), max_s=60.0)
        assert controller.safety_mode == NORMAL, run.name
        end = forward_kinematics(config.nominal, controller.q_cmd[None])[0]
        np.testing.assert_allclose(end[:3, 3], run.T_base_flange[-1, :3, 3], atol=1e-6)
