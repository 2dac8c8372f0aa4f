"""Unit tests of the fake controller's parts that need no sockets: wire types, motion, parsing, state."""

from __future__ import annotations

import numpy as np
import pytest

from fakes import rtde_wire as w
from fakes.cell import SimCellConfig, SimulatedCell
from fakes.fast_kinematics import ArmKinematics, pose_from_transform, rotvec_from_matrix
from fakes.ur_controller import UrController
from fakes.ur_dashboard import NOT_REMOTE, handle_command
from fakes.ur_motion import JointMove, LinearMove, SpeedMove, StopMove, Trapezoid
from fakes.ur_script import ControlProgram, UnknownProgramError, split_programs
from hil.geometry.coupling import CouplingLimit, JointCoupling
from hil.geometry.kinematics import forward_kinematics, geometric_jacobian
from hil.geometry.robots import get_robot
from hil.geometry.se3 import transform_to_pose


def test_variable_table_types():
    assert w.output_type("actual_q") == "VECTOR6D"
    assert w.output_type("runtime_state") == "UINT32"
    assert w.output_type("output_int_register_12") == "INT32"
    assert w.output_type("input_double_register_47") == "DOUBLE"
    assert w.output_type("output_bit_register_64") == "BOOL"
    assert w.output_type("output_int_register_48") is None
    assert w.output_type("no_such_thing") is None
    assert w.input_type("input_int_register_3") == "INT32"
    assert w.input_type("output_int_register_3") is None  # outputs are not writable
    assert w.input_type("standard_digital_output_mask") == "UINT8"


def test_recipe_round_trip():
    recipe = w.Recipe.build(
        3,
        ["timestamp", "actual_q", "robot_mode", "joint_mode"],
        ["DOUBLE", "VECTOR6D", "INT32", "VECTOR6INT32"],
    )
    values = [1.5, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 7, [253] * 6]
    payload = recipe.pack(values)
    assert len(payload) == 8 + 48 + 4 + 24
    decoded = recipe.unpack(payload)
    assert decoded["timestamp"] == 1.5 and decoded["joint_mode"] == (253,) * 6
    assert w.split_names(b"a,b,,c,") == ["a", "b", "c"]


def test_trapezoid_timing():
    long_move = Trapezoid(2.0, 1.0, 2.0)  # reaches the speed limit
    assert long_move.duration == pytest.approx(2.0 / 1.0 + 1.0 / 2.0)
    short_move = Trapezoid(0.3, 1.05, 1.4)  # triangular
    assert short_move.duration == pytest.approx(2 * np.sqrt(0.3 / 1.4))
    t = np.linspace(0, short_move.duration, 200)
    s = np.array([short_move.at(x)[0] for x in t])
    assert np.all(np.diff(s) >= -1e-15) and s[-1] == pytest.approx(0.3)


def test_joint_move_is_timed_by_the_leading_axis():
    q0, q1 = np.zeros(6), np.array([0.5, -0.2, 0.1, 0, 0, 0.25])
    move = JointMove(q0, q1, 1.0, 2.0)
    assert move.duration == pytest.approx(Trapezoid(0.5, 1.0, 2.0).duration)
    q = q0
    for _ in range(2000):
        q, _ = move.advance(0.001, q)
        if move.finished:
            break
    np.testing.assert_array_equal(q, q1)
    with pytest.raises(ValueError, match="speed"):
        JointMove(q0, q1, 0.0, 1.0)


def test_linear_move_ends_exactly_on_target():
    model = get_robot("ur10")
    q0 = np.array([0.2, -1.4, 1.5, -1.6, -1.5, 0.3])
    T1 = forward_kinematics(model, q0[None])[0]
    T1[:3, 3] += [0.05, 0.1, -0.05]
    move = LinearMove(model, q0, T1, 0.25, 1.2)
    q = q0
    while not move.finished:
        q, _ = move.advance(0.008, q)
    np.testing.assert_allclose(forward_kinematics(model, q[None])[0], T1, atol=1e-12)


def test_stop_and_speed_moves():
    stop = StopMove(np.array([1.0, 0, 0, 0, 0, -0.5]), 2.0)
    q = np.zeros(6)
    while not stop.finished:
        q, qd = stop.advance(0.01, q)
    assert q[0] == pytest.approx(0.25) and q[5] == pytest.approx(-0.125)  # v^2 / 2a
    speed = SpeedMove(np.zeros(6), np.array([0.2, 0, 0, 0, 0, 0]), 1.0)
    for _ in range(50):
        q, qd = speed.advance(0.01, q)
    assert qd[0] == pytest.approx(0.2)


