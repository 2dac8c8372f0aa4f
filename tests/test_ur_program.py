"""The fake controller's URScript runner (fakes.ur_program) without sockets: compile errors with their line and
column, and the actions a program yields (its motions, waits and messages) on a controller of the nominal UR10."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from fakes.ur_primary import (
    MESSAGE_RUNTIME_EXCEPTION,
    parse_robot_messages,
    runtime_exception,
    version_message,
)
from fakes.ur_program import Halt, Message, Move, ScriptError, UserProgram, Wait
from hil.geometry.ik import solve_ik
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.robots import get_robot
from hil.geometry.se3 import pose_to_transform

UR10 = get_robot("ur10")
HOME = np.array([0.1, -1.6, 1.5, -1.4, -1.57, 0.2])


class NominalArm:
    """A controller as the program sees it: the nominal UR10, commanded joints that follow every move."""

    def __init__(self) -> None:
        self.q_cmd = HOME.copy()
        self.T_flange_tcp = np.eye(4)
        self.payload = (0.0, (0.0, 0.0, 0.0))
        self.digital_out = 0

    def _ik(self, T_base_flange, q_seed=None):
        seed = self.q_cmd if q_seed is None else np.asarray(q_seed, float)
        res = solve_ik(UR10, T_base_flange[None], q_seed=seed[None], q_near=seed)
        return res.q[0] if res.success[0] else None

    def flange_pose_of(self, q):
        return forward_kinematics(UR10, np.asarray(q, float)[None])[0]

    def joints_in(self, q_wire):  # a UR reports its kinematic joints
        return np.asarray(q_wire, float)

    def joints_out(self, q):
        return np.asarray(q, float)


def run(text: str) -> tuple[list, NominalArm]:
    """Every action of the program, the arm at each move's target before the next statement runs."""
    arm = NominalArm()
    actions = []
    for action in UserProgram(text).run(arm):
        actions.append(action)
        if isinstance(action, Move):
            arm.q_cmd = action.target if action.kind == "joint" else arm._ik(action.target)
    return actions, arm


def test_unsupported_function_is_a_script_error_at_its_line_and_column():
    with pytest.raises(ScriptError) as err:
        UserProgram(
            'def p():\n  movej([0, -1.57, 0, 0, 0, 0])\n  x = 1 + socket_read_ascii_float(6, "s")\nend\n'
        )
    assert (err.value.line, err.value.column) == (3, 11)
    assert "socket_read_ascii_float" in err.value.message
    with pytest.raises(ScriptError, match="missing 'end'"):
        UserProgram("def p():\n  while True:\n    sync()\nend\n")


def test_loops_branches_functions_and_poses_run_in_order():
    program = """def job():
  set_gravity([0.0, 0.0, 9.82])
  $ 1 "Robot Program"
  def lift(pose, dz):
    return pose_trans(pose, p[0, 0, -dz, 0, 0, 0])
  end
  global start = get_forward_kin()
  i = 0
  while (i < 3):
    if i == 1:
      textmsg("middle ", i)
    elif i == 2:
      sleep(0.25)
    else:
      set_standard_digital_out(2, True)
    end
    movel(lift(start, 0.01 * (i + 1)), a=1.2, v=0.25, r=0.001)
    i = i + 1
  end
  movej(get_inverse_kin(start, qnear=[0.1, -1.6, 1.5, -1.4, -1.57, 0.2]))
  halt
  movej([0, 0, 0, 0, 0, 0])
end
"""
    with pytest.raises(Halt):
        run(program)
    arm = NominalArm()
    steps = UserProgram(program).run(arm)
    actions = []
    try:
        for action in steps:
            actions.append(action)
            if isinstance(action, Move):
                arm.q_cmd = action.target if action.kind == "joint" else arm._ik(action.target)
    except Halt:
        pass
    kinds = [type(a).__name__ for a in actions]
    assert kinds == ["Move", "Message", "Move", "Wait", "Move", "Move"]
    assert actions[1] == Message("middle 1")
    assert actions[3] == Wait(0.25)
    start = forward_kinematics(UR10, HOME[None])[0]
    for k, move in enumerate(a for a in actions[:5] if isinstance(a, Move)):
        assert move.kind == "linear" and move.speed == 0.25
        lifted = start @ pose_to_transform(np.array([0, 0, -0.01 * (k + 1), 0, 0, 0]))
        np.testing.assert_allclose(move.target, lifted, atol=1e-9)
    np.testing.assert_allclose(actions[-1].target, HOME, atol=1e-6)  # back on qnear's solution
    assert arm.digital_out == 1 << 2


def test_set_tcp_moves_the_flange_target():
    program = "def t():\n  set_tcp(p[0, 0, 0.1, 0, 0, 0])\n  movel(p[0.5, -0.3, 0.4, 0, 3.14159, 0])\nend\n"
    actions, _ = run(program)
    T_tcp = pose_to_transform(np.array([0.5, -0.3, 0.4, 0, 3.14159, 0]))
    np.testing.assert_allclose(actions[0].target[:3, 3], T_tcp[:3, 3] - 0.1 * T_tcp[:3, 2], atol=1e-12)


def test_primary_messages_frame_as_a_client_parses_them():
    exc = ScriptError(3, 11, "the fake controller does not run 'socket_open'")
    stream = version_message((5, 11, 0, 0)) + runtime_exception(exc)
    messages, rest = parse_robot_messages(stream + stream[:7])
    assert rest == stream[:7]  # a package cut short waits for its rest
    assert [kind for kind, _ in messages] == [3, MESSAGE_RUNTIME_EXCEPTION]
    name_len = messages[0][1][0]
    assert messages[0][1][1 : 1 + name_len] == b"URControl"
    assert struct.unpack(">BB", messages[0][1][1 + name_len : 3 + name_len]) == (5, 11)
    assert struct.unpack(">ii", messages[1][1][:8]) == (3, 11)
    assert messages[1][1][8:].endswith(b"'socket_open'")
