"""The real ur-rtde 1.6.5 client (receive, control, IO, dashboard) against `hil sim`, on both personalities."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fakes.launch import sim_cell
from fakes.ur_script import ControlProgram, UnknownProgramError, parse_path
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.robots import get_robot
from hil.geometry.se3 import pose_to_transform, transform_to_pose

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")
rtde_io = pytest.importorskip("rtde_io")
dashboard_client = pytest.importorskip("dashboard_client")

TIME_SCALE = 10.0
ROBOTS = {"eseries": "ur10e", "cb3": "ur10"}


class Rig:
    """One simulated cell and the ur-rtde clients connected to it."""

    def __init__(self, cell, personality: str):
        self.cell = cell
        self.personality = personality
        self.model = get_robot(ROBOTS[personality])
        self.host = cell.host
        self.dash = dashboard_client.DashboardClient(self.host)
        self.dash.connect(2000)
        self.rx = rtde_receive.RTDEReceiveInterface(self.host)
        self.ctrl = rtde_control.RTDEControlInterface(self.host)

    def new_control(self) -> None:
        """Disconnect the old control interface before building a fresh one (never rebind a live one)."""
        self.ctrl.disconnect()
        self.ctrl = None
        self.ctrl = rtde_control.RTDEControlInterface(self.host)

    def settle_stream(self) -> None:
        """Let the receive stream catch up with the controller's present: it is a separate socket from
        the control stream and lags by a varying number of packages on a busy machine."""
        now_s = self.cell.control.call("ping")["time_s"]  # the fake's clock, after what we saw happen
        wait_for(lambda: self.rx.getTimestamp() >= now_s, "the receive stream caught up")

    def ensure_running(self) -> None:
        """Start the control program again if an earlier test left it stopped (keeps failures local)."""
        if self.ctrl.isProgramRunning():
            return
        self.ctrl.reuploadScript()
        deadline = time.monotonic() + 5
        while not self.ctrl.isProgramRunning():
            assert time.monotonic() < deadline, "the control program did not start again"
            time.sleep(0.01)

    def home(self) -> list[float]:
        self.ensure_running()
        q = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
        assert self.ctrl.moveJ(q, 3.0, 10.0)
        self.settle_stream()
        return q

    def close(self) -> None:
        for client in (self.ctrl, self.rx, self.dash):
            if client is not None:
                client.disconnect()
        self.ctrl = self.rx = self.dash = None


def wait_for(condition, what: str, timeout_s: float = 10.0) -> None:
    """Poll a condition with a generous deadline (CI machines are busy)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.001)


@pytest.fixture(scope="module", params=["eseries", "cb3"])
def rig(request):
    personality = request.param
    with sim_cell(robot=ROBOTS[personality], personality=personality, time_scale=TIME_SCALE) as cell:
        rig = Rig(cell, personality)
        try:
            yield rig
        finally:
            rig.close()  # clients first, then the fake


def assert_pose_close(actual, desired, atol: float) -> None:
    """Compare UR poses as transforms (rotation vectors near pi are ill-conditioned component-wise)."""
    np.testing.assert_allclose(
        pose_to_transform(np.asarray(actual)), pose_to_transform(np.asarray(desired)), atol=atol
    )


def _trapezoid(distance: float, v: float, a: float) -> float:
    peak = min(v, np.sqrt(distance * a))
    return distance / peak + peak / a


@pytest.mark.timeout(30)
def test_versions_and_dashboard_state(rig):
    dash = rig.dash
    expected = "5.11" if rig.personality == "eseries" else "3.15"
    assert dash.polyscopeVersion().startswith(expected)
    assert dash.robotmode() == "Robotmode: RUNNING"
    assert "NORMAL" in dash.safetystatus()
    assert dash.getRobotModel() == "UR10"
    assert dash.running()
    assert dash.programState().startswith("PLAYING")
    if rig.personality == "eseries":
        assert dash.isInRemoteControl()
        assert dash.getSerialNumber().isdigit()
    assert rig.rx.getRobotMode() == 7 and rig.rx.getSafetyMode() == 1
    assert rig.ctrl.isProgramRunning()


