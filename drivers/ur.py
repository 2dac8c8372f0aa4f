"""Universal Robots driver on ur-rtde (the only module that imports it).

Moves are sent asynchronously and supervised from Python, so every failure surfaces as a typed error
within a bounded time: protective / emergency stop from the safety bits, program stopped from the
runtime state, frozen data from RTDE timestamps that stop advancing, timeouts from the trapezoid time.
State checks read one consistent snapshot of the receive stream. The control stream (async progress)
is a separate socket that may run packages ahead of it, so when the control stream reports a move's end
the driver waits for the receive stream to catch up before it judges the outcome.
Connections are probed with plain sockets before the ur-rtde constructors run (those block without a
timeout and hold Python's global lock), rebuilt on `recover()`, and torn down control-first.
"""

from __future__ import annotations

import ctypes
import logging
import math
import socket
import struct
import threading
import time
import weakref
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.geometry.se3 import pose_to_transform, transform_to_pose
from hil.instruments.robot import (
    EmergencyStopError,
    ProgramNotRunningError,
    ProtectiveStopError,
    RobotConfigError,
    RobotConnectionError,
    RobotError,
    RobotNotReadyError,
    RobotState,
    RobotTimeoutError,
    StaleDataError,
)

log = logging.getLogger(__name__)

# ur-rtde's receive threads (one per receive and per control interface) poll their socket in a loop that sleeps
# 100 us when no packet waits: with Linux's default timer slack of 50 us each wakes about 2 700 times a
# second, some 7 % of a core per thread for as long as the robot is connected, whether it moves or not. A
# thread inherits its creator's timer slack, so the interfaces are built with a coarser one: each poll may
# then sleep up to this much longer, half the controller's cycle between packets: 1 ms of an e-Series' 2 ms, 4 ms
# of a CB3's 8 ms (a packet that waited is read at the next wake, and the loop reads on without sleeping while
# packets wait). RECEIVE_TIMER_SLACK_NS, the finer, is also the slack of a controller whose version says nothing.
RECEIVE_TIMER_SLACK_NS = 1_000_000
CB3_RECEIVE_TIMER_SLACK_NS = 4_000_000
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30


def receive_timer_slack_ns(version: str) -> int:
    """The receive threads' timer slack for a controller of this version ('major.minor.bugfix.build'): a CB3's
    (major 3, or below 5) streams every 8 ms, an e-Series' (major 5 and on) every 2 ms."""
    major = version.split(".", 1)[0]
    if major.isdigit() and int(major) < 5:
        return CB3_RECEIVE_TIMER_SLACK_NS
    return RECEIVE_TIMER_SLACK_NS


@contextmanager
def coarse_timer_slack(slack_ns: int = RECEIVE_TIMER_SLACK_NS) -> Iterator[None]:
    """Threads started inside get a timer slack of `slack_ns` (Linux; elsewhere nothing changes); the
    calling thread's own slack is restored on leaving."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        previous = libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
    except (OSError, AttributeError):
        yield
        return
    if previous < 0 or libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) != 0:
        yield
        return
    try:
        yield
    finally:
        libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(previous), 0, 0, 0)


ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF"}
ROBOT_MODES |= {4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP"}
SAFETY_MODES |= {6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}
_PROTECTIVE_BIT, _ROBOT_ESTOP_BIT, _ANY_ESTOP_BIT = 1 << 2, 1 << 6, 1 << 7
_PLAYING = 2
_SNAPSHOT_TRIES = 50
_AT_REST_RAD_S = 1e-6  # target joint speed below which a move has ended


@dataclass(frozen=True)
class _Snapshot:
    """Controller state read from one and the same receive package."""

    stamp: float
    safety_bits: int
    safety_mode: int
    robot_mode: int
    runtime_state: int


@dataclass(frozen=True)
class URConfig:
    """Connection, speed limits and supervision settings of one UR robot (from the cell config)."""

    host: str
    joint_speed: float = 1.05  # rad/s, default for move_joints
    joint_accel: float = 1.4  # rad/s^2
    linear_speed: float = 0.25  # m/s, default for move_linear
    linear_accel: float = 1.2  # m/s^2
    max_joint_speed: float = math.pi  # rad/s, hard limit for any request
    max_joint_accel: float = 10.0
    max_linear_speed: float = 1.0  # m/s
    max_linear_accel: float = 5.0
    joint_limit_rad: float = 2 * math.pi
    connect_timeout_s: float = 5.0
    connect_attempts: int = 3
    settle_dwell_s: float = 0.2
    settle_timeout_s: float = 30.0
    stale_after_s: float = 0.5  # data timestamps must advance within this wall time
    stream_sync_timeout_s: float = 2.0  # how long the receive stream may lag what the control stream saw
    move_timeout_margin_s: float = 10.0
    reach_tolerance_rad: float = 1e-3  # a joint move ends this close to its target
    reach_tolerance_m: float = 1e-4  # a linear move ends this close (and within reach_tolerance_rad)
    recover_timeout_s: float = 20.0
    power_on_at_connect: bool = False  # power on and release the brakes if the arm is off at connect

    @classmethod
    def from_mapping(cls, values: dict) -> URConfig:
        """Build from a cell configuration section (e.g. parsed TOML/JSON); unknown keys are an error."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(values) - known)
        if unknown:
            raise RobotConfigError(f"unknown UR settings {unknown}; known: {sorted(known)}")
        return cls(**values)

    def __post_init__(self) -> None:
        for name in (
            "joint_speed",
            "joint_accel",
            "linear_speed",
            "linear_accel",
            "stale_after_s",
            "stream_sync_timeout_s",
        ):
            if not getattr(self, name) > 0:
                raise RobotConfigError(f"URConfig.{name} must be positive, got {getattr(self, name)}")
        for name, limit in (
            ("joint_speed", "max_joint_speed"),
            ("joint_accel", "max_joint_accel"),
            ("linear_speed", "max_linear_speed"),
            ("linear_accel", "max_linear_accel"),
        ):
            if getattr(self, name) > getattr(self, limit):
                raise RobotConfigError(
                    f"URConfig.{name} {getattr(self, name)} exceeds {limit} {getattr(self, limit)}"
                )


