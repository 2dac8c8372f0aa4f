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
from fakes.ur_motion import JointMove
from hil.runner.cell_config import parse_cell_config
from hil.runner.envelope import EnvelopeError
from procedures import grid_sampling
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
    controller._start_motion(JointMove(controller.q_cmd, q_target, 1.05, 1.4), is_async=False)
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