@pytest.mark.timeout(30)
def test_movej_reaches_target_in_trapezoid_time(rig):
    q0 = rig.home()
    target = list(q0)
    target[0] += 0.3
    assert rig.ctrl.moveJ(target, 1.05, 1.4)
    rig.settle_stream()
    move = rig.cell.control.call("robot.state")["last_move"]
    assert move["kind"] == "JointMove"
    assert move["planned_duration_s"] == pytest.approx(_trapezoid(0.3, 1.05, 1.4), rel=1e-12)
    # the move ends on the first tick at or after its duration; under CPU load a tick spans up to 10 periods
    max_tick = 10 * TIME_SCALE / rig.cell.info["robot"]["frequency_hz"]
    assert 0 <= (move["finished_s"] - move["started_s"]) - move["planned_duration_s"] <= max_tick
    np.testing.assert_allclose(rig.rx.getTargetQ(), target, atol=1e-12)
    actual = np.array(rig.rx.getActualQ())
    np.testing.assert_allclose(actual, target, atol=2e-5)
    assert np.any(actual != np.array(target))  # encoder noise from the simulated cell


@pytest.mark.timeout(30)
def test_movel_follows_a_straight_line(rig):
    rig.home()
    start = np.array(rig.rx.getActualTCPPose())
    target = start.copy()
    target[:3] += [0.10, -0.05, -0.08]
    rig.cell.control.call("set_time_scale", value=1.0)  # ~0.7 s of wall time to sample the path in
    try:
        assert rig.ctrl.moveL(target.tolist(), 0.25, 1.2, True)
        positions = []
        while rig.ctrl.getAsyncOperationProgress() >= 0 or len(positions) < 3:
            positions.append(rig.rx.getTargetTCPPose()[:3])
            time.sleep(0.002)
    finally:
        rig.cell.control.call("set_time_scale", value=TIME_SCALE)
    rig.settle_stream()
    direction = (target[:3] - start[:3]) / np.linalg.norm(target[:3] - start[:3])
    offsets = np.array(positions) - start[:3]
    off_line = offsets - np.outer(offsets @ direction, direction)
    assert np.max(np.linalg.norm(off_line, axis=1)) < 1e-5
    assert len(positions) > 5
    assert_pose_close(rig.rx.getTargetTCPPose(), target, atol=1e-9)


@pytest.mark.timeout(30)
def test_movej_ik_and_movel_fk(rig):
    q0 = rig.home()
    pose = transform_to_pose(forward_kinematics(rig.model, np.array([q0]) + [0.2, 0.1, -0.1, 0, 0.1, 0])[0])
    assert rig.ctrl.moveJ_IK(pose.tolist(), 1.0, 2.0)
    rig.settle_stream()
    assert_pose_close(rig.rx.getTargetTCPPose(), pose, atol=1e-8)
    assert rig.ctrl.moveL_FK(q0, 0.5, 2.0)
    rig.settle_stream()
    np.testing.assert_allclose(rig.rx.getTargetQ(), q0, atol=1e-6)


@pytest.mark.timeout(30)
def test_forward_and_inverse_kinematics_agree_with_ours(rig):
    q = [0.3, -1.2, 1.4, -1.5, -1.4, 0.4]
    tcp = [0.0, 0.0, 0.1, 0.0, 0.0, 0.2]
    expected = forward_kinematics(rig.model, np.array([q]))[0] @ pose_to_transform(np.array(tcp))
    assert_pose_close(rig.ctrl.getForwardKinematics(q, tcp), transform_to_pose(expected), atol=1e-10)
    pose = transform_to_pose(forward_kinematics(rig.model, np.array([q]))[0]).tolist()
    solution = rig.ctrl.getInverseKinematics(pose, [0.25, -1.15, 1.35, -1.45, -1.45, 0.35])
    T = forward_kinematics(rig.model, np.array([solution]))[0]
    np.testing.assert_allclose(T, pose_to_transform(np.array(pose)), atol=1e-8)
    np.testing.assert_allclose(solution, q, atol=1e-6)  # the branch nearest qnear


