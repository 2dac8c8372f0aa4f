"""Two simulated cells at once on different loopback addresses, each driven through its own driver."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.ur import URConfig, URRobot
from fakes.launch import sim_cell

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets

pytest.importorskip("rtde_control")

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


@pytest.mark.timeout(60)
def test_two_cells_run_side_by_side():
    with (
        sim_cell(robot="ur10", personality="cb3", seed=1, time_scale=10.0) as cell_a,
        sim_cell(robot="ur10e", personality="eseries", seed=2, time_scale=10.0) as cell_b,
    ):
        assert cell_a.host != cell_b.host
        assert cell_a.info["robot"]["rtde_port"] == cell_b.info["robot"]["rtde_port"] == 30004
        robot_a, robot_b = URRobot(URConfig(cell_a.host)), URRobot(URConfig(cell_b.host))
        try:
            assert robot_a.version.startswith("3.15") and robot_b.version.startswith("5.11")
            target_a, target_b = HOME + [0.4, 0, 0, 0, 0, 0], HOME + [-0.3, 0.1, 0, 0, 0, 0]
            robot_a.move_joints(target_a)
            robot_b.move_joints(target_b)
            np.testing.assert_allclose(
                cell_a.control.call("robot.state")["commanded_q"], target_a, atol=1e-12
            )
            np.testing.assert_allclose(
                cell_b.control.call("robot.state")["commanded_q"], target_b, atol=1e-12
            )
            np.testing.assert_allclose(robot_a.joints(), target_a, atol=2e-5)
            np.testing.assert_allclose(robot_b.joints(), target_b, atol=2e-5)
            # a fault in one cell leaves the other untouched
            cell_a.control.call("robot.fault", kind="protective_stop")
            deadline = time.monotonic() + 2.0
            while not robot_a.state().protective_stop:  # the data stream reports it on the next cycle
                assert time.monotonic() < deadline
            assert not robot_b.state().protective_stop
            robot_b.move_joints(HOME)
        finally:
            robot_a.close()
            robot_b.close()