def probe_controller(host: str, timeout_s: float, rtde_port: int = 30004, dashboard_port: int = 29999) -> str:
    """Check, with socket timeouts, that RTDE answers its handshake and streams, and the dashboard greets.

    The ur-rtde constructors wait forever for these replies and for the first data package (holding the
    GIL while they do), so the driver only calls them once this probe passed. Returns the controller
    version 'major.minor.bugfix.build'.
    """
    return _probe(host, timeout_s, rtde_port, dashboard_port)[0]


def _probe(
    host: str, timeout_s: float, rtde_port: int = 30004, dashboard_port: int = 29999
) -> tuple[str, float]:
    """`probe_controller`, also returning the controller timestamp (s) of the data package it received."""
    try:
        with socket.create_connection((host, rtde_port), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
            _read_rtde_reply(sock, ord("V"))
            sock.sendall(struct.pack(">HB", 3, ord("v")))
            payload = _read_rtde_reply(sock, ord("v"))
            numbers = struct.unpack(">IIII", payload[:16])
            version = ".".join(str(x) for x in numbers)
            # the control constructor waits, without a timeout, for a first data package: check one comes
            frequency = 500.0 if numbers[0] >= 5 else 125.0
            names = b"timestamp,"
            sock.sendall(struct.pack(">HBd", 3 + 8 + len(names), ord("O"), frequency) + names)
            _read_rtde_reply(sock, ord("O"))
            sock.sendall(struct.pack(">HB", 3, ord("S")))
            if _read_rtde_reply(sock, ord("S"))[:1] != b"\x01":
                raise RobotConnectionError(f"RTDE at {host} refused to start synchronisation")
            (stamp,) = struct.unpack(">d", _read_rtde_reply(sock, ord("U"))[1:9])  # after the recipe id
        with socket.create_connection((host, dashboard_port), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            greeting = sock.recv(256)
            if not greeting:
                raise RobotConnectionError(f"dashboard of {host} closed without a greeting")
    except (OSError, struct.error) as exc:
        raise RobotConnectionError(f"controller at {host} does not answer: {exc}") from exc
    return version, stamp


def _identity(dash: Any) -> tuple[str, str]:
    """The arm's serial number and model as its dashboard reports them; "" for what the controller does not
    say (ur-rtde asks for the serial number only from PolyScope 5.6 on: a CB3 arm is keyed by its cell)."""

    def ask(question: Callable[[], str]) -> str:
        try:
            return str(question()).strip()
        except RuntimeError:
            return ""

    return ask(dash.getSerialNumber), ask(dash.getRobotModel)


def _read_rtde_reply(sock: socket.socket, expected_type: int) -> bytes:
    header = _recv_exact(sock, 3)
    size, kind = struct.unpack(">HB", header)
    payload = _recv_exact(sock, size - 3)
    if kind != expected_type:
        raise RobotConnectionError(f"RTDE replied with message type {kind}, expected {expected_type}")
    return payload


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise RobotConnectionError("RTDE connection closed during the handshake")
        data += chunk
    return data


def _reason(exc: Exception | None) -> str:
    """An error's cause alone, without its remedy (the caller words what to do)."""
    return exc.message if isinstance(exc, RobotError) else str(exc)


def _disconnect_quietly(client: Any) -> None:
    """One ur-rtde client's disconnect(); a dead peer must not stop the rest of the teardown."""
    try:
        client.disconnect()
    except Exception as exc:
        log.debug("disconnect failed: %s", exc)


class URRobot:
    """`Robot` on a UR controller through ur-rtde (receive + control + dashboard)."""

    def __init__(self, config: URConfig):
        self.config = config
        # ur-rtde's receive, control and dashboard interfaces (untyped C++ objects); None when not connected
        self._rx: Any | None = None
        self._ctrl: Any | None = None
        self._dash: Any | None = None
        self.version = ""
        self.serial_number = ""  # what the dashboard reports ("" when the controller does not say)
        self.model_name = ""
        self._last_stamp = -1.0
        self._last_stamp_wall = 0.0
        self._program_restarted_s = -math.inf  # monotonic time ur-rtde last restarted the control program
        self._connect()
        # make sure the clients are disconnected before the interpreter (or the fake) goes away
        self._finalizer = weakref.finalize(self, URRobot._release, [self._ctrl, self._rx, self._dash])

    # ------------------------------------------------------------------ connection
    def _connect(self) -> None:
        """Probe, then build dashboard, receive and control interfaces, with bounded retries."""
        import dashboard_client
        import rtde_control
        import rtde_receive

        cfg = self.config
        last: Exception | None = None
        for attempt in range(cfg.connect_attempts):
            try:
                self.version = probe_controller(cfg.host, cfg.connect_timeout_s)
                self._dash = dash = dashboard_client.DashboardClient(cfg.host)
                dash.connect(int(cfg.connect_timeout_s * 1000))
                self.serial_number, self.model_name = _identity(dash)
                with coarse_timer_slack(receive_timer_slack_ns(self.version)):
                    self._rx = rx = rtde_receive.RTDEReceiveInterface(cfg.host)
                self._require_arm_ready()  # the control program would not start otherwise (a 5 s stall)
                with coarse_timer_slack(receive_timer_slack_ns(self.version)):
                    self._ctrl = ctrl = rtde_control.RTDEControlInterface(
                        cfg.host, -1.0, rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
                    )
                ctrl.setTcp([0.0] * 6)  # TCP pose = flange pose
                self._program_restarted_s = time.monotonic()  # ur-rtde (re)started its program just now
                self._await_program_on_receive_stream()
                self._last_stamp, self._last_stamp_wall = rx.getTimestamp(), time.monotonic()
                return
            except (EmergencyStopError, ProtectiveStopError, RobotNotReadyError):
                self._disconnect()
                raise
            except (RuntimeError, RobotConnectionError) as exc:
                last = exc
                log.info("connect to %s, attempt %d failed: %s", cfg.host, attempt + 1, _reason(exc))
                self._disconnect()
                time.sleep(min(2.0, 0.2 * 2**attempt))
        raise RobotConnectionError(f"could not connect to the UR controller at {cfg.host}: {_reason(last)}")

    def _await_program_on_receive_stream(self) -> None:
        """The control interface saw its program start; the receive stream, another socket, may report it some
        cycles later (more on a loaded PC), and the first command's check reads that stream: wait for it there,
        bounded (if it never shows, that check names what the controller says)."""
        rx = self._receive()
        deadline = time.monotonic() + self.config.stream_sync_timeout_s
        while rx.getRuntimeState() != _PLAYING and time.monotonic() < deadline:
            time.sleep(0.002)

    def _require_arm_ready(self) -> None:
        """Before the control program is uploaded: the arm must be powered, brakes released, no stop."""
        rx = self._receive()
        deadline = time.monotonic() + 2.0
        while rx.getTimestamp() <= 0 and time.monotonic() < deadline:
            time.sleep(0.002)
        bits = rx.getSafetyStatusBits()
        if bits & (_ANY_ESTOP_BIT | _ROBOT_ESTOP_BIT):
            raise EmergencyStopError(
                "the robot is emergency stopped", "release the e-stop, power on, then connect"
            )
        if bits & _PROTECTIVE_BIT:
            raise ProtectiveStopError(
                "the robot is protective stopped",
                "inspect the cell, unlock the protective stop, then connect",
            )
        mode = ROBOT_MODES.get(rx.getRobotMode(), "UNKNOWN")
        if mode == "RUNNING":
            return
        if not self.config.power_on_at_connect:
            raise RobotNotReadyError(
                f"the arm is {mode}, not RUNNING",
                "power on and release the brakes on the pendant, or use URConfig(power_on_at_connect=True)",
            )
        dash = self._dashboard()
        dash.powerOn()
        dash.brakeRelease()
        deadline = time.monotonic() + self.config.recover_timeout_s
        while ROBOT_MODES.get(rx.getRobotMode()) != "RUNNING":
            if time.monotonic() > deadline:
                raise RobotNotReadyError("the arm did not reach RUNNING after power on and brake release")
            time.sleep(0.02)

    def _receive(self) -> Any:
        """The RTDE receive interface; RobotConnectionError when it is gone (closed or being rebuilt)."""
        if self._rx is None:
            raise RobotConnectionError(f"not connected to {self.config.host}")
        return self._rx

    def _control(self) -> Any:
        """The RTDE control interface; RobotConnectionError when it is gone (closed or being rebuilt)."""
        if self._ctrl is None:
            raise RobotConnectionError(f"not connected to {self.config.host}")
        return self._ctrl

    def _dashboard(self) -> Any:
        """The dashboard client; RobotConnectionError when it is gone (closed or being rebuilt)."""
        if self._dash is None:
            raise RobotConnectionError(f"not connected to {self.config.host}")
        return self._dash

    def _disconnect(self) -> None:
        URRobot._release([self._ctrl, self._rx, self._dash])
        self._ctrl = self._rx = self._dash = None

    @staticmethod
    def _release(clients: list) -> None:
        """Disconnect the clients (control, receive, dashboard; any may be None or already gone) side by side.

        ur-rtde's disconnect() of an interface ends in a fixed 500 ms wait, with the GIL released: one after the
        other, control and receive took 1 s, side by side 0.5 s. (Each interface's destructor disconnects and
        waits once more, then with the GIL held: that second wait is ur-rtde's and stays.)
        """
        live = [client for client in clients if client is not None]
        helpers = []
        for client in live[1:]:
            helper = threading.Thread(
                target=_disconnect_quietly, args=(client,), name="ur-disconnect", daemon=True
            )
            try:
                helper.start()
            except RuntimeError:  # no new thread at interpreter shutdown (a finalizer): one after the other
                _disconnect_quietly(client)
                continue
            helpers.append(helper)
        if live:
            _disconnect_quietly(live[0])
        for helper in helpers:
            helper.join()

    def _rebuild(self) -> None:
        """Rebuild the control interface; everything if the receive stream is not provably alive too."""
        import rtde_control

        self._finalizer.detach()
        # disconnect before building anew (never rebind a live one): it frees the input registers
        URRobot._release([self._ctrl])
        self._ctrl = None
        try:
            _, controller_time_s = _probe(self.config.host, self.config.connect_timeout_s)
            healthy = self._receive_reaches(controller_time_s)
        except RobotConnectionError:
            healthy = False
        if healthy:
            try:
                with coarse_timer_slack(receive_timer_slack_ns(self.version)):
                    self._ctrl = ctrl = rtde_control.RTDEControlInterface(
                        self.config.host, -1.0, rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
                    )
                ctrl.setTcp([0.0] * 6)
                self._program_restarted_s = time.monotonic()  # ur-rtde (re)started its program just now
            except (RuntimeError, RobotConnectionError) as exc:
                log.warning("rebuilding the control interface failed (%s); reconnecting everything", exc)
                healthy = False
        if not healthy:
            self._disconnect()
            self._connect()
        self._finalizer = weakref.finalize(self, URRobot._release, [self._ctrl, self._rx, self._dash])

    def _receive_reaches(self, controller_time_s: float) -> bool:
        """Whether the receive stream delivers a package at least as new as `controller_time_s` (read
        from a fresh connection just now). A recent timestamp is no proof: after a dropped connection
        ur-rtde's receive thread keeps reporting "connected" until its next read fails."""
        rx = self._rx
        deadline = time.monotonic() + self.config.stream_sync_timeout_s
        while rx is not None and rx.isConnected():
            if rx.getTimestamp() >= controller_time_s:
                return True
            if time.monotonic() > deadline:
                break
            time.sleep(0.002)
        return False

    # ------------------------------------------------------------------ supervision
    def _read_consistent(self, *getters) -> list:
        """Call receive getters so that all values come from one package: the receive thread replaces a
        whole package under one lock, so an unchanged timestamp around the reads means one package."""
        rx = self._receive()
        for _ in range(_SNAPSHOT_TRIES):
            stamp = rx.getTimestamp()
            values = [stamp, *(getter() for getter in getters)]
            if rx.getTimestamp() == stamp:
                break
        return values[1:]  # after that many tries a package from the last moments is good enough

    def _snapshot(self) -> _Snapshot:
        """Timestamp, safety and program state from one receive package."""
        rx = self._receive()
        return _Snapshot(
            *self._read_consistent(
                rx.getTimestamp, rx.getSafetyStatusBits, rx.getSafetyMode, rx.getRobotMode, rx.getRuntimeState
            )
        )

    def _check(self) -> _Snapshot:
        """Raise the typed error for the controller's current condition, if any; else return the state.

        All fields come from one receive package, so a stop that also ended the program is reported as
        the stop, never as "program not running" read from a newer package than the safety bits. Just
        after ur-rtde restarted the control program, a package without it is read again (see
        `_receive_may_lag_restart`)."""
        if self._rx is None or self._ctrl is None:
            raise RobotConnectionError(f"not connected to {self.config.host}")
        while True:
            self._check_stream()
            snapshot = self._snapshot()
            bits = snapshot.safety_bits
            if bits & (_ANY_ESTOP_BIT | _ROBOT_ESTOP_BIT):
                raise EmergencyStopError("the robot is emergency stopped")
            if bits & _PROTECTIVE_BIT:
                raise ProtectiveStopError("the robot is protective stopped")
            if not self._ctrl.isConnected():
                raise RobotConnectionError(f"RTDE control connection to {self.config.host} lost")
            if snapshot.runtime_state == _PLAYING:
                return snapshot
            if not self._receive_may_lag_restart():
                raise ProgramNotRunningError("the control program is not running on the controller")
            time.sleep(0.002)

    def _receive_may_lag_restart(self) -> bool:
        """Whether a receive package without a running program may be late news rather than a stop.

        ur-rtde restarts the control program whenever it builds the control interface (`_connect`,
        `_rebuild`: a script still running is stopped and uploaded again) and for a path move (the script
        uploaded again with the path injected); each time it returns once its own stream shows the program
        running. The receive stream is another socket: for a while it can still deliver packages from the
        gap, even after one that showed the old program running. Within `stream_sync_timeout_s` of a
        restart, and while the control stream says the program runs, such a package is read again; a
        program that really stopped ends the control stream's "running" too."""
        ctrl = self._ctrl
        return (
            time.monotonic() - self._program_restarted_s < self.config.stream_sync_timeout_s
            and ctrl is not None
            and bool(ctrl.isProgramRunning())
        )

    def _supervise_async(self, op_before: int, expected_s: float, what: str) -> None:
        """Wait for the async operation started after `op_before` to finish, checking faults meanwhile."""
        deadline = time.monotonic() + expected_s * 3 + self.config.move_timeout_margin_s
        while True:
            self._check()
            status = self._control().getAsyncOperationProgressEx()
            if status.operationId() != op_before and not status.isAsyncOperationRunning():
                # read after the status on the same (control) stream, so never from an older package
                if not self._control().isProgramRunning():
                    self._raise_program_end(what)
                return
            if time.monotonic() > deadline:
                self._try_stop()
                raise RobotTimeoutError(
                    f"{what} did not finish within {deadline - time.monotonic() + 0:.0f} s"
                )
            time.sleep(0.004)

    def _raise_program_end(self, what: str) -> None:
        """The control stream saw the program end with the move: wait for the receive stream (which may
        lag) to show why, so the error names the cause (stop, e-stop, program stopped)."""
        deadline = time.monotonic() + self.config.stream_sync_timeout_s
        while time.monotonic() < deadline:
            self._check()
            time.sleep(0.002)
        raise ProgramNotRunningError(f"the control program ended during {what}")

    def _sync_stream(self, packages: int = 2) -> None:
        """Wait for a couple of fresh receive packages: the receive and control streams are separate
        sockets, so right after the control side reports an event the receive side may lag a cycle."""
        deadline = time.monotonic() + self.config.stale_after_s
        rx = self._receive()
        stamp, seen = rx.getTimestamp(), 0
        while seen < packages:
            now_stamp = rx.getTimestamp()
            if now_stamp != stamp:
                stamp, seen = now_stamp, seen + 1
            elif time.monotonic() > deadline:
                self._check_stream()
                return
            time.sleep(0.0005)

    def _try_stop(self) -> None:
        try:
            if self._ctrl is not None and self._ctrl.isProgramRunning():
                self._ctrl.stopJ(2.0)
        except RuntimeError as exc:
            log.warning("stop failed: %s", exc)

    # ------------------------------------------------------------------ motion
    def move_joints(self, q: np.ndarray, speed: float | None = None, accel: float | None = None) -> None:
        cfg = self.config
        q = _vector(q, 6, "joint target")
        if np.any(np.abs(q) > cfg.joint_limit_rad):
            raise RobotConfigError(f"joint target {np.round(q, 4)} outside +-{cfg.joint_limit_rad:.3f} rad")
        speed = _limited(speed, cfg.joint_speed, cfg.max_joint_speed, "joint speed (rad/s)")
        accel = _limited(accel, cfg.joint_accel, cfg.max_joint_accel, "joint acceleration (rad/s^2)")
        self._check()
        distance = float(np.max(np.abs(q - self.joints())))
        ctrl = self._control()
        op_before = ctrl.getAsyncOperationProgressEx().operationId()
        if not ctrl.moveJ(q.tolist(), speed, accel, True):
            self._check()
            raise RobotError("the controller refused moveJ", "check the target and the controller log")
        self._supervise_async(op_before, _trapezoid_time(distance, speed, accel), "moveJ")

        def left_of(q_now: np.ndarray, T_now: np.ndarray) -> tuple[float, bool]:
            radians = float(np.max(np.abs(q_now - q)))
            return radians, radians <= cfg.reach_tolerance_rad

        self._wait_arrived("moveJ", left_of, "rad")

    def _wait_arrived(self, what: str, left_of, unit: str) -> None:
        """After the control stream reported the end of a move, wait until the receive stream (a separate
        socket that may lag) shows the arm at rest on the target; a move that really ended short fails.
        `left_of(target_q, T_base_flange_target)` gives the distance left and whether it is arrived."""
        deadline = time.monotonic() + self.config.stream_sync_timeout_s
        rx = self._receive()
        while True:
            self._check()
            target_q, target_qd, target_pose = self._read_consistent(
                rx.getTargetQ, rx.getTargetQd, rx.getTargetTCPPose
            )
            left, arrived = left_of(np.asarray(target_q), pose_to_transform(np.asarray(target_pose)))
            if arrived and float(np.max(np.abs(target_qd))) < _AT_REST_RAD_S:
                return
            if time.monotonic() > deadline:
                raise RobotError(
                    f"{what} ended {left:.4f} {unit} from its target", "the move was interrupted; retry"
                )
            time.sleep(0.002)

    def move_linear(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        cfg = self.config
        T = np.asarray(T_base_flange, float)
        pose = transform_to_pose(T) if T.shape == (4, 4) else _vector(T, 6, "pose")
        if not np.all(np.isfinite(pose)):
            raise RobotConfigError(f"linear target {pose} is not finite")
        speed = _limited(speed, cfg.linear_speed, cfg.max_linear_speed, "linear speed (m/s)")
        accel = _limited(accel, cfg.linear_accel, cfg.max_linear_accel, "linear acceleration (m/s^2)")
        self._check()
        current = self.flange_pose()
        target = pose_to_transform(pose)
        distance = max(
            float(np.linalg.norm(target[:3, 3] - current[:3, 3])),
            _rotation_angle(current[:3, :3].T @ target[:3, :3]),
        )
        ctrl = self._control()
        op_before = ctrl.getAsyncOperationProgressEx().operationId()
        if not ctrl.moveL(pose.tolist(), speed, accel, True):
            self._check()
            raise RobotError("the controller refused moveL", "check that the pose is reachable")
        self._supervise_async(op_before, _trapezoid_time(distance, speed, accel), "moveL")

        def left_of(q_now: np.ndarray, T_now: np.ndarray) -> tuple[float, bool]:
            metres = float(np.linalg.norm(T_now[:3, 3] - target[:3, 3]))
            turned = _rotation_angle(T_now[:3, :3].T @ target[:3, :3])
            return metres, metres <= cfg.reach_tolerance_m and turned <= cfg.reach_tolerance_rad

        self._wait_arrived("moveL", left_of, "m")

    def move_path(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        """moveL through waypoints (ur-rtde's path form, blend radius 0: the arm stops at each waypoint)."""
        cfg = self.config
        T = np.asarray(T_base_flange, float)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) < 1 or not np.all(np.isfinite(T)):
            raise RobotConfigError(f"a path needs finite waypoints (K, 4, 4), got shape {T.shape}")
        speed = _limited(speed, cfg.linear_speed, cfg.max_linear_speed, "linear speed (m/s)")
        accel = _limited(accel, cfg.linear_accel, cfg.max_linear_accel, "linear acceleration (m/s^2)")
        self._check()
        poses = [transform_to_pose(t) for t in T]
        legs = np.vstack([self.flange_pose()[None], T])
        expected_s = sum(
            _trapezoid_time(
                max(float(np.linalg.norm(b[:3, 3] - a[:3, 3])), _rotation_angle(a[:3, :3].T @ b[:3, :3])),
                speed,
                accel,
            )
            for a, b in zip(legs[:-1], legs[1:], strict=True)
        )
        ctrl = self._control()
        op_before = ctrl.getAsyncOperationProgressEx().operationId()
        path = [[*map(float, p), speed, accel, 0.0] for p in poses]
        moved = ctrl.moveL(path, True)
        self._program_restarted_s = time.monotonic()  # a path runs in a freshly uploaded control program
        if not moved:
            self._check()
            raise RobotError(
                "the controller refused the moveL path", "check that every waypoint is reachable"
            )
        self._supervise_async(op_before, expected_s, "moveL path")
        target = T[-1]

        def left_of(q_now: np.ndarray, T_now: np.ndarray) -> tuple[float, bool]:
            metres = float(np.linalg.norm(T_now[:3, 3] - target[:3, 3]))
            turned = _rotation_angle(T_now[:3, :3].T @ target[:3, :3])
            return metres, metres <= cfg.reach_tolerance_m and turned <= cfg.reach_tolerance_rad

        self._wait_arrived("moveL path", left_of, "m")

    def stop(self) -> None:
        """Decelerate to rest; a no-op when the program is not running (the controller already holds it)."""
        ctrl = self._ctrl
        if ctrl is None or not ctrl.isConnected():
            raise RobotConnectionError(f"cannot stop: no control connection to {self.config.host}")
        if ctrl.isProgramRunning():
            ctrl.stopJ(self.config.max_joint_accel / 2)

    # ------------------------------------------------------------------ reading
    def joints(self) -> np.ndarray:
        self._check_stream()
        return np.array(self._receive().getActualQ(), float)

    def flange_pose(self) -> np.ndarray:
        self._check_stream()
        return pose_to_transform(np.array(self._receive().getActualTCPPose(), float))

    def temperature_c(self) -> float | None:
        """The arm's temperature from its joint sensors (mean of the six, degC); None when not reported."""
        self._check_stream()
        t = np.asarray(self._receive().getJointTemperatures(), float)
        return float(np.mean(t)) if t.size and np.all(np.isfinite(t)) else None

    def _check_stream(self) -> None:
        """Readings need only a live, advancing data stream (not a running program)."""
        rx = self._rx
        if rx is None or not rx.isConnected():
            raise RobotConnectionError(f"RTDE receive connection to {self.config.host} lost")
        stamp, now = rx.getTimestamp(), time.monotonic()
        if stamp != self._last_stamp:
            self._last_stamp, self._last_stamp_wall = stamp, now
        elif now - self._last_stamp_wall > self.config.stale_after_s:
            raise StaleDataError(
                f"RTDE data from {self.config.host} frozen for {now - self._last_stamp_wall:.2f} s "
                f"(timestamp {stamp:.3f} s)"
            )

    def wait_settled(self, dwell_s: float | None = None, timeout_s: float | None = None) -> None:
        dwell_s = self.config.settle_dwell_s if dwell_s is None else dwell_s
        deadline = time.monotonic() + (self.config.settle_timeout_s if timeout_s is None else timeout_s)
        rx = self._receive()
        while True:
            self._check()
            # At rest by the receive stream alone: ur-rtde's isSteady() is a command to the control script, and
            # with the controller gone it sleeps in its reconnect loop for ever (seen after Ctrl-C of hil demo).
            if max(np.max(np.abs(rx.getActualQd())), np.max(np.abs(rx.getTargetQd()))) < 1e-6:
                break
            if time.monotonic() > deadline:
                raise RobotTimeoutError("the robot did not settle")
            time.sleep(0.005)
        end = time.monotonic() + dwell_s
        while time.monotonic() < end:  # keep supervising during the dwell
            self._check()
            time.sleep(min(0.01, max(0.0, end - time.monotonic())))

    def state(self) -> RobotState:
        rx = self._rx
        if rx is None or not rx.isConnected():
            return RobotState(False, "DISCONNECTED", "UNKNOWN", False, False, False, float("nan"))
        snapshot = self._snapshot()
        bits = snapshot.safety_bits
        return RobotState(
            connected=bool(self._ctrl is not None and self._ctrl.isConnected()),
            robot_mode=ROBOT_MODES.get(snapshot.robot_mode, "UNKNOWN"),
            safety_mode=SAFETY_MODES.get(snapshot.safety_mode, "UNKNOWN"),
            program_running=snapshot.runtime_state == _PLAYING,
            protective_stop=bool(bits & _PROTECTIVE_BIT),
            emergency_stop=bool(bits & (_ANY_ESTOP_BIT | _ROBOT_ESTOP_BIT)),
            timestamp_s=snapshot.stamp,
        )

    # ------------------------------------------------------------------ recovery and teardown
    def recover(self) -> None:
        """Unlock a protective stop, power the arm if needed, and rebuild the connections."""
        cfg = self.config
        deadline = time.monotonic() + cfg.recover_timeout_s
        self._ensure_dashboard()
        dash = self._dashboard()
        mode = dash.safetystatus() if self.version.startswith("5") else dash.safetymode()
        if "EMERGENCY" in mode:
            raise EmergencyStopError(f"cannot recover: {mode.strip()}")
        if "PROTECTIVE_STOP" in mode:
            while True:
                try:
                    dash.unlockProtectiveStop()
                    break
                except Exception as exc:  # refused within 5 s of the stop: wait and retry
                    if time.monotonic() > deadline:
                        raise ProtectiveStopError(
                            f"the protective stop could not be unlocked: {exc}"
                        ) from exc
                    time.sleep(0.2)
            dash.closeSafetyPopup()
        if "RUNNING" not in dash.robotmode():
            dash.powerOn()
            dash.brakeRelease()
            while "RUNNING" not in dash.robotmode():
                if time.monotonic() > deadline:
                    raise RobotError("the arm did not reach RUNNING after power on and brake release")
                time.sleep(0.05)
        self._rebuild()
        self._sync_stream()  # the receive stream may report the restarted program a cycle late
        self._check()

    def _ensure_dashboard(self) -> None:
        if self._dash is not None and self._dash.isConnected():
            return
        import dashboard_client

        probe_controller(self.config.host, self.config.connect_timeout_s)
        self._dash = dash = dashboard_client.DashboardClient(self.config.host)
        dash.connect(int(self.config.connect_timeout_s * 1000))

    def close(self) -> None:
        """Stop any motion, then disconnect control, receive and dashboard (side by side: `_release`)."""
        if self._ctrl is not None:
            self._try_stop()
        self._finalizer.detach()
        self._disconnect()

    def __enter__(self) -> URRobot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class URDriver:
    """The `ur` instrument plug-in (entry point in pyproject.toml): UR arms through ur-rtde."""

    kind = "robot"
    summary = "Universal Robots CB3 and e-Series arms through ur-rtde"

    def open(self, settings: Mapping[str, Any]) -> URRobot:
        """Connect with the cell's robot settings (`host` and URConfig's keys)."""
        return URRobot(URConfig.from_mapping(dict(settings)))


plugin = URDriver()


def _vector(value, n: int, what: str) -> np.ndarray:
    v = np.asarray(value, float).reshape(-1)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise RobotConfigError(f"{what} must be {n} finite numbers, got {value!r}")
    return v


def _limited(value: float | None, default: float, limit: float, what: str) -> float:
    value = default if value is None else float(value)
    if not (0 < value <= limit):
        raise RobotConfigError(f"{what} {value} outside (0, {limit}]")
    return value


def _trapezoid_time(distance: float, speed: float, accel: float) -> float:
    if distance <= 0:
        return 0.0
    v = min(speed, math.sqrt(distance * accel))
    return distance / v + v / accel


def _rotation_angle(R: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))
