"""The UR driver against `hil sim`: moves, readings, bad input, and a typed error for every injected fault."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.ur import URConfig, URRobot
from fakes.launch import random_loopback_host, sim_cell
from fakes.ur_modes import PLAYING
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.robots import get_robot
from hil.instruments.robot import (
    EmergencyStopError,
    ProgramNotRunningError,
    ProtectiveStopError,
    Robot,
    RobotConfigError,
    RobotConnectionError,
    RobotNotReadyError,
    StaleDataError,
)

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets

pytest.importorskip("rtde_control")

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


@pytest.fixture(scope="module")
def cell():
    with sim_cell(robot="ur10e", time_scale=10.0) as running:
        yield running


@pytest.fixture(scope="module")
def robot(cell):
    robot = URRobot(URConfig(cell.host))
    try:
        yield robot
    finally:
        robot.close()  # before the fake goes away


@pytest.fixture
def ready_robot(robot, cell):
    """The shared robot, ready: a test that failed half-way must not leave its fault to the next one."""
    cell.control.call("robot.clear_faults")
    if not robot.state().ready:
        cell.control.call("robot.release_estop")
        robot.recover()
    return robot


@pytest.fixture
def sole_cell(robot, cell):
    """The cell with the shared robot closed: one control interface per controller owns the registers."""
    robot.close()  # closing twice is harmless
    wait_for(lambda: cell.control.call("robot.state")["rtde_clients"] == 0, "the fake saw the clients go")
    return cell


def wait_for(condition, what: str, timeout_s: float = 10.0) -> None:
    """Poll a condition on another process's state (it sees our socket events a little later)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.01)


@pytest.mark.timeout(30)
def test_moves_and_readings(robot, cell):
    assert isinstance(robot, Robot)
    target = HOME + [0.3, -0.2, 0.25, 0.1, 0.0, 0.2]
    robot.move_joints(target)
    robot.wait_settled(dwell_s=0.05)
    np.testing.assert_allclose(robot.joints(), target, atol=2e-5)
    T = robot.flange_pose()
    np.testing.assert_allclose(T, forward_kinematics(get_robot("ur10e"), target[None])[0], atol=1e-4)
    T_goal = T.copy()
    T_goal[:3, 3] += [0.05, 0.02, -0.1]
    robot.move_linear(T_goal)
    robot.wait_settled(dwell_s=0.0)
    np.testing.assert_allclose(robot.flange_pose()[:3, 3], T_goal[:3, 3], atol=1e-4)
    corners = np.tile(T_goal, (3, 1, 1))  # moveL through waypoints (ur-rtde's path form), ending at the last
    corners[:, :3, 3] += [[0.03, 0.0, 0.0], [0.03, 0.03, 0.0], [0.0, 0.0, 0.0]]
    robot.move_path(corners, speed=0.1)
    np.testing.assert_allclose(robot.flange_pose()[:3, 3], T_goal[:3, 3], atol=1e-4)
    state = robot.state()
    assert state.ready and state.robot_mode == "RUNNING" and state.safety_mode == "NORMAL"


@pytest.mark.timeout(30)
def test_a_path_is_driven_while_the_receive_stream_still_reports_the_program_restart(ready_robot, cell):
    """ur-rtde runs a path in a control program it uploads anew, and returns once its own stream shows that
    program running. The receive stream is another socket: on a loaded PC it still delivers packages from
    the restart's gap after that. The driver must read those as late news while the control stream says
    the program runs, not refuse the path with "program not running" (CI once failed so, by chance)."""
    robot = ready_robot
    robot.move_joints(HOME + [0.3, -0.2, 0.25, 0.1, 0.0, 0.2])
    robot.wait_settled(dwell_s=0.0)
    corners = np.tile(robot.flange_pose(), (2, 1, 1))
    corners[:, :3, 3] += [[0.02, 0.0, 0.0], [0.02, 0.02, 0.0]]
    rx, ctrl = robot._rx, robot._ctrl  # the driver's own ur-rtde interfaces, read beside it
    late_news: list[int] = []  # receive-stream states without a program while the control stream has one
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.is_set():
            state, running = rx.getRuntimeState(), ctrl.isProgramRunning()
            if running and state != PLAYING:
                late_news.append(state)
            time.sleep(0.001)

    sampler = threading.Thread(target=sample, daemon=True)
    cell.control.call("robot.fault", kind="reader_lag", duration_s=0.25)  # read-only clients' packages late
    sampler.start()
    try:
        robot.move_path(corners, speed=0.1)
    finally:
        cell.control.call("robot.clear_faults")
        sampling.set()
        sampler.join()
    assert late_news, "the receive stream never lagged the restart: the test did not test the lag"
    np.testing.assert_allclose(robot.flange_pose()[:3, 3], corners[-1, :3, 3], atol=1e-4)