@pytest.mark.timeout(30)
def test_set_tcp_shifts_the_reported_tcp(rig):
    rig.home()
    flange = pose_to_transform(np.array(rig.rx.getActualTCPPose()))
    assert rig.ctrl.setTcp([0, 0, 0.1, 0, 0, 0])
    np.testing.assert_allclose(rig.ctrl.getTCPOffset(), [0, 0, 0.1, 0, 0, 0], atol=1e-12)
    rig.settle_stream()
    shifted = np.array(rig.rx.getActualTCPPose())
    np.testing.assert_allclose(shifted[:3], flange[:3, 3] + 0.1 * flange[:3, 2], atol=1e-4)
    assert rig.ctrl.setTcp([0] * 6)


@pytest.mark.timeout(30)
def test_async_move_stopj_and_is_steady(rig):
    q0 = rig.home()
    target = list(q0)
    target[0] += 2.0
    assert rig.ctrl.moveJ(target, 0.5, 1.0, True)
    assert rig.ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning()
    wait_for(lambda: rig.rx.getTargetQ()[0] > q0[0] + 0.01, "the async move is under way")
    rig.ctrl.stopJ(2.0)
    rig.settle_stream()
    deadline = time.monotonic() + 5
    while not rig.ctrl.isSteady():
        assert time.monotonic() < deadline
    q = rig.rx.getTargetQ()
    assert q0[0] < q[0] < target[0]
    assert rig.ctrl.getAsyncOperationProgress() < 0
    # stopL decelerates an async linear move too
    pose = np.array(rig.rx.getActualTCPPose())
    pose[2] -= 0.2
    assert rig.ctrl.moveL(pose.tolist(), 0.1, 0.5, True)
    wait_for(
        lambda: rig.rx.getTargetTCPPose()[2] < pose[2] + 0.2 - 0.005, "the async linear move is under way"
    )
    rig.ctrl.stopL(1.0)
    rig.settle_stream()
    assert rig.rx.getTargetTCPPose()[2] > pose[2]


@pytest.mark.timeout(30)
def test_speedj_and_speedstop(rig):
    q0 = rig.home()
    assert rig.ctrl.speedJ([0.2, 0, 0, 0, 0, 0], 2.0, 0.0)
    wait_for(lambda: rig.rx.getTargetQ()[0] > q0[0] + 0.02, "the joint speeds up")
    assert rig.ctrl.speedStop(5.0)
    rig.settle_stream()
    q = rig.rx.getTargetQ()
    assert q[0] > q0[0] + 0.01
    np.testing.assert_allclose(q[1:], q0[1:], atol=1e-12)
    assert not np.any(rig.rx.getTargetQd())


@pytest.mark.timeout(30)
def test_joint_and_linear_paths(rig):
    q0 = rig.home()
    waypoints = [np.add(q0, [0.1 * i, -0.05 * i, 0.05 * i, 0, 0, 0]).tolist() for i in (1, 2, 3)]
    assert rig.ctrl.moveJ([w + [1.0, 2.0, 0.0] for w in waypoints])
    rig.settle_stream()
    # ur-rtde writes path waypoints into the script text with 6 significant digits
    np.testing.assert_allclose(rig.rx.getTargetQ(), waypoints[-1], atol=1e-5)
    pose = np.array(rig.rx.getActualTCPPose())
    path = [np.add(pose, [0, 0, -0.05 * i, 0, 0, 0]).tolist() + [0.25, 1.2, 0.0] for i in (1, 2)]
    assert rig.ctrl.moveL(path)
    rig.settle_stream()
    assert_pose_close(rig.rx.getTargetTCPPose(), path[-1][:6], atol=1e-5)


