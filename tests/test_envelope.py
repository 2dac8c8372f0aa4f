"""The safety envelope: poses and whole paths outside it are refused before any motion."""

from __future__ import annotations

import contextlib
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.data.store import CampaignStore
from hil.geometry.ik import default_home
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.robots import get_robot
from hil.instruments.robot import RobotState
from hil.runner.cell_config import parse_cell_config
from hil.runner.envelope import Envelope, EnvelopeError
from hil.runner.operator import ScriptedOperator
from hil.runner.planners import wrist_points
from hil.runner.session import Session
from tests.cell_fixtures import sim_cell_toml

UR10 = get_robot("ur10")
TOOLS = np.array([[0.03, -0.02, 0.11], [-0.06, 0.04, 0.09]])


def _half_space_envelope() -> Envelope:
    """Only the half of the cell in front of the robot (y > -0.2 m) and above the table (z > -0.1 m)."""
    return Envelope(
        np.array([-1.5, -0.2, -0.1]), np.array([1.5, 1.5, 1.5]), np.full(6, -2 * np.pi), np.full(6, 2 * np.pi)
    )


def test_a_pose_outside_the_box_is_named():
    env = _half_space_envelope()
    q_in = np.array([-np.pi / 2, -1.2, 1.4, -1.7, -1.57, 0.0])  # UR arm points along -x rotated by q1: +y
    q_out = q_in.copy()
    q_out[0] = np.pi / 2  # towards -y
    assert env.pose_problems(UR10, q_in[None], TOOLS) == [None]
    with pytest.raises(EnvelopeError, match="pose 2: .*outside the box"):
        env.check_poses(UR10, np.stack([q_in, q_out]), TOOLS)


def test_a_joint_move_whose_path_leaves_the_box_is_refused_though_both_ends_are_inside():
    env = Envelope(np.array([-1.5, -0.3, -0.1]), np.array([1.5, 1.5, 1.5]), np.full(6, -7.0), np.full(6, 7.0))
    q_a = np.array([-np.pi / 2 + 0.9, -1.2, 1.4, -1.7, -1.57, 0.0])  # towards +y, turned by 0.9 rad
    q_b = q_a.copy()
    q_b[0] = -np.pi / 2 - 0.9 + 2 * np.pi  # same side, but reached the long way round through -y
    env.check_poses(UR10, np.stack([q_a, q_b]), TOOLS)
    with pytest.raises(EnvelopeError, match="% along the move"):
        env.check_joint_move(UR10, q_a, q_b, TOOLS)


def test_joint_limits_and_linear_segments_are_checked():
    env = Envelope(
        np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 1.5]), np.full(6, -np.pi), np.full(6, np.pi)
    )
    q = np.array([0.0, -1.2, 1.4, -1.7, -1.57, 4.0])
    assert "joint(s) 6" in env.pose_problems(UR10, q[None], TOOLS)[0]
    T_a = np.eye(4)
    T_a[:3, 3] = [0.6, 0.0, 0.8]
    T_b = T_a.copy()
    T_b[:3, 3] = [0.6, 0.0, 0.1]  # dips below the box floor at z = 0.2
    with pytest.raises(EnvelopeError, match="linear move"):
        env.check_linear_move(T_a, T_b, TOOLS)


class RecordingRobot:
    """An arm that goes wherever it is told and remembers every commanded target (no controller here:
    this checks the Session's guard, the wire protocol is tested against the fake controller)."""

    def __init__(self, q: np.ndarray):
        self.q = np.asarray(q, float)
        self.commanded: list[tuple[np.ndarray, np.ndarray]] = []

    def move_joints(self, q, speed=None, accel=None):
        self.commanded.append((self.q.copy(), np.asarray(q, float)))
        self.q = np.asarray(q, float)

    def joints(self):
        return self.q.copy()

    def flange_pose(self):
        return forward_kinematics(UR10, self.q[None])[0]

    def wait_settled(self, dwell_s=None, timeout_s=None):
        pass

    def stop(self):
        pass

    def state(self):
        return RobotState(True, "RUNNING", "NORMAL", True, False, False, 0.0)

    def recover(self):
        pass

    def close(self):
        pass


class NoTracker:
    def close(self):
        pass


@pytest.fixture(scope="module")
def config():
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["box_min_mm"] = [-1200.0, -300.0, -50.0]  # the robot may not swing behind itself
    data["envelope"]["box_max_mm"] = [1200.0, 1400.0, 1300.0]
    return parse_cell_config(data)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.lists(st.floats(-np.pi, np.pi), min_size=6, max_size=6), min_size=1, max_size=6))
def test_no_commanded_pose_or_path_ever_leaves_the_envelope(config, tmp_path_factory, targets):
    home = default_home(UR10)
    home[0] = -np.pi / 2  # start inside: arm towards +y
    assert config.envelope.pose_problems(UR10, home[None], config.nests_flange_m) == [None]
    robot = RecordingRobot(home)
    store = CampaignStore(tmp_path_factory.mktemp("env") / "campaign.sqlite")
    session = Session(config, robot, NoTracker(), store, ScriptedOperator({}))
    for q in [home + 0.05, *np.asarray(targets)]:  # the first, a small move from inside, must be allowed
        with contextlib.suppress(EnvelopeError):
            session.move_joints(q)
    session.close()
    assert len(robot.commanded) >= 1
    env = config.envelope
    for q_from, q_to in robot.commanded:  # an independent, finer check of every path that was commanded
        path = q_from + np.linspace(0, 1, 400)[:, None] * (q_to - q_from)
        T = forward_kinematics(UR10, path)
        tools = np.einsum("nij,kj->nki", T[:, :3, :3], config.nests_flange_m) + T[:, None, :3, 3]
        assert not env.point_violations(tools).any()
        assert not env.point_violations(wrist_points(UR10, path)).any()
        assert not env.joint_violations(path).any()
