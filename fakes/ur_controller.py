"""Fake Universal Robots controller that the unmodified ur-rtde client drives over loopback.

Servers: RTDE (30004), Dashboard (29999) and the script ports (30001-30003, which accept programs).
It recognises ur-rtde's uploaded control program and re-implements its register handshake in Python
(`ControlProgram` gives the register offset, realtime commands and injected paths). Motion uses the
nominal model (the controller's beliefs); the joints it commands go to the simulated cell, and
`actual_q` comes back from the cell's encoders. The caller's clock calls `tick(dt)` every cycle.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from fakes import rtde_wire as w
from fakes.fast_kinematics import ArmKinematics
from fakes.rtde_output import OutputPacker
from fakes.ur_dashboard import serve_dashboard
from fakes.ur_modes import (
    IDLE,
    NORMAL,
    PAUSED,
    PERSONALITIES,
    PLAYING,
    POWER_OFF,
    PROTECTIVE_STOP,
    ROBOT_EMERGENCY_STOP,
    ROBOT_MODES,
    RUNNING,
    SAFETY_MODES,
    STOPPED,
)
from fakes.ur_motion import Motion, StopMove
from fakes.ur_primary import PrimaryClients, ProgramRunner, runtime_exception
from fakes.ur_program import ScriptError, UserProgram
from fakes.ur_rtde_server import RtdeConnection
from fakes.ur_script import ControlProgram, UnknownProgramError, read_programs
from fakes.ur_script_runtime import ScriptRuntime
from hil.geometry.collision import CellBodies
from hil.geometry.robots import robot_body

if TYPE_CHECKING:
    from fakes.cell import SimulatedCell

log = logging.getLogger(__name__)

RTDE_PORT, DASHBOARD_PORT, PRIMARY_PORT, SECONDARY_PORT, REALTIME_PORT = 30004, 29999, 30001, 30002, 30003

PROTECTIVE_STOP_UNLOCK_DELAY_S = 5.0  # simulated seconds before a protective stop may be unlocked


def default_personality(robot: str) -> str:
    """e-Series robots (ur5e, ur10e, ...) get the e-Series personality, the others CB3."""
    return "eseries" if robot.lower().rstrip().endswith("e") else "cb3"


@dataclass
class PlannedFault:
    """A fault armed to fire during a future move (or at once), see `UrController.inject_fault`."""

    kind: str
    at_move: int  # absolute move number (1-based) it fires in; 0 = at once
    fraction: float  # of the move's duration
    duration_s: float  # for stalls and latency spikes (wall seconds); a reader lag's delay


# RTDE outputs this controller models with values that never change (`_output_getters`)
FIXED_OUTPUTS = frozenset(
    {"actual_main_voltage", "actual_robot_voltage", "actual_tool_accelerometer", "actual_execution_time"}
)

FAULT_KINDS = (
    "protective_stop",
    "emergency_stop",
    "drop_rtde",
    "stop_script",
    "stall",
    "latency",
    "reader_lag",
)


class UrController(ScriptRuntime):
    """One fake UR controller bound to one loopback address and one simulated cell."""

    def __init__(
        self,
        cell: SimulatedCell,
        host: str = "127.0.0.1",
        personality: str | None = None,
        script_start_delay_s: float = 0.05,
        remote_control: bool = True,
        powered: bool = True,
        ports: dict[str, int] | None = None,
    ):
        self.cell = cell
        self.model = cell.nominal
        # the joints on the wire are the controller's (a FANUC-like J3 against the horizontal); inside, the
        # controller works in the model's kinematic joints, as the simulated arm does
        self.coupling = cell.coupling
        # the arm's own body (its robot file's capsules): a move into itself ends in a protective stop
        self.arm_body = (
            CellBodies(robot_body(cell.config.robot), margin_m=0.0, self_margin_m=0.0)
            if cell.config.self_collision_stop
            else None
        )
        self.host = host
        name = personality or default_personality(cell.config.robot)
        if name not in PERSONALITIES:
            raise ValueError(f"unknown personality '{name}'; choose one of {', '.join(PERSONALITIES)}")
        self.personality = PERSONALITIES[name]
        self.period_s = 1.0 / self.personality.frequency_hz
        self.ports = {
            "rtde": RTDE_PORT,
            "dashboard": DASHBOARD_PORT,
            "primary": PRIMARY_PORT,
            "secondary": SECONDARY_PORT,
            "realtime": REALTIME_PORT,
            **(ports or {}),
        }
        self.script_start_delay_s = script_start_delay_s
        self.remote_control = remote_control
        self.serial_number = "20235500" + f"{cell.config.seed % 1000:03d}"
        self.robot_model_name = cell.config.robot.upper().rstrip("E")
        self.loaded_program = ""
        self._servers: list[asyncio.AbstractServer] = []
        self._rtde_server: asyncio.AbstractServer | None = None
        self._tasks: set[asyncio.Task] = set()
        self._rtde: list[RtdeConnection] = []
        self._input_owner: dict[str, RtdeConnection] = {}
        self._output_recipe_counter = 0
        # robot and safety state
        self.robot_mode = RUNNING if powered else POWER_OFF
        self.safety_mode = NORMAL
        self.runtime_state = STOPPED
        self._protective_stop_time = -1e9
        # registers and IO
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.in_bits = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.digital_out = 0
        self.analog_out = [0.0, 0.0]
        self.speed_slider = 1.0
        self.payload = (0.0, (0.0, 0.0, 0.0))
        self._last_ii0_write = time.monotonic()
        # program and motion
        self.program: ControlProgram | None = None
        self.user_program: ProgramRunner | None = None  # a URScript program sent to a script port, running
        self.primary = PrimaryClients()
        self.programs_received = 0
        self.refused_programs: list[str] = []
        self.last_program_text = ""
        self._start_at: float | None = None
        self._executing = False
        self._blocking: str | None = None  # the sync command waiting for its motion to end
        self.motion: Motion | None = None
        self._motion_fresh = False
        self._motion_is_async = False
        self._async_op_id = 0
        self._async_counter = 0
        self._watchdog_period_s = 0.0
        self.q_cmd = np.asarray(cell.commanded_q, float)
        self.qd_cmd = np.zeros(6)
        self.actual_q = np.asarray(cell.encoder_joints(), float)
        self._q_history: collections.deque[np.ndarray] = collections.deque(maxlen=1000)
        self.T_flange_tcp = np.eye(4)
        self.moves_started = 0
        self.last_move: dict = {}
        self._move_started_at = 0.0
        self._still_ticks = 0
        self._init_faults()
        self.tick_count = 0
        self.kin = ArmKinematics(self.model)
        self._outputs = self._output_getters()
        self._target_pose_cache: tuple = (None, None)
        self._actual_pose_cache: tuple = (None, None)

    def _init_faults(self) -> None:
        """No fault armed, none active, none logged yet."""
        self._planned: list[PlannedFault] = []
        self._stall_until = 0.0
        self._latency_until = 0.0
        self._held: list[tuple[RtdeConnection, bytes]] = []  # data packages a latency spike holds back
        self._reader_lag_s = 0.0  # how late a reader lag delivers each package to read-only clients (0: none)
        # packages a reader lag delays: (when due, client, package), in the order they were made
        self._lagged: collections.deque[tuple[float, RtdeConnection, bytes]] = collections.deque()
        self.fault_log: list[dict] = []

    # ---------------------------------------------------------------- servers
    async def start(self) -> None:
        """Listen on every port of this controller's address."""
        specs = [
            (self.ports["rtde"], self._serve_rtde),
            (self.ports["dashboard"], self._serve_dashboard),
            (self.ports["primary"], self._serve_primary),
            (self.ports["secondary"], self._serve_primary),
            (self.ports["realtime"], self._serve_script),
        ]
        try:
            for port, handler in specs:
                self._servers.append(await asyncio.start_server(handler, self.host, port, reuse_address=True))
            self._rtde_server = self._servers[0]
        except OSError:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop listening and drop every client."""
        for server in self._servers:
            server.close()
        for conn in list(self._rtde):
            conn.abort()
        for task in list(self._tasks):
            task.cancel()
        for server in self._servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1.0)
        self._servers.clear()

    def _track_current_task(self) -> None:
        """Remember a client's handler task so `close()` can cancel it."""
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _serve_rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._track_current_task()
        _nodelay(writer)
        conn = RtdeConnection(self, reader, writer)
        self._rtde.append(conn)
        await conn.serve()

    async def _serve_dashboard(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._track_current_task()
        _nodelay(writer)
        await serve_dashboard(self, reader, writer)

    async def _serve_primary(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Primary and secondary ports: programs in, the version and robot messages out (fakes.ur_primary)."""
        self._track_current_task()
        await self.primary.serve(self, reader, writer)

    async def _serve_script(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Accept programs; complete ones are started, the client never reads anything back."""
        self._track_current_task()
        try:
            async for text in read_programs(reader, "script"):
                self.receive_program(text)
        except ConnectionError:
            pass
        finally:
            with contextlib.suppress(Exception):
                writer.close()

    # ---------------------------------------------------------------- RTDE bookkeeping
    def next_output_recipe_id(self) -> int:
        self._output_recipe_counter = self._output_recipe_counter % 255 + 1
        return self._output_recipe_counter

    def claim_inputs(self, conn: RtdeConnection, names: list[str]) -> set[str]:
        """Reserve input variables for a connection; returns the names another connection holds."""
        taken = {n for n in names if self._input_owner.get(n, conn) is not conn and not n.endswith("_mask")}
        if not taken:
            for n in names:
                self._input_owner[n] = conn
        return taken

    def rtde_disconnected(self, conn: RtdeConnection) -> None:
        if conn in self._rtde:
            self._rtde.remove(conn)
        for name in [n for n, c in self._input_owner.items() if c is conn]:
            del self._input_owner[name]

    def apply_inputs(self, values: dict[str, Any]) -> None:
        """Apply one client data package to registers and IO."""
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                index = int(name.rsplit("_", 1)[1])
                self.in_int[index] = int(value)
                if self.program is not None and index == self.program.offset:
                    self._last_ii0_write = time.monotonic()
            elif name.startswith("input_double_register_"):
                self.in_double[int(name.rsplit("_", 1)[1])] = float(value)
            elif name.startswith("input_bit_register_"):
                bit = int(name.rsplit("_", 1)[1])
                self.in_bits = self.in_bits | (1 << bit) if value else self.in_bits & ~(1 << bit)
        if "standard_digital_output_mask" in values:
            self._set_bits(
                0, values["standard_digital_output_mask"], values.get("standard_digital_output", 0)
            )
        if "configurable_digital_output_mask" in values:
            self._set_bits(
                8, values["configurable_digital_output_mask"], values.get("configurable_digital_output", 0)
            )
        if "tool_digital_output_mask" in values:
            self._set_bits(16, values["tool_digital_output_mask"], values.get("tool_digital_output", 0))
        if values.get("speed_slider_mask"):
            self.speed_slider = min(1.0, max(0.0, float(values.get("speed_slider_fraction", 1.0))))
        mask = values.get("standard_analog_output_mask", 0)
        for i in range(2):
            if mask & (1 << i) and f"standard_analog_output_{i}" in values:
                self.analog_out[i] = float(values[f"standard_analog_output_{i}"])

    def _set_bits(self, shift: int, mask: int, value: int) -> None:
        mask, value = int(mask) << shift, int(value) << shift
        self.digital_out = (self.digital_out & ~mask) | (value & mask)

    # ---------------------------------------------------------------- state names
    @property
    def robot_mode_name(self) -> str:
        return ROBOT_MODES.get(self.robot_mode, "UNKNOWN")

    @property
    def safety_mode_name(self) -> str:
        return SAFETY_MODES.get(self.safety_mode, "UNDEFINED_SAFETY_MODE")

    @property
    def program_running(self) -> bool:
        return self.runtime_state == PLAYING

    @property
    def program_state_name(self) -> str:
        return {PLAYING: "PLAYING", PAUSED: "PAUSED"}.get(self.runtime_state, "STOPPED")

    @property
    def program_name(self) -> str:
        return f"{self.program.name}.urp" if self.program else "<unnamed>"

    def robot_status_bits(self) -> int:
        powered = self.robot_mode in (4, 5, 6, RUNNING)
        return int(powered) | (int(self.program_running) << 1) | (int(powered) << 3)

    def safety_status_bits(self) -> int:
        bits = {NORMAL: 1 << 0, PROTECTIVE_STOP: 1 << 2, ROBOT_EMERGENCY_STOP: (1 << 6) | (1 << 7)}
        value = bits.get(self.safety_mode, 0)
        if self.safety_mode != NORMAL:
            value |= 1 << 10
        return value

    # ---------------------------------------------------------------- dashboard actions
    def dashboard_power_on(self) -> str:
        if self.safety_mode == ROBOT_EMERGENCY_STOP:
            return "Failed to execute: power on"  # [A] wording
        if self.robot_mode == POWER_OFF:
            self.robot_mode = IDLE
        return "Powering on"

    def dashboard_power_off(self) -> None:
        self._halt_program(STOPPED)
        self.robot_mode = POWER_OFF

    def dashboard_brake_release(self) -> str:
        if self.robot_mode == IDLE and self.safety_mode == NORMAL:
            self.robot_mode = RUNNING
        return "Brake releasing"

    def dashboard_unlock_protective_stop(self) -> str:
        if self.safety_mode == PROTECTIVE_STOP:
            if self.cell.time_s - self._protective_stop_time < PROTECTIVE_STOP_UNLOCK_DELAY_S:
                return (
                    "Cannot unlock protective stop until 5s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                )
            self.safety_mode = NORMAL
        return "Protective stop releasing"

    def dashboard_restart_safety(self) -> str:
        if self.safety_mode in (PROTECTIVE_STOP, 9):
            self.safety_mode = NORMAL
            self.robot_mode = POWER_OFF
            self._halt_program(STOPPED)
        return "Restarting safety"

    def dashboard_play(self) -> str:
        if self.program is None or self.safety_mode != NORMAL or self.robot_mode != RUNNING:
            return "Failed to execute: play"
        if self.runtime_state == PAUSED:
            self.runtime_state = PLAYING
            self._script_reset_loop()
        elif self.runtime_state == STOPPED:
            self._start_program_now()
        return "Starting program"

    def dashboard_stop(self) -> None:
        self._halt_program(STOPPED)

    def dashboard_pause(self) -> str:
        if self.runtime_state != PLAYING:
            return "Failed to execute: pause"
        self._halt_program(PAUSED)
        return "Pausing program"

    # ---------------------------------------------------------------- programs
    def receive_program(self, text: str) -> None:
        """A complete program arrived on a script port: start it if it is ur-rtde's control program."""
        self.programs_received += 1
        self.last_program_text = text
        log.debug("program received (%d bytes)", len(text))
        user: UserProgram | None = None
        try:
            program: ControlProgram | None = ControlProgram.parse(text)
        except UnknownProgramError:
            program = None
            try:
                user = UserProgram(text)
            except ScriptError as exc:
                log.error("script error in a program sent to the controller: %s", exc)
                self.refused_programs.append(f"script error: {exc}")
                self.primary.broadcast(runtime_exception(exc), f"runtime exception: {exc}")
                return
        if self.personality.is_eseries and not self.remote_control:
            log.error("refused a program: the robot is in local mode")
            self.refused_programs.append("local mode")
            return
        if self.robot_mode != RUNNING or self.safety_mode != NORMAL:
            log.warning(
                "program not started: robot mode %s, safety mode %s",
                self.robot_mode_name,
                self.safety_mode_name,
            )
            self.refused_programs.append(f"robot {self.robot_mode_name} / safety {self.safety_mode_name}")
            return
        self._halt_program(STOPPED)
        if user is not None:  # a user program: it replaces ur-rtde's control program and runs at once
            self.program = None
            self.user_program = ProgramRunner(self, user)
            self.runtime_state = PLAYING
            return
        self.program = program
        self._start_at = time.monotonic() + self.script_start_delay_s

    def _start_program_now(self) -> None:
        self._start_at = None
        self._watchdog_period_s = 0.0  # a new program starts without an RTDE watchdog
        self.runtime_state = PLAYING
        self._script_reset_loop()

    def _script_reset_loop(self) -> None:
        """What the control script does on (re)start: async progress finished, then ready."""
        self._executing = False
        self._blocking = None
        self._async_register(-1)
        self._oi(0, 1)

    def _halt_program(self, new_state: int) -> None:
        """Stop or pause the program. The script no longer runs, so it writes no register: an async
        move cut short stays "running" in the progress register [A], as on a stopped real program."""
        self._start_at = None
        self.user_program = None
        if self.runtime_state in (PLAYING, PAUSED):
            self.runtime_state = new_state
        if new_state == STOPPED:
            self.runtime_state = STOPPED
        self._blocking = None
        self._motion_is_async = False
        if self.motion is not None and not isinstance(self.motion, StopMove):
            self._stop_motion(decel=None)

    # ---------------------------------------------------------------- clock
    def tick(self, dt: float) -> None:
        """One controller cycle of dt simulated seconds: script, motion, cell, then data out."""
        self.tick_count += 1
        now = time.monotonic()
        if self._start_at is not None and now >= self._start_at:
            self._start_program_now()
        if self.runtime_state == PLAYING and self.program is not None:
            self._check_watchdog(now)
            self._script_cycle()
        elif self.runtime_state == PLAYING and self.user_program is not None:
            self.user_program.cycle()
            if self.user_program.done:
                self.user_program = None
                self.runtime_state = STOPPED
        self._advance_motion(dt)
        if self.cell.set_commanded_joints(self.q_cmd):  # the arm moved: time passes for the physics
            self.cell.advance_physics(dt)
        self.actual_q = np.asarray(self.cell.encoder_joints(), float)
        self._q_history.appendleft(self.actual_q)
        self._publish(now)

    def _check_watchdog(self, now: float) -> None:
        if self._watchdog_period_s > 0 and now - self._last_ii0_write > self._watchdog_period_s:
            log.warning(
                "RTDE watchdog: no command register write for %.3f s; stopping", now - self._last_ii0_write
            )
            self._watchdog_period_s = 0.0
            self._halt_program(STOPPED)

    # ---------------------------------------------------------------- faults
    def inject_fault(
        self, kind: str, at_move: int | None = None, fraction: float = 0.5, duration_s: float = 3.0
    ) -> dict:
        """Arm a fault: at once (at_move None) or `fraction` of the way through the at_move-th next move."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault '{kind}'; choose one of {', '.join(FAULT_KINDS)}")
        if at_move is None:
            self._fire(PlannedFault(kind, 0, 0.0, duration_s))
            return {"fired": True}
        if at_move < 1:
            raise ValueError("at_move counts moves from now: 1 is the next move")
        fault = PlannedFault(kind, self.moves_started + int(at_move), float(fraction), float(duration_s))
        self._planned.append(fault)
        return {"armed": True, "move": fault.at_move}

    def _fire_planned_faults(self, motion: Motion) -> None:
        if not self._planned:
            return
        elapsed = self.cell.time_s - self._move_started_at
        duration = getattr(motion, "duration", 0.0)
        for fault in list(self._planned):
            if fault.at_move == self.moves_started and elapsed >= fault.fraction * duration:
                self._planned.remove(fault)
                self._fire(fault)

    def _fire(self, fault: PlannedFault) -> None:
        log.warning("fault injected: %s", fault.kind)
        self.fault_log.append({"kind": fault.kind, "time_s": self.cell.time_s, "move": self.moves_started})
        if fault.kind == "protective_stop":
            self.trigger_protective_stop("injected")
        elif fault.kind == "emergency_stop":
            self.safety_mode = ROBOT_EMERGENCY_STOP
            self.motion = None
            self.qd_cmd = np.zeros(6)
            self._halt_program(STOPPED)
            self.robot_mode = POWER_OFF
        elif fault.kind == "drop_rtde":
            self._rtde_outage(fault.duration_s)
        elif fault.kind == "stop_script":
            self._halt_program(STOPPED)
        elif fault.kind == "stall":
            self._stall_until = time.monotonic() + fault.duration_s
        elif fault.kind == "latency":
            self._latency_until = time.monotonic() + fault.duration_s
        elif fault.kind == "reader_lag":
            self._reader_lag_s = fault.duration_s

    def _rtde_outage(self, duration_s: float) -> None:
        """Drop every RTDE client and refuse new ones for duration_s (a network outage)."""
        for conn in list(self._rtde):
            conn.abort()
        server = self._rtde_server
        if server is None:
            return
        server.close()
        self._rtde_server = None

        async def reopen() -> None:
            await asyncio.sleep(duration_s)
            try:
                self._rtde_server = await asyncio.start_server(
                    self._serve_rtde, self.host, self.ports["rtde"], reuse_address=True
                )
                self._servers.append(self._rtde_server)
            except OSError as exc:
                log.error("could not reopen the RTDE port after the outage: %s", exc)

        task = asyncio.get_running_loop().create_task(reopen())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def trigger_protective_stop(self, why: str) -> None:
        log.warning("protective stop (%s)", why)
        self.safety_mode = PROTECTIVE_STOP
        self._protective_stop_time = self.cell.time_s
        self.motion = None
        self.qd_cmd = np.zeros(6)
        if self.runtime_state == PLAYING:
            self.runtime_state = PAUSED
        self._blocking = None

    def release_emergency_stop(self) -> None:
        """The operator releases the e-stop button; the arm stays powered off until power on."""
        if self.safety_mode == ROBOT_EMERGENCY_STOP:
            self.safety_mode = NORMAL

    def clear_faults(self) -> None:
        self._planned.clear()
        self._stall_until = self._latency_until = 0.0
        self._reader_lag_s = 0.0  # what is already late still arrives, in order

    # ---------------------------------------------------------------- data out
    def _publish(self, now: float) -> None:
        if not self._rtde:
            return
        if now < self._stall_until:
            return
        holding = now < self._latency_until
        if not holding and self._held:
            for conn, payload in self._held:
                conn.send_package(payload)
            self._held.clear()
        for conn in self._rtde:
            if not conn.streaming or self.tick_count % conn.output_every_n_ticks:
                continue
            if conn.packer is None:
                recipe = conn.output_recipe
                assert recipe is not None  # a connection streams only once it has an output recipe
                sources = [self._output_source(name) for name in recipe.names]
                conn.packer = OutputPacker(recipe, [g for g, _ in sources], [fixed for _, fixed in sources])
            payload = conn.packer.package()
            if holding:
                self._held.append((conn, payload))
            elif not conn.input_recipes and (self._reader_lag_s > 0 or self._lagged):
                self._send_late(conn, payload, now)
            else:
                conn.send_package(payload)
        self._deliver_late(now)

    def _send_late(self, conn: RtdeConnection, payload: bytes, now: float) -> None:
        """A reader lag: a client that only reads (no input recipe, like ur-rtde's receive interface) gets
        each package `_reader_lag_s` after it was made, as from a loaded PC whose receive thread runs behind,
        while the control interface's stream keeps time. Packages stay in order; after the lag ends, new
        ones queue behind the late ones until those are out."""
        due = now + self._reader_lag_s
        if self._lagged:
            due = max(due, self._lagged[-1][0])
        self._lagged.append((due, conn, payload))

    def _deliver_late(self, now: float) -> None:
        while self._lagged and self._lagged[0][0] <= now:
            _, conn, payload = self._lagged.popleft()
            conn.send_package(payload)

    def getter(self, name: str) -> Any:
        """A zero-argument function returning the current value of one RTDE output variable."""
        return self._output_source(name)[0]

    def _output_source(self, name: str) -> tuple[Any, bool]:
        """The getter of one RTDE output variable, and whether its value is fixed (held constant, or not
        modelled: zeros), so that a package may carry the value read once."""
        getter = self._outputs.get(name)
        if getter is not None:
            return getter, name in FIXED_OUTPUTS
        for prefix, table in (
            ("output_int_register_", self.out_int),
            ("output_double_register_", self.out_double),
            ("input_int_register_", self.in_int),
            ("input_double_register_", self.in_double),
        ):
            if name.startswith(prefix):
                index = int(name[len(prefix) :])
                return (lambda table=table, index=index: table[index]), False
        if name.startswith("input_bit_register_"):
            bit = int(name.rsplit("_", 1)[1])
            return (lambda: bool(self.in_bits >> bit & 1)), False
        zero = _zero(w.output_type(name) or "DOUBLE")
        return (lambda: zero), True

    def output_value(self, name: str) -> Any:
        """Current value of one RTDE output variable."""
        return self.getter(name)()

    def _output_getters(self) -> dict[str, Any]:
        """Name -> zero-argument getter for every modelled output; the rest read as zeros."""
        return {
            "timestamp": lambda: self.cell.time_s,
            "actual_q": lambda: self.joints_out(self.actual_q),
            "target_q": lambda: self.joints_out(self.q_cmd),
            "actual_qd": lambda: self.joints_out(self.qd_cmd),
            "target_qd": lambda: self.joints_out(self.qd_cmd),
            "actual_TCP_pose": self._actual_tcp_pose,
            "target_TCP_pose": self._target_tcp_pose,
            "actual_TCP_speed": self._tcp_speed,
            "target_TCP_speed": self._tcp_speed,
            "robot_mode": lambda: self.robot_mode,
            "safety_mode": lambda: self.safety_mode,
            "safety_status": lambda: self.safety_mode,
            "runtime_state": lambda: self.runtime_state,
            "robot_status_bits": self.robot_status_bits,
            "safety_status_bits": self.safety_status_bits,
            "joint_mode": lambda: [253] * 6 if self.robot_mode == RUNNING else [236] * 6,
            "joint_temperatures": lambda: [float(self.cell.structure_temperature_c())] * 6,  # the arm's
            "speed_scaling": lambda: self.speed_slider,
            "target_speed_fraction": lambda: self.speed_slider,
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 48.0,
            "actual_tool_accelerometer": lambda: (0.0, 0.0, 9.81),
            "actual_digital_output_bits": lambda: self.digital_out,
            "standard_analog_output0": lambda: self.analog_out[0],
            "standard_analog_output1": lambda: self.analog_out[1],
            "payload": lambda: self.payload[0],
            "payload_cog": lambda: self.payload[1],
            "actual_execution_time": lambda: 0.2,
            "input_bit_registers0_to_31": lambda: self.in_bits & 0xFFFFFFFF,
            "input_bit_registers32_to_63": lambda: (self.in_bits >> 32) & 0xFFFFFFFF,
        }

    def _actual_tcp_pose(self) -> list[float]:
        # keyed on the joints, not the tick: an arm standing still (most ticks) reads the same encoders, and
        # the forward kinematics was a quarter of an idle cell's CPU
        key = (self.actual_q.tobytes(), self.T_flange_tcp.tobytes())
        if self._actual_pose_cache[0] != key:
            self._actual_pose_cache = (key, self._tcp_pose(self.actual_q, self.T_flange_tcp))
        return self._actual_pose_cache[1]

    def _target_tcp_pose(self) -> list[float]:
        key = (self.q_cmd.tobytes(), self.T_flange_tcp.tobytes())
        if self._target_pose_cache[0] != key:
            self._target_pose_cache = (key, self._tcp_pose(self.q_cmd, self.T_flange_tcp))
        return self._target_pose_cache[1]

    def _tcp_speed(self) -> Any:
        if not self.qd_cmd.any():  # the array's own any: twice a package, np.any's dispatch cost more
            return (0.0,) * 6
        return self.kin.jacobian(self.q_cmd, self.T_flange_tcp[:3, 3]) @ self.qd_cmd

    # ---------------------------------------------------------------- introspection
    def state(self) -> dict:
        """JSON-friendly snapshot for the control channel."""
        return {
            "personality": self.personality.name,
            "version": ".".join(map(str, self.personality.version)),
            "robot_mode": self.robot_mode_name,
            "safety_mode": self.safety_mode_name,
            "runtime_state": self.runtime_state,
            "program": self.program.name if self.program else None,
            "user_program_running": self.user_program is not None,
            "primary_messages": list(self.primary.messages),
            "programs_received": self.programs_received,
            "refused_programs": list(self.refused_programs),
            "moves_started": self.moves_started,
            "last_move": dict(self.last_move),
            "moving": self.motion is not None,
            "commanded_q": self.q_cmd.tolist(),
            "T_flange_tcp": self.T_flange_tcp.tolist(),
            "rtde_clients": len(self._rtde),
            "faults": list(self.fault_log),
            "remote_control": self.remote_control,
            "ticks": self.tick_count,
        }


def _zero(type_name: str) -> Any:
    width = w.TYPE_WIDTH[type_name]
    scalar = 0.0 if "D" in type_name else 0
    if type_name == "BOOL":
        scalar = False
    return scalar if width == 1 else [scalar] * width


def _nodelay(writer: asyncio.StreamWriter) -> None:
    import socket

    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
