"""The fake controller's output packages (fakes.rtde_output): the bytes of every variable's value of the moment,
the fixed and unmodelled ones packed in once, through changes of joints, speeds, modes, registers and IO."""

from __future__ import annotations

import numpy as np
import pytest

from fakes import rtde_wire as w
from fakes.cell import SimCellConfig, SimulatedCell
from fakes.rtde_output import OutputPacker
from fakes.ur_controller import UrController
from fakes.ur_modes import POWER_OFF, PROTECTIVE_STOP

# what ur-rtde 1.6's receive interface asks for, with registers and bits of both sides (scalars, vectors,
# modelled, fixed and unmodelled variables, interleaved)
NAMES = [
    "timestamp", "target_q", "target_qd", "target_qdd", "target_current", "actual_q", "actual_qd",
    "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
    "actual_digital_input_bits", "joint_temperatures", "actual_execution_time", "robot_mode", "joint_mode",
    "safety_mode", "actual_tool_accelerometer", "speed_scaling", "actual_main_voltage", "actual_digital_output_bits",
    "runtime_state", "standard_analog_output0", "robot_status_bits", "safety_status_bits", "payload", "payload_cog",
    "payload_inertia", "output_int_register_2", "output_double_register_13", "input_int_register_5",
    "input_double_register_7", "input_bit_register_70", "output_bit_register_65", "input_bit_registers0_to_31",
]  # fmt: skip


@pytest.fixture(scope="module")
def controller() -> UrController:
    return UrController(SimulatedCell(SimCellConfig(robot="ur10e")))


def _plain_package(controller: UrController, recipe: w.Recipe) -> bytes:
    """The package as Recipe.pack makes it of every variable's current value."""
    return bytes([recipe.recipe_id]) + recipe.pack([controller.output_value(name) for name in recipe.names])


def test_packages_are_the_bytes_of_every_variables_current_value(controller):
    recipe = w.Recipe.build(7, NAMES, [w.output_type(n) or "" for n in NAMES])
    sources = [controller._output_source(name) for name in NAMES]
    packer = OutputPacker(recipe, [g for g, _ in sources], [fixed for _, fixed in sources])
    fixed = {name for name, (_, is_fixed) in zip(NAMES, sources, strict=True) if is_fixed}
    assert fixed == {
        "target_qdd", "target_current", "actual_TCP_force", "actual_digital_input_bits", "actual_execution_time",
        "actual_tool_accelerometer", "actual_main_voltage", "payload_inertia", "output_bit_register_65",
    }  # fmt: skip

    def change_state(step: int) -> None:
        c = controller
        # the cell's clock moves on (in `hil sim` a listener of the clock beside the tick), the encoders read
        c.cell.advance_timer(c.period_s)
        c.tick(c.period_s)
        if step == 1:
            c.q_cmd = c.q_cmd + np.array([0.1, -0.05, 0.02, 0.0, 0.3, -0.2])
            c.qd_cmd = np.array([0.2, -0.1, 0.0, 0.05, 0.0, -0.3])
        elif step == 2:
            c.T_flange_tcp = np.array([[1, 0, 0, 0.01], [0, 1, 0, 0.02], [0, 0, 1, 0.15], [0, 0, 0, 1.0]])
            c.out_int[2], c.out_double[13], c.in_int[5], c.in_double[7] = -4, 2.5, 9, -0.125
        elif step == 3:
            c.in_bits |= (1 << 70) | 0b101
            c.digital_out, c.analog_out[0], c.speed_slider = 0b1001, 0.75, 0.4
            c.payload = (1.2, (0.0, 0.01, 0.05))
        elif step == 4:
            c.safety_mode, c.robot_mode = PROTECTIVE_STOP, POWER_OFF
            c.qd_cmd = np.zeros(6)

    seen = set()
    for step in range(6):
        change_state(step)
        package = packer.package()
        assert package == _plain_package(controller, recipe)
        seen.add(package[1:])
        values = recipe.unpack(package[1:])
        assert values["timestamp"] == controller.cell.time_s
    assert len(seen) == 6  # every state its own package: nothing read once that may change
    assert values["output_int_register_2"] == -4 and values["input_bit_register_70"] is True
    assert values["payload"] == 1.2 and values["safety_mode"] == PROTECTIVE_STOP
    assert values["actual_main_voltage"] == 48.0 and values["target_qdd"] == (0.0,) * 6