@pytest.mark.timeout(20)
def test_bad_input_fails_before_any_motion(robot, cell):
    before = cell.control.call("robot.state")["moves_started"]
    with pytest.raises(RobotConfigError, match="6 finite"):
        robot.move_joints([0.0, 1.0, float("nan"), 0, 0, 0])
    with pytest.raises(RobotConfigError, match="joint speed"):
        robot.move_joints(HOME, speed=50.0)
    with pytest.raises(RobotConfigError, match="outside"):
        robot.move_joints(HOME + [7.0, 0, 0, 0, 0, 0])
    with pytest.raises(RobotConfigError, match="linear acceleration"):
        robot.move_linear(robot.flange_pose(), accel=-1.0)
    with pytest.raises(RobotConfigError, match="waypoints"):
        robot.move_path(robot.flange_pose())  # one pose, not (K, 4, 4)
    with pytest.raises(RobotConfigError, match="linear speed"):
        robot.move_path(robot.flange_pose()[None], speed=5.0)
    assert cell.control.call("robot.state")["moves_started"] == before


FAULTS = [
    ("protective_stop", {}, ProtectiveStopError),
    ("emergency_stop", {}, EmergencyStopError),
    ("stop_script", {}, ProgramNotRunningError),
    ("drop_rtde", {"duration_s": 1.0}, RobotConnectionError),
    ("stall", {"duration_s": 1.0}, StaleDataError),
    ("latency", {"duration_s": 1.0}, StaleDataError),
]
STOPS = ("protective_stop", "emergency_stop", "stop_script")  # faults that halt the controller's motion


@pytest.mark.timeout(40)
@pytest.mark.parametrize(("kind", "options", "error"), FAULTS, ids=[f[0] for f in FAULTS])
def test_fault_gives_typed_error_then_recovers(ready_robot, cell, kind, options, error):
    robot = ready_robot
    robot.move_joints(HOME)
    far = HOME + [1.2, 0, 0, 0, 0, 0]
    cell.control.call("robot.fault", kind=kind, at_move=1, fraction=0.3, **options)
    with pytest.raises(error) as info:
        robot.move_joints(far, speed=0.5)
    # The error names the fault, not the supervision deadline (that is RobotTimeoutError), and it came while the
    # fault lasted: a driver that waited out the 1 s stall or latency would see the move end normally. A hang is
    # caught by the test's timeout; how fast each fault surfaces is measured in benchmarks/ur_fake.py.
    assert "next:" in str(info.value)
    controller = cell.control.call("robot.state")
    fault = controller["faults"][-1]
    assert (fault["kind"], fault["move"]) == (kind, controller["moves_started"])  # it fired during this move
    if kind in STOPS:  # the stop cut the move short: the controller never finished it
        assert controller["last_move"]["finished_s"] is None
        assert controller["commanded_q"][0] < far[0] - 0.1
    if kind == "emergency_stop":
        with pytest.raises(EmergencyStopError):
            robot.recover()  # the button is still pressed
        cell.control.call("robot.release_estop")
    robot.recover()
    assert robot.state().ready
    robot.move_joints(far)
    np.testing.assert_allclose(robot.joints(), far, atol=2e-5)


@pytest.mark.timeout(30)
def test_close_leaves_the_robot_stopped_and_disconnected(robot, cell):
    robot.move_joints(HOME)
    robot.close()
    assert not cell.control.call("robot.state")["moving"]
    wait_for(lambda: cell.control.call("robot.state")["rtde_clients"] == 0, "the fake saw the clients go")
    with pytest.raises(RobotConnectionError):
        robot.joints()
    robot.close()  # closing twice is harmless


@pytest.mark.timeout(20)
def test_connect_to_nothing_fails_fast():
    # The socket probe (with timeouts) gave up, so ur-rtde's constructors (which wait without a timeout) never
    # ran; a hang is caught by the test's timeout, and the time to fail is in benchmarks/ur_fake.py.
    with pytest.raises(RobotConnectionError, match="could not connect .*does not answer"):
        URRobot(URConfig(random_loopback_host(), connect_timeout_s=0.5, connect_attempts=2))