def test_fast_kinematics_match_the_batch_model():
    model = get_robot("ur5e")
    kin = ArmKinematics(model)
    for q in np.random.default_rng(0).uniform(-3, 3, (20, 6)):
        np.testing.assert_allclose(kin.fk(q), forward_kinematics(model, q[None])[0], atol=1e-14)
        np.testing.assert_allclose(kin.jacobian(q), geometric_jacobian(model, q[None])[0], atol=1e-14)
    R = np.diag([1.0, -1.0, -1.0])  # a rotation by exactly pi
    np.testing.assert_allclose(np.abs(rotvec_from_matrix(R)), [np.pi, 0, 0], atol=1e-12)
    T = forward_kinematics(model, np.array([[0.1, -1, 1, 0.2, 0.3, 0.4]]))[0]
    np.testing.assert_allclose(pose_from_transform(T), transform_to_pose(T), atol=1e-12)


def test_split_programs_waits_for_the_end_line():
    done, rest = split_programs("def a():\n  x = 1\n  if x:\n    y = 2\n  end\n")
    assert done == [] and rest.startswith("def a")
    done, rest = split_programs(rest + "end\ndef b():\n")
    assert len(done) == 1 and done[0].endswith("end") and rest.startswith("def b")


def test_unknown_programs_are_refused():
    with pytest.raises(UnknownProgramError, match="not ur-rtde"):
        ControlProgram.parse("def other():\nend\n")
    with pytest.raises(UnknownProgramError, match="markers"):
        ControlProgram.parse("def rtde_control():\n  textmsg(1)\nend\n")


@pytest.fixture
def controller():
    return UrController(SimulatedCell(SimCellConfig(robot="ur10e", seed=3)))


def test_dashboard_state_machine(controller):
    c = controller
    assert handle_command(c, "robotmode") == "Robotmode: RUNNING"
    assert handle_command(c, "PolyscopeVersion").startswith("URSoftware 5.11")
    c.inject_fault("protective_stop")
    assert handle_command(c, "safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    assert handle_command(c, "unlock protective stop").startswith("Cannot unlock")  # within 5 s
    c.cell.advance_time(5.1)
    assert handle_command(c, "unlock protective stop") == "Protective stop releasing"
    assert handle_command(c, "safetymode") == "Safetymode: NORMAL"
    c.remote_control = False
    assert handle_command(c, "power off") == NOT_REMOTE
    assert handle_command(c, "is in remote control") == "false"
    c.remote_control = True
    assert handle_command(c, "power off") == "Powering off"
    assert handle_command(c, "robotmode") == "Robotmode: POWER_OFF"
    assert handle_command(c, "power on") == "Powering on"
    assert handle_command(c, "brake release") == "Brake releasing"
    assert handle_command(c, "robotmode") == "Robotmode: RUNNING"
    assert handle_command(c, "stop") == "Stopped"
    assert handle_command(c, "no such command").startswith("could not understand")


def test_emergency_stop_needs_release_and_power(controller):
    c = controller
    c.inject_fault("emergency_stop")
    assert c.safety_status_bits() & (1 << 7)
    assert handle_command(c, "power on").startswith("Failed")
    c.release_emergency_stop()
    assert handle_command(c, "power on") == "Powering on"
    handle_command(c, "brake release")
    assert c.robot_mode_name == "RUNNING" and c.safety_mode_name == "NORMAL"
    with pytest.raises(ValueError, match="unknown fault"):
        c.inject_fault("meteor")


def test_a_coupled_robots_controller_speaks_its_own_joints_and_moves_the_kinematic_arm():
    """The simulated LR Mate's controller reports and takes FANUC's joints (J3 = -q2 - q3, the forearm against
    the horizontal); the arm it commands is the kinematic one; a target beyond an interaction limit is refused."""
    c = UrController(SimulatedCell(SimCellConfig(robot="lrmate200id", seed=1, geometric_errors=False)))
    coupling = c.coupling
    assert coupling is not None and coupling.describe() == "kinematic q3 = -J2 - J3"
    q_kinematic = np.array([0.1, 0.3, -0.5, 0.2, -0.8, 0.4])
    c.q_cmd = q_kinematic
    c.tick(c.period_s)
    reported = np.asarray(c.output_value("actual_q"))
    np.testing.assert_allclose(reported, coupling.to_controller(q_kinematic[None])[0], atol=1e-5)
    assert reported[2] == pytest.approx(-0.3 + 0.5, abs=1e-5)  # J3 = -(q2 + q3): the forearm's elevation
    np.testing.assert_allclose(c.cell.encoder_joints(), q_kinematic, atol=1e-5)  # the arm: kinematic
    target_wire = np.array([0.0, 0.4, 0.1, 0.0, -0.5, 0.0])
    np.testing.assert_allclose(c._checked_joints(target_wire), [0.0, 0.4, -0.5, 0.0, -0.5, 0.0])
    c.coupling = JointCoupling(
        coupling.kinematic_from_controller, (CouplingLimit(np.array([0, 1, 1, 0, 0, 0.0]), -1.0, 0.4),)
    )
    with pytest.raises(ValueError, match="interaction limits"):
        c._checked_joints(target_wire)  # J2 + J3 = 0.5 rad > 0.4