@pytest.mark.timeout(30)
def test_uploaded_program_is_parsed_from_its_text(rig):
    rig.ensure_running()
    text = rig.cell.control.call("robot.last_program")
    program = ControlProgram.parse(text)
    assert program.offset == 0
    assert program.realtime_commands == {6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
    assert {1, 2, 3, 4, 29, 30, 43, 44, 45, 46, 47, 255} <= program.handled_commands
    segments = parse_path(text)  # the last upload carried the moveL path
    assert [s.kind for s in segments] == ["movel_pose", "movel_pose"]
    with pytest.raises(UnknownProgramError, match="pinned"):
        ControlProgram.parse(text.replace("14.02.2024-12:23", "01.01.2030-00:00"))
    with pytest.raises(UnknownProgramError, match="not ur-rtde"):
        ControlProgram.parse("def my_program():\n  movej([0,0,0,0,0,0])\nend\n")


@pytest.mark.timeout(30)
def test_unmodelled_commands_still_signal_done(rig):
    rig.ensure_running()
    # ur-rtde returns True only once the script signalled done, and waits 3 s for "ready" before the next
    # command (then returns False): each True says the previous command handed the handshake back. A command
    # that never signals done hangs the client (300 s), caught by the test's timeout. Handshake latencies are
    # in benchmarks/ur_fake.py.
    assert rig.ctrl.setPayload(1.0, [0, 0, 0.05])
    assert rig.ctrl.zeroFtSensor()
    assert rig.ctrl.teachMode() and rig.ctrl.endTeachMode()
    assert rig.ctrl.isJointsWithinSafetyLimits([0, -1.5, 1.5, -1.5, -1.5, 0])
    rig.settle_stream()
    assert rig.rx.getPayload() == 1.0  # and the script ran them: the modelled one took effect


@pytest.mark.timeout(30)
def test_io_interface_sets_outputs(rig):
    io = rtde_io.RTDEIOInterface(rig.host)
    try:
        # the IO interface writes without any acknowledgement: wait for the receive stream to show it
        assert io.setStandardDigitalOut(3, True)
        wait_for(lambda: rig.rx.getDigitalOutState(3), "digital output 3 reads high")
        assert io.setStandardDigitalOut(3, False)
        wait_for(lambda: not rig.rx.getDigitalOutState(3), "digital output 3 reads low")
    finally:
        io.disconnect()  # before the fake could go away (a late IO destructor aborts the process)


@pytest.mark.timeout(40)
def test_stop_script_and_reupload(rig):
    rig.ensure_running()
    rig.ctrl.stopScript()
    assert not rig.ctrl.isProgramRunning()
    rig.settle_stream()  # the receive stream is a separate socket and may lag a cycle
    assert rig.rx.getRuntimeState() == 1
    assert rig.ctrl.reuploadScript()
    deadline = time.monotonic() + 5
    while not rig.ctrl.isProgramRunning():  # the controller takes a moment to start the program
        assert time.monotonic() < deadline
        time.sleep(0.01)
    rig.home()


@pytest.mark.timeout(40)
def test_protective_stop_pauses_then_unlock_and_fresh_control(rig):
    q0 = rig.home()
    rig.ctrl.triggerProtectiveStop()
    deadline = time.monotonic() + 5
    while not rig.rx.isProtectiveStopped():
        assert time.monotonic() < deadline
    assert rig.dash.programState().startswith("PAUSED")
    target = list(q0)
    target[0] += 0.2
    assert not rig.ctrl.moveJ(target)  # the client gives up at once on a protective stop
    while True:  # the controller refuses to unlock during the first 5 (simulated) seconds
        try:
            rig.dash.unlockProtectiveStop()
            break
        except RuntimeError:
            assert time.monotonic() < deadline
            time.sleep(0.1)
    rig.dash.play()  # resumes the paused control program: the same interface works again
    deadline = time.monotonic() + 5
    while not rig.ctrl.isProgramRunning():
        assert time.monotonic() < deadline
    assert rig.ctrl.moveJ(target)
    rig.new_control()  # and so does a fresh one, which uploads the program again
    assert rig.ctrl.moveJ(q0)
    rig.settle_stream()
    np.testing.assert_allclose(rig.rx.getTargetQ(), q0, atol=1e-12)


@pytest.mark.timeout(30)
def test_controller_belief_differs_from_the_physical_arm(rig):
    q = rig.home()
    belief = pose_to_transform(np.array(rig.rx.getActualTCPPose()))
    truth = np.array(rig.cell.control.call("cell.state")["T_base_flange_true"])
    nominal = forward_kinematics(rig.model, np.array([q]))[0]
    np.testing.assert_allclose(belief[:3, 3], nominal[:3, 3], atol=1e-4)
    gap = np.linalg.norm(truth[:3, 3] - belief[:3, 3])
    assert 1e-5 < gap < 0.05  # hidden errors of the simulated cell


@pytest.mark.timeout(30)
def test_remote_control_gating_and_unknown_programs(rig):
    import socket

    rig.ensure_running()
    if rig.personality == "eseries":
        rig.cell.control.call("robot.set_remote_control", value=False)
        try:
            assert not rig.dash.isInRemoteControl()
            with pytest.raises(RuntimeError, match="remote control"):
                rtde_control.RTDEControlInterface(rig.host)
        finally:
            rig.cell.control.call("robot.set_remote_control", value=True)
    before = len(rig.cell.control.call("robot.state")["refused_programs"])
    with socket.create_connection((rig.host, 30002), timeout=2) as sock:
        # a program with a statement the fake controller does not run: a script error, the program not started
        sock.sendall(
            b'def my_program():\n  socket_open("10.0.0.1", 30000)\n  movej([0, 0, 0, 0, 0, 0])\nend\n'
        )
    deadline = time.monotonic() + 2
    while len(rig.cell.control.call("robot.state")["refused_programs"]) == before:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert rig.ctrl.isProgramRunning()  # the refused program did not replace the control program


@pytest.mark.timeout(30)
def test_rtde_watchdog_stops_the_program_when_not_kicked(rig):
    rig.ensure_running()
    # the client must write the command register at >= 2 Hz (wall time: a busy test process kicking
    # every 20 ms can still miss a 50 ms watchdog)
    assert rig.ctrl.setWatchdog(2.0)
    for _ in range(5):
        assert rig.ctrl.kickWatchdog()
        time.sleep(0.02)
    assert rig.ctrl.isProgramRunning()
    deadline = time.monotonic() + 3
    while rig.ctrl.isProgramRunning():  # no more kicks: the controller stops the program
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert rig.ctrl.reuploadScript()
    while not rig.ctrl.isProgramRunning():
        assert time.monotonic() < deadline + 3
        time.sleep(0.01)
    rig.home()


@pytest.mark.timeout(30)
def test_pose_trans_waypoint_and_flange_queries(rig):
    q0 = rig.home()
    a, b = [0.1, 0.2, 0.3, 0.1, -0.2, 0.3], [0.05, 0.0, 0.1, 0.0, 0.4, 0.0]
    expected = pose_to_transform(np.array(a)) @ pose_to_transform(np.array(b))
    assert_pose_close(rig.ctrl.poseTrans(a, b), transform_to_pose(expected), atol=1e-12)
    flange = forward_kinematics(rig.model, np.array([q0]))[0]
    np.testing.assert_allclose(
        pose_to_transform(np.array(rig.ctrl.getForwardKinematics())), flange, atol=1e-4
    )
    target = list(q0)
    target[0] += 1.0
    assert rig.ctrl.moveJ(target, 0.3, 1.0, True)
    waypoint = rig.ctrl.getTargetWaypoint()
    rig.ctrl.stopJ(3.0)
    goal = forward_kinematics(rig.model, np.array([target]))[0]
    np.testing.assert_allclose(pose_to_transform(np.array(waypoint)), goal, atol=1e-9)
    rig.home()


@pytest.mark.timeout(30)
def test_second_control_interface_is_refused_while_registers_are_in_use(rig):
    rig.ensure_running()
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(rig.host)
    assert rig.ctrl.isConnected() and rig.ctrl.isProgramRunning()
    rig.home()