def test_config_from_mapping_checks_keys_and_limits():
    config = URConfig.from_mapping({"host": "127.0.0.9", "joint_speed": 0.5, "max_joint_speed": 1.0})
    assert config.joint_speed == 0.5
    with pytest.raises(RobotConfigError, match="unknown UR settings"):
        URConfig.from_mapping({"host": "127.0.0.9", "joint_sped": 0.5})
    with pytest.raises(RobotConfigError, match="exceeds"):
        URConfig(host="127.0.0.9", linear_speed=2.0, max_linear_speed=1.0)


@pytest.mark.timeout(30)
def test_short_latency_spike_is_ridden_through(sole_cell):
    cell = sole_cell
    robot = URRobot(URConfig(cell.host, stale_after_s=0.5))
    try:
        robot.move_joints(HOME)
        cell.control.call("robot.fault", kind="latency", at_move=1, fraction=0.3, duration_s=0.2)
        robot.move_joints(HOME + [0.5, 0, 0, 0, 0, 0], speed=0.5)
        assert cell.control.call("robot.state")["faults"][-1]["kind"] == "latency"
    finally:
        robot.close()


@pytest.mark.timeout(60)
def test_powered_off_arm_is_reported_or_powered_on_when_allowed():
    with sim_cell(robot="ur10", time_scale=10.0, extra_args=("--powered-off",)) as off:
        with pytest.raises(RobotNotReadyError, match="POWER_OFF"):
            URRobot(URConfig(off.host))
        # refused before uploading the control program, which a powered-off controller would not start (ur-rtde
        # then waits 5 s for it): the fake received none
        assert off.control.call("robot.state")["programs_received"] == 0
        robot = URRobot(URConfig(off.host, power_on_at_connect=True))
        try:
            robot.move_joints(HOME + [0.2, 0, 0, 0, 0, 0])
            assert robot.state().robot_mode == "RUNNING"
            assert off.control.call("robot.state")["refused_programs"] == []  # uploaded once powered
        finally:
            robot.close()


def test_threads_started_for_the_receive_interfaces_get_a_coarse_timer_slack_and_the_caller_keeps_its_own():
    """ur-rtde's receive threads poll every 100 us; started inside `coarse_timer_slack` they inherit a slack of
    RECEIVE_TIMER_SLACK_NS (wake about a thousand times a second, not 2 700), and the caller's slack is
    restored. Read through prctl from inside each thread, as the kernel applies it."""
    import ctypes
    import sys
    import threading

    from drivers.ur import RECEIVE_TIMER_SLACK_NS, coarse_timer_slack

    if not sys.platform.startswith("linux"):
        pytest.skip("timer slack is Linux's")
    libc = ctypes.CDLL(None, use_errno=True)

    def slack() -> int:
        return libc.prctl(30, 0, 0, 0, 0)  # PR_GET_TIMERSLACK

    seen: list[int] = []
    before = slack()
    with coarse_timer_slack():
        worker = threading.Thread(target=lambda: seen.append(slack()))
        worker.start()
        worker.join()
    assert seen == [RECEIVE_TIMER_SLACK_NS]
    assert slack() == before != RECEIVE_TIMER_SLACK_NS


def test_receive_threads_of_a_cb3_get_half_its_cycle_as_slack_and_an_e_series_or_unknown_controller_one_ms():
    """The slack follows the controller's cycle, known from its version at connect: a CB3 (3.x) streams every
    8 ms, its receive threads may oversleep 4 ms; an e-Series (5.x) every 2 ms, 1 ms; a version that says
    nothing gets the finer. The CB3's is what a thread started inside `coarse_timer_slack` then runs with."""
    import ctypes
    import sys
    import threading

    from drivers.ur import CB3_RECEIVE_TIMER_SLACK_NS, RECEIVE_TIMER_SLACK_NS, coarse_timer_slack
    from drivers.ur import receive_timer_slack_ns as slack_for

    assert CB3_RECEIVE_TIMER_SLACK_NS == 4_000_000 and RECEIVE_TIMER_SLACK_NS == 1_000_000
    assert slack_for("3.15.7.106331") == slack_for("3.0.0.0") == CB3_RECEIVE_TIMER_SLACK_NS
    assert slack_for("5.11.1.108318") == slack_for("10.1.0.0") == RECEIVE_TIMER_SLACK_NS
    assert slack_for("") == slack_for("x.1") == RECEIVE_TIMER_SLACK_NS
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    seen: list[int] = []
    with coarse_timer_slack(slack_for("3.15.7.106331")):
        worker = threading.Thread(target=lambda: seen.append(libc.prctl(30, 0, 0, 0, 0)))
        worker.start()
        worker.join()
    assert seen == [CB3_RECEIVE_TIMER_SLACK_NS]
