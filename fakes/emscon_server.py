"""A fake Leica emScon tracker server speaking the TPI binary protocol over TCP and over a pseudo-terminal.

Results come from the simulated cell: the SMR the beam is locked on, in the tracker frame, with the cell's
noise model and the meteo of its clock. Server-side state (units, coordinate system, measurement mode,
reflector, system settings, environment, search parameters) is shared by every connection, as on a real
emScon server. Choices the fact sheet marks as assumptions (emscon_protocol.md §8) are made as it
recommends: failure answers are full size, "no target" is status 37 (configurable), a beam break during a
measurement is an error packet (command 49) instead of the result, Set* commands are followed by their
"...Changed" status event to every client, cylindrical/left-handed systems answer NotImplemented.
The fake's dStd equals its a-priori std (it does not model averaging within lMeasTime).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
import threading
import tty
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, CoordinateSystem, Status, StatusChange

log = logging.getLogger(__name__)

_FLUSH = object()  # writer-queue marker: end of a command's output (used by the "merged" framing mode)


@dataclass(frozen=True)
class Reflector:
    id: int
    name: str
    target_type: int  # ES_TargetType
    surface_offset_m: float = 0.0


@dataclass
class EmsconServerConfig:
    """Behaviour of the fake tracker (timings are wall-clock unless named sim)."""

    initialized: bool = False  # a freshly powered tracker needs Initialize
    init_delay_s: float = 0.05
    motion_delay_s: float = 0.0  # GoPosition / FindReflector answer after this
    no_target_status: int = Status.NO_DISTANCE_SET
    acceptance_half_angle_rad: float = math.radians(30.0)  # SMR opening: beyond it the beam is lost
    search_radius_m: float = 0.05
    search_timeout_ms: int = 5000
    max_tracking_speed_m_s: float = 4.0
    capture_m: float = 0.005  # jump the tracker still follows with no time passing
    track_poll_s: float = 0.02
    # True: the fake owns the clock, waits wall_time_scale x the measurement time and then calls
    # cell.advance_time(measurement time). False (inside `hil sim`, whose clock task moves the cell on):
    # wait until the cell clock has advanced by the measurement time.
    advance_clock: bool = True
    wall_time_scale: float = 1.0  # wall seconds per simulated measurement second (own clock only)
    external_clock_poll_s: float = 0.002
    initial_lock_smr: int | None = None
    reflectors: tuple[Reflector, ...] = (
        Reflector(1, "RRR 1.5in", 5),
        Reflector(2, "RRR 0.5in", 6),
        Reflector(3, "CatsEye", 2),
    )
    birdbath_point_m: tuple[float, float, float] = (0.15, 0.0, -0.2)  # home nest on the tracker stand
    tracker_name: str = "AT901-LR"
    max_distance_m: float = 80.0
    min_distance_m: float = 0.0
    serial_number: int = 390123
    version: tuple[int, int, int] = (3, 8, 712)
    temperature_range_c: tuple[float, float] = (-20.0, 60.0)
    pressure_range_hpa: tuple[float, float] = (500.0, 1200.0)
    humidity_range_pct: tuple[float, float] = (0.0, 100.0)


@dataclass
class _Faults:
    beam_break_count: int = 0
    beam_break_rate: float = 0.0  # chance that any shot breaks the beam (people walking through the cell)
    no_target: bool = False
    slow_delay_s: float = 0.0
    drop_next_command: bool = False
    line_down: bool = False  # the serial line (pty) is "unplugged": nothing in, nothing out
    garbage_bytes: int = 0
    inject: bytes | None = None  # sent instead of everything the next command would have produced
    outlier_count: int = 0  # the next N results are offset by outlier_offset_m along x (air turbulence)
    outlier_offset_m: float = 0.0
    framing: str = "normal"  # "normal" | "bytewise" | "merged"

    def to_dict(self) -> dict:
        """JSON-able view (bytes as hex)."""
        return {k: v.hex() if isinstance(v, bytes) else v for k, v in self.__dict__.items()}


@dataclass
class _TrackerState:
    """The server-side state every client shares."""

    units: codec.Units = field(default_factory=codec.Units)
    cs: CoordinateSystem = CoordinateSystem.RHR
    meas_mode: int = 0
    meas_time_ms: int = 1000
    use_adm: bool = False
    statistic_mode: tuple[int, int] = (0, 0)
    reflector_id: int = 1
    # WMS, ApplyTransformation, ApplyStationOrientation, KeepLastPosition, SendUnsolicited, SendReflectorPos,
    # TryMode, HasNivel, HasVideoCamera
    settings: list[int] = field(default_factory=lambda: [1, 0, 0, 1, 1, 0, 0, 1, 0])
    manual_meteo: tuple[float, float, float] | None = None  # °C, hPa, %RH when no weather monitor
    search_radius_m: float = 0.05
    search_timeout_ms: int = 5000
    initialized: bool = False
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    locked_smr: int | None = None
    lock_p_m: np.ndarray | None = None
    lock_sim_s: float = 0.0
    lock_wall_s: float = 0.0
    last_result_status: int = 0
    measuring: int = 0
    exit_requests: int = 0
    busy_replies: int = 0  # commands refused with ServerBusy (a client sent while one was pending)
    laser_on: bool = True
    face: int = 1
    temperature_range: int = 3  # ES_TR_Automatic
    station_orientation: tuple = (0.0,) * 6
    transformation: tuple = (0.0,) * 6 + (1.0,)
    refraction: tuple[float, float] = (1.000271, 1.000271)
    long_params: dict = field(default_factory=lambda: {codec.SP_TCP_COMMAND_QUEUE_SIZE: 0})
    double_params: dict = field(default_factory=dict)
    command_counts: Counter = field(default_factory=Counter)  # per command name, for tests and tracker.state


class _Session:
    """One client byte stream (a TCP connection or the pty): splits packets, runs one command at a time."""

    def __init__(
        self, server: EmsconServer, write: Callable[[bytes], None], close: Callable[[], None] | None
    ):
        self.server = server
        self._write = write
        self._close = close
        self.splitter = codec.FrameSplitter()
        self.busy = False
        self.closed = False
        self.queue: asyncio.Queue = asyncio.Queue()
        self.writer_task = asyncio.get_running_loop().create_task(self._writer())
        self.tasks: set[asyncio.Task] = set()

    @property
    def is_serial(self) -> bool:
        return self._close is None

    def send(self, *packets: bytes, flush: bool = True) -> None:
        if self.closed or (self.is_serial and self.server.faults.line_down):
            return
        for packet in packets:
            self.queue.put_nowait(packet)
        if flush:
            self.queue.put_nowait(_FLUSH)

    async def _writer(self) -> None:
        held: list[bytes] = []
        while True:
            item = await self.queue.get()
            mode = self.server.faults.framing
            if item is _FLUSH:
                if held:
                    self._write(b"".join(held))
                    held.clear()
                continue
            if mode == "merged":
                held.append(item)
            elif mode == "bytewise":
                for i in range(len(item)):
                    self._write(item[i : i + 1])
                    await asyncio.sleep(0.0002)
            else:
                self._write(item)

    def feed(self, data: bytes) -> None:
        if self.is_serial and self.server.faults.line_down:
            return
        try:
            packets = self.splitter.feed(data)
        except codec.CodecError as exc:
            log.warning("fake tracker: framing error from client, closing: %s", exc)
            packets = exc.packets
            self.splitter.reset()
            self.shutdown()
        for packet in packets:
            command = codec.COMMAND_HEAD.unpack_from(packet)[2] if len(packet) >= 12 else -1
            if self.busy:
                self.server.state.busy_replies += 1
                self.send(codec.pack_answer(command, Status.SERVER_BUSY))
                continue
            self.busy = True
            task = asyncio.get_running_loop().create_task(self._run(packet, command))
            self.tasks.add(task)
            task.add_done_callback(self.tasks.discard)

    async def _run(self, packet: bytes, command: int) -> None:
        try:
            faults = self.server.faults
            if faults.drop_next_command:
                faults.drop_next_command = False
                if self.is_serial:  # a serial line cannot be closed from this end: it goes silent
                    faults.line_down = True
                else:
                    self.shutdown()
                return
            if faults.slow_delay_s > 0:
                await asyncio.sleep(faults.slow_delay_s)
            if faults.inject is not None:
                data, faults.inject = faults.inject, None
                self.send(data)
                return
            if faults.garbage_bytes > 0:
                n, faults.garbage_bytes = faults.garbage_bytes, 0
                garbage = b"\xff\xff\xff\x7f" + os.urandom(max(0, n - 4))  # size field 2 GiB: a desync
                self.send(garbage[:n])
            await self.server.handle(self, packet, command)
        except Exception:  # a fake must survive its own bugs long enough to report them
            log.exception("fake tracker: command %s failed", command)
            self.send(codec.pack_answer(command, Status.UNKNOWN))
        finally:
            self.busy = False
            self.send(flush=True)

    def shutdown(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.writer_task.cancel()
        if self._close is not None:
            self._close()
        self.server._sessions.discard(self)


class EmsconServer:
    """The fake emScon server: `await start()`, `.url`, `await open_pty()`, `await close()`."""

    def __init__(
        self, cell, host: str = "127.0.0.1", port: int = 0, config: EmsconServerConfig | None = None
    ):
        self.cell = cell
        self.host = host
        self.requested_port = port
        self.config = config or EmsconServerConfig()
        self.faults = _Faults()
        self._fault_rng = np.random.default_rng([getattr(cell.config, "seed", 0), 3])  # random beam breaks
        self.state = _TrackerState(
            initialized=self.config.initialized,
            search_radius_m=self.config.search_radius_m,
            search_timeout_ms=self.config.search_timeout_ms,
        )
        self.port: int | None = None
        self.pty_path: str | None = None
        self._server: asyncio.AbstractServer | None = None
        self._sessions: set[_Session] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._poll_task: asyncio.Task | None = None
        self._pty_fds: tuple[int, int] | None = None
        self._pty_out = bytearray()
        self._lock_generation = 0
        self.sent_results: deque[bytes] = deque(maxlen=1000)  # raw result packets, for tests

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    # ---- lifecycle ---------------------------------------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._server = await asyncio.start_server(self._on_client, self.host, self.requested_port)
        self.port = self._server.sockets[0].getsockname()[1]
        if self.config.initial_lock_smr is not None:
            self._lock(self.config.initial_lock_smr)
        self._poll_task = self._loop.create_task(self._poll())
        log.info("fake emScon tracker on %s", self.url)

    async def close(self) -> None:
        if self._poll_task is not None:
            self._poll_task.cancel()
        for session in list(self._sessions):
            for task in list(session.tasks):
                task.cancel()
            session.shutdown()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        if self._pty_fds is not None:
            master, slave = self._pty_fds
            self.loop.remove_reader(master)
            self.loop.remove_writer(master)
            os.close(master)
            os.close(slave)
            self._pty_fds = None

    async def open_pty(self) -> str:
        """Serve the same protocol on a pseudo-terminal; returns the serial device path for the driver."""
        if self._loop is None:
            self._loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: a clean 8-bit line
        os.set_blocking(master, False)
        self._pty_fds = (master, slave)
        self.pty_path = os.ttyname(slave)
        session = _Session(self, self._pty_write, None)
        self._sessions.add(session)
        self._loop.add_reader(master, self._pty_readable, session)
        return self.pty_path

    def _pty_readable(self, session: _Session) -> None:
        if self._pty_fds is None:
            return
        try:
            data = os.read(self._pty_fds[0], 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # EIO while no one holds the slave open (we do, so this is rare)
            return
        if data:
            session.feed(data)

    def _pty_write(self, data: bytes) -> None:
        self._pty_out.extend(data)
        self._pty_flush()

    def _pty_flush(self) -> None:
        if self._pty_fds is None:
            return
        master = self._pty_fds[0]
        try:
            while self._pty_out:
                n = os.write(master, self._pty_out)
                del self._pty_out[:n]
        except BlockingIOError:
            self.loop.add_writer(master, self._pty_flush)
            return
        except OSError:
            self._pty_out.clear()
        self.loop.remove_writer(master)

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        session = _Session(self, writer.write, writer.close)
        self._sessions.add(session)
        try:
            while not session.closed:
                data = await reader.read(65536)
                if not data:
                    break
                session.feed(data)
        except (ConnectionError, OSError):
            pass
        finally:
            for task in list(session.tasks):
                task.cancel()
            session.shutdown()

    def broadcast(self, *packets: bytes) -> None:
        for session in list(self._sessions):
            session.send(*packets)

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the server runs on (set by start() or open_pty())."""
        if self._loop is None:
            raise RuntimeError("the fake tracker is not started: await start() or open_pty() first")
        return self._loop

    def _call_in_loop(self, fn: Callable[[], object]) -> None:
        """Run fn on the server's loop (control handlers may be called from another thread)."""
        loop = self._loop
        if loop is None:
            fn()
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            fn()
        else:
            loop.call_soon_threadsafe(fn)

    # ---- lock and tracking -------------------------------------------------------------------------------
    def _visible(self, smr_id: int) -> bool:
        return self.cell.smr_facing_angle_rad(smr_id) <= self.config.acceptance_half_angle_rad

    def _lock(self, smr_id: int) -> None:
        st = self.state
        st.locked_smr = smr_id
        st.lock_p_m = np.asarray(self.cell.smr_center_tracker(smr_id), dtype=float)
        st.lock_sim_s = self.cell.time_s
        st.lock_wall_s = self._loop.time() if self._loop else 0.0
        st.direction = st.lock_p_m / np.linalg.norm(st.lock_p_m)
        self._lock_generation += 1

    def _lose_lock(self, command: int = Command.UNKNOWN) -> None:
        st = self.state
        if st.locked_smr is None:
            return
        log.info("fake tracker: beam to SMR %s broken", st.locked_smr)
        st.locked_smr = None
        self._lock_generation += 1
        if st.settings[4]:
            self.broadcast(codec.pack_error(command, self.config.no_target_status))
        self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))

    def _track(self) -> None:
        """Follow the locked SMR; lose it if it moved faster than the tracker follows or turned away."""
        st = self.state
        if st.locked_smr is None:
            return
        p = np.asarray(self.cell.smr_center_tracker(st.locked_smr), dtype=float)
        wall = self.loop.time()
        dt = max(self.cell.time_s - st.lock_sim_s, wall - st.lock_wall_s, 0.0)
        allowed = self.config.capture_m + self.config.max_tracking_speed_m_s * dt
        if np.linalg.norm(p - st.lock_p_m) > allowed or not self._visible(st.locked_smr):
            self._lose_lock(Command.START_MEASUREMENT if st.measuring else Command.UNKNOWN)
            return
        st.lock_p_m, st.lock_sim_s, st.lock_wall_s = p, self.cell.time_s, wall
        st.direction = p / np.linalg.norm(p)

    async def _poll(self) -> None:
        while True:
            await asyncio.sleep(self.config.track_poll_s)
            try:
                self._track()
            except Exception:
                log.exception("fake tracker: tracking poll failed")

    def _search(self, p_aim_m: np.ndarray, radius_m: float) -> int | None:
        """The visible SMR nearest the aimed point within the search radius, if any."""
        best, best_d = None, radius_m
        for smr_id in self.cell.smr_ids:
            d = float(np.linalg.norm(self.cell.smr_center_tracker(smr_id) - p_aim_m))
            if d <= best_d and self._visible(smr_id):
                best, best_d = smr_id, d
        return best

    def _ready(self) -> bool:
        st = self.state
        return st.locked_smr is not None and st.laser_on and not self.faults.no_target

    def _acquire(self, p_aim_m: np.ndarray) -> bool:
        """Aim at a point and lock the SMR found there; announces the new state to every client."""
        st = self.state
        st.direction = p_aim_m / max(float(np.linalg.norm(p_aim_m)), 1e-9)
        blind = self.faults.no_target or not st.laser_on
        found = None if blind else self._search(p_aim_m, st.search_radius_m)
        if found is None:
            if st.locked_smr is not None:
                st.locked_smr = None
                self._lock_generation += 1
            self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))
            return False
        self._lock(found)
        self.broadcast(
            codec.pack_status_change(StatusChange.DISTANCE_SET),
            codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
        )
        return True

    # ---- environment -------------------------------------------------------------------------------------
    def _meteo(self) -> tuple[float, float, float]:
        """(°C, hPa, %RH) in use: the weather monitor (cell meteo) or the manual values."""
        if self.state.settings[0] == codec.WeatherMonitorStatus.NOT_CONNECTED and self.state.manual_meteo:
            return self.state.manual_meteo
        m = self.cell.meteo()
        return (m.temperature_c, m.pressure_hpa, m.humidity_pct)

    def _meteo_wire(self) -> tuple[float, float, float]:
        t, p, h = self._meteo()
        u = self.state.units
        return (u.temperature_to_wire(t), u.pressure_to_wire(p), h)

    # ---- commands ----------------------------------------------------------------------------------------
    async def handle(self, session: _Session, packet: bytes, command: int) -> None:
        """Answer one command packet on `session` (unsolicited events go to every client)."""
        try:
            known = Command(command)
        except ValueError:
            session.send(codec.pack_answer(command, Status.NOT_IMPLEMENTED))
            return
        self.state.command_counts[known.name] += 1
        try:
            cmd = codec.decode_client_packet(packet)
        except codec.CodecError:
            session.send(codec.pack_answer(command, Status.WRONG_PARAMETER))
            return
        self._track()
        handler = getattr(self, f"_cmd_{known.name.lower()}", None)
        if handler is None:
            session.send(codec.pack_answer(command, Status.NOT_IMPLEMENTED))
            return
        result = handler(session, *cmd.params)
        if asyncio.iscoroutine(result):
            result = await result
        if result is not None:  # (status, values...) of a plain answer
            session.send(codec.pack_answer(command, *result))

    def _cmd_exit_application(self, session):
        self.state.exit_requests += 1
        log.error("fake tracker: a client sent ExitApplication (would stop a real emScon server)")
        return (Status.NOT_IMPLEMENTED,)

    def _cmd_get_system_status(self, session):
        st, cfg = self.state, self.config
        tps = (
            codec.TrackerProcessorStatus.INITIALIZED
            if st.initialized
            else codec.TrackerProcessorStatus.COMPENSATION_SET
        )
        laser = codec.LaserStatus.LASER_READY if st.laser_on else codec.LaserStatus.LASER_OFF
        return (0, st.last_result_status, tps, laser, 2, *cfg.version, st.settings[0], 0, cfg.serial_number)

    def _cmd_get_tracker_status(self, session):
        if self.state.measuring:
            return (0, codec.TrackerStatus.BUSY)
        ready = self.state.initialized and self._ready()
        return (0, codec.TrackerStatus.READY if ready else codec.TrackerStatus.NOT_READY)

    def _cmd_get_measurement_status_info(self, session):
        st = self.state
        info = 1 | 2 | 4 | 8 | 4096
        if st.initialized:
            info |= codec.MSI_INITIALIZED
        if self._ready():
            info |= codec.MSI_REFLECTOR_FOUND
        return (0, st.last_result_status, info)

    def _changed(self, session, change: StatusChange, command: int):
        session.send(codec.pack_answer(command, Status.ALL_OK))
        self.broadcast(codec.pack_status_change(change))

    def _cmd_set_units(self, session, *values):
        try:
            self.state.units = codec.Units.from_tuple(values)
        except ValueError:
            bad = next(i for i in range(5) if not _valid_unit(i, values[i]))
            return (Status.WRONG_PARAMETER1 + bad,)
        self._changed(session, StatusChange.UNITS_CHANGED, Command.SET_UNITS)

    def _cmd_get_units(self, session):
        return (0, *self.state.units.as_tuple())

    async def _cmd_initialize(self, session):
        await asyncio.sleep(self.config.init_delay_s)
        self.state.initialized = True
        session.send(codec.pack_answer(Command.INITIALIZE, Status.ALL_OK))
        self.broadcast(codec.pack_status_change(StatusChange.INITIALIZATION_STATUS_CHANGED))
        if self._ready():
            self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_READY))

    def _cmd_set_measurement_mode(self, session, mode):
        if mode != codec.MeasMode.STATIONARY:
            return (Status.NOT_IMPLEMENTED,)
        self.state.meas_mode = mode
        self._changed(session, StatusChange.MEASUREMENT_MODE_CHANGED, Command.SET_MEASUREMENT_MODE)

    def _cmd_get_measurement_mode(self, session):
        return (0, self.state.meas_mode)

    def _cmd_set_stationary_mode_params(self, session, meas_time_ms, use_adm):
        if not 1 <= meas_time_ms <= 3_600_000:
            return (Status.PARAMETER1_OUT_OF_RANGE_NOK,)
        self.state.meas_time_ms, self.state.use_adm = meas_time_ms, bool(use_adm)
        self._changed(
            session, StatusChange.STATIONARY_MODE_PARAMS_CHANGED, Command.SET_STATIONARY_MODE_PARAMS
        )

    def _cmd_get_stationary_mode_params(self, session):
        return (0, self.state.meas_time_ms, int(self.state.use_adm))

    def _cmd_set_coordinate_system_type(self, session, cs):
        if cs not in codec.SUPPORTED_SYSTEMS:
            return (Status.NOT_IMPLEMENTED,)
        self.state.cs = CoordinateSystem(cs)
        self._changed(
            session, StatusChange.COORDINATE_SYSTEM_TYPE_CHANGED, Command.SET_COORDINATE_SYSTEM_TYPE
        )

    def _cmd_get_coordinate_system_type(self, session):
        return (0, self.state.cs)

    def _cmd_set_system_settings(self, session, *settings):
        if settings[0] not in (0, 1, 2):
            return (Status.WRONG_PARAMETER1,)
        self.state.settings = [int(v) for v in settings]
        self._changed(session, StatusChange.SYSTEM_SETTINGS_CHANGED, Command.SET_SYSTEM_SETTINGS)

    def _cmd_get_system_settings(self, session):
        return (0, *self.state.settings)

    def _cmd_set_statistic_mode(self, session, stationary, continuous):
        if stationary not in (0, 1) or continuous not in (0, 1):
            return (Status.WRONG_PARAMETER,)
        self.state.statistic_mode = (stationary, continuous)
        self._changed(session, StatusChange.STATISTIC_MODE_CHANGED, Command.SET_STATISTIC_MODE)

    def _cmd_get_statistic_mode(self, session):
        return (0, *self.state.statistic_mode)

    def _cmd_get_reflectors(self, session):
        refl = self.config.reflectors
        u = self.state.units
        session.send(
            *(
                codec.pack_answer(
                    Command.GET_REFLECTORS, 0, len(refl), r.id, r.target_type,
                    u.length_to_wire(r.surface_offset_m), codec.encode_name(r.name),
                )
                for r in refl
            )
        )  # fmt: skip

    def _cmd_set_reflector(self, session, reflector_id):
        if reflector_id not in {r.id for r in self.config.reflectors}:
            return (Status.WRONG_PARAMETER1,)
        self.state.reflector_id = reflector_id
        self._changed(session, StatusChange.REFLECTOR_CHANGED, Command.SET_REFLECTOR)

    def _cmd_get_reflector(self, session):
        return (0, self.state.reflector_id)

    def _cmd_set_environment_params(self, session, t, p, h):
        u, cfg = self.state.units, self.config
        t_c, p_hpa = u.temperature_from_wire(t), u.pressure_from_wire(p)
        ranges = (cfg.temperature_range_c, cfg.pressure_range_hpa, cfg.humidity_range_pct)
        if not all(lo <= v <= hi for v, (lo, hi) in zip((t_c, p_hpa, h), ranges, strict=True)):
            return (Status.METEO_DATA_OUT_OF_RANGE,)
        self.state.manual_meteo = (t_c, p_hpa, h)
        self._changed(session, StatusChange.ENVIRONMENT_PARAMS_CHANGED, Command.SET_ENVIRONMENT_PARAMS)

    def _cmd_get_environment_params(self, session):
        return (0, *self._meteo_wire())

    def _cmd_set_search_params(self, session, radius, timeout_ms):
        radius_m = self.state.units.length_from_wire(radius)
        if not radius_m > 0 or timeout_ms < 0:
            return (Status.WRONG_PARAMETER1 if not radius_m > 0 else Status.WRONG_PARAMETER2,)
        self.state.search_radius_m, self.state.search_timeout_ms = radius_m, timeout_ms
        self._changed(session, StatusChange.SEARCH_PARAMS_CHANGED, Command.SET_SEARCH_PARAMS)

    def _cmd_get_search_params(self, session):
        return (0, self.state.units.length_to_wire(self.state.search_radius_m), self.state.search_timeout_ms)

    def _cmd_stop_measurement(self, session):
        return (0,)

    def _wire_point(self, v1, v2, v3, spherical: bool) -> np.ndarray:
        """A point from the wire: in the current CS, or (HVD commands) always as Hz, V, D.

        HVD angles follow the current spherical convention when one is selected, else SCC (an assumption).
        """
        cs = self.state.cs
        if spherical and cs not in codec.SPHERICAL_SYSTEMS:
            cs = CoordinateSystem.SCC
        return codec.wire_to_cartesian(np.array([v1, v2, v3]), cs, self.state.units)

    async def _go(self, session, command: int, p_aim_m: np.ndarray, lock: bool) -> None:
        if not self.state.initialized:
            session.send(codec.pack_answer(command, Status.TRACKER_NOT_INITIALIZED))
            return
        if not np.all(np.isfinite(p_aim_m)):
            session.send(codec.pack_answer(command, Status.WRONG_PARAMETER))
            return
        await asyncio.sleep(self.config.motion_delay_s)
        if lock:
            self._acquire(p_aim_m)
        else:
            self.state.direction = p_aim_m / max(float(np.linalg.norm(p_aim_m)), 1e-9)
            if self.state.locked_smr is not None:
                self._lose_lock()
        session.send(codec.pack_answer(command, Status.ALL_OK))

    async def _cmd_go_position(self, session, v1, v2, v3, use_adm):
        await self._go(session, Command.GO_POSITION, self._wire_point(v1, v2, v3, False), True)

    async def _cmd_go_position_hvd(self, session, hz, vt, d, use_adm):
        await self._go(session, Command.GO_POSITION_HVD, self._wire_point(hz, vt, d, True), True)

    async def _cmd_point_laser(self, session, v1, v2, v3):
        await self._go(session, Command.POINT_LASER, self._wire_point(v1, v2, v3, False), False)

    async def _cmd_point_laser_hvd(self, session, hz, vt, d):
        await self._go(session, Command.POINT_LASER_HVD, self._wire_point(hz, vt, d, True), False)

    async def _cmd_find_reflector(self, session, approx_distance):
        if not self.state.initialized:
            return (Status.TRACKER_NOT_INITIALIZED,)
        distance_m = self.state.units.length_from_wire(approx_distance)
        if not distance_m > 0:
            return (Status.WRONG_PARAMETER1,)
        await asyncio.sleep(self.config.motion_delay_s)
        if not self._acquire(self.state.direction * distance_m):
            return (self.config.no_target_status,)
        return (0,)

    def _cmd_get_direction(self, session):
        cs = CoordinateSystem.SCW if self.state.cs == CoordinateSystem.SCW else CoordinateSystem.SCC
        hz, v, _ = codec.cartesian_to_wire(self.state.direction, cs, self.state.units)
        return (0, hz, v)

    async def _cmd_start_measurement(self, session):
        st = self.state
        if not st.initialized:
            st.last_result_status = Status.TRACKER_NOT_INITIALIZED
            return (Status.TRACKER_NOT_INITIALIZED,)
        if not self._ready():
            st.last_result_status = self.config.no_target_status
            return (self.config.no_target_status,)
        generation = self._lock_generation
        session.send(codec.pack_answer(Command.START_MEASUREMENT, Status.ALL_OK), flush=False)
        session.send(codec.pack_status_change(StatusChange.MEAS_STATUS_BUSY), flush=False)
        meas_s = st.meas_time_ms / 1000.0
        st.measuring += 1
        try:
            random_break = self.faults.beam_break_rate > 0 and self._fault_rng.random() < self.faults.beam_break_rate
            if self.faults.beam_break_count > 0 or random_break:
                self.faults.beam_break_count = max(0, self.faults.beam_break_count - 1)
                await self._pass_time(meas_s / 2)
                st.last_result_status = self.config.no_target_status
                session.send(codec.pack_error(Command.START_MEASUREMENT, self.config.no_target_status))
                self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))
                if self._ready():  # the SMR did not move: the tracker catches the beam again
                    self.broadcast(
                        codec.pack_status_change(StatusChange.DISTANCE_SET),
                        codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
                    )
                return None
            await self._pass_time(meas_s)
            self._track()
        finally:
            st.measuring -= 1
        if generation != self._lock_generation or not self._ready():
            st.last_result_status = self.config.no_target_status
            session.send(codec.pack_error(Command.START_MEASUREMENT, self.config.no_target_status))
            return None
        result = self._result_packet()
        self.sent_results.append(result)
        session.send(result, codec.pack_status_change(StatusChange.MEAS_STATUS_READY))
        st.last_result_status = 0
        return None

    async def _pass_time(self, dt_s: float) -> None:
        """Let dt_s of simulated time pass: advance the cell clock ourselves, or wait for its owner."""
        if self.config.advance_clock:
            await asyncio.sleep(dt_s * self.config.wall_time_scale)
            self.cell.advance_time(dt_s)
            return
        target = self.cell.time_s + dt_s
        while self.cell.time_s < target:
            await asyncio.sleep(self.config.external_clock_poll_s)

    def _result_packet(self) -> bytes:
        st = self.state
        p_m = np.asarray(self.cell.measure_smr(st.locked_smr), dtype=float)
        if self.faults.outlier_count > 0:
            self.faults.outlier_count -= 1
            p_m = p_m + np.array([self.faults.outlier_offset_m, 0.0, 0.0])
        sigma_m = float(self.cell.tracker_sigma_m(float(np.linalg.norm(p_m))))
        values = codec.cartesian_to_wire(p_m, st.cs, st.units)
        std = codec.cartesian_std_to_wire(np.full(3, sigma_m), p_m, st.cs, st.units)
        std_total = st.units.length_to_wire(math.sqrt(3.0) * sigma_m)
        return codec.pack_single_meas_result(
            0, values, std, std_total, std, std_total, self._meteo_wire(), extended=bool(st.statistic_mode[0])
        )

    # ---- the rest of the fact sheet's command subset ------------------------------------------------------
    def _cmd_set_temperature_range(self, session, value):
        if value not in (0, 1, 2, 3):
            return (Status.WRONG_PARAMETER1,)
        self.state.temperature_range = value
        self._changed(session, StatusChange.TEMPERATURE_RANGE_CHANGED, Command.SET_TEMPERATURE_RANGE)

    def _cmd_get_temperature_range(self, session):
        return (0, self.state.temperature_range)

    def _cmd_switch_laser(self, session, on):
        self.state.laser_on = bool(on)
        if not on:
            self._lose_lock()
        return (0,)

    def _cmd_set_station_orientation_params(self, session, *values):
        if any(values):  # the fake reports raw tracker-frame results only
            return (Status.NOT_IMPLEMENTED,)
        self.state.station_orientation = values
        self._changed(
            session, StatusChange.STATION_ORIENTATION_PARAMS_CHANGED, Command.SET_STATION_ORIENTATION_PARAMS
        )

    def _cmd_get_station_orientation_params(self, session):
        return (0, *self.state.station_orientation)

    def _cmd_set_transformation_params(self, session, *values):
        if any(values[:6]) or values[6] != 1.0:  # identity only, as above
            return (Status.NOT_IMPLEMENTED,)
        self.state.transformation = values
        self._changed(session, StatusChange.TRANSFORMATION_PARAMS_CHANGED, Command.SET_TRANSFORMATION_PARAMS)

    def _cmd_get_transformation_params(self, session):
        return (0, *self.state.transformation)

    def _cmd_set_refraction_params(self, session, ifm, adm):
        if not (1.0 <= ifm < 1.001 and 1.0 <= adm < 1.001):
            return (Status.WRONG_PARAMETER1 if not 1.0 <= ifm < 1.001 else Status.WRONG_PARAMETER2,)
        self.state.refraction = (ifm, adm)
        self._changed(session, StatusChange.REFRACTION_PARAMS_CHANGED, Command.SET_REFRACTION_PARAMS)

    def _cmd_get_refraction_params(self, session):
        return (0, *self.state.refraction)

    def _cmd_change_face(self, session):
        if not self.state.initialized:
            return (Status.TRACKER_NOT_INITIALIZED,)
        self.state.face = 2 if self.state.face == 1 else 1
        face_event = StatusChange.IS_FACE1 if self.state.face == 1 else StatusChange.IS_FACE2
        self._changed(session, face_event, Command.CHANGE_FACE)

    def _cmd_get_face(self, session):
        return (0, self.state.face)

    async def _cmd_go_bird_bath(self, session):
        await self._go(session, Command.GO_BIRD_BATH, np.array(self.config.birdbath_point_m), True)

    async def _cmd_go_bird_bath2(self, session, clockwise):
        await self._go(session, Command.GO_BIRD_BATH2, np.array(self.config.birdbath_point_m), True)

    def _cmd_get_tp_info(self, session):
        # boot, TP firmware and LCP firmware versions, processor type ATC900 (6), uP type, clock, sensor type
        return (0, 1, 0, 3, 2, 2, 1, 6, 0, 0, codec.LTS_AT901_LR)

    def _cmd_set_long_system_parameter(self, session, param, value):
        if param == codec.SP_TCP_COMMAND_QUEUE_SIZE and value != 0:
            return (Status.NOT_IMPLEMENTED,)  # the fake keeps the queue off: one command at a time
        self.state.long_params[param] = value
        return (0,)

    def _cmd_get_long_system_parameter(self, session, param):
        return (0, param, self.state.long_params.get(param, 0))

    def _cmd_set_double_system_parameter(self, session, param, value):
        self.state.double_params[param] = value
        return (0,)

    def _cmd_get_double_system_parameter(self, session, param):
        return (0, param, self.state.double_params.get(param, 0.0))

    def _cmd_get_object_temperature(self, session):
        return (0, self.state.units.temperature_to_wire(self.cell.meteo().temperature_c))

    def _cmd_clear_command_queue(self, session, which):
        return (0,) if which in (0, 1) else (Status.WRONG_PARAMETER1,)

    def _cmd_get_current_prism_position(self, session):
        if not self._ready():
            return (self.config.no_target_status,)
        st = self.state
        return (0, *codec.cartesian_to_wire(st.lock_p_m, st.cs, st.units))

    def _cmd_get_tracker_info(self, session):
        cfg, u = self.config, self.state.units
        return (
            0, codec.LTS_AT901_LR, codec.encode_name(cfg.tracker_name), cfg.serial_number, 1, 1, 1, 1,
            0.0, u.length_to_wire(cfg.max_distance_m), u.length_to_wire(cfg.min_distance_m), 1000, 2,
            u.angle_to_wire(2 * math.pi), u.angle_to_wire(math.radians(145.0)), 0, 1, 0,
        )  # fmt: skip

    def _cmd_get_system_software_version(self, session):
        return (0, codec.encode_name(".".join(map(str, self.config.version))))

    # ---- control channel (fault injection) ---------------------------------------------------------------
    def control_handlers(self) -> dict[str, Callable[[dict], dict]]:
        """Commands for the control channel: tracker.fault, tracker.clear, tracker.state, tracker.guide_beam."""
        return {
            "tracker.guide_beam": self._ctl_guide_beam,
            "tracker.fault": self._ctl_fault,
            "tracker.clear": self._ctl_clear,
            "tracker.state": self._ctl_state,
        }

    def _ctl_fault(self, request: dict) -> dict:
        """Inject a fault. kind: beam_break (count: the next N shots; rate: each shot with that chance), no_target, slow (delay_s), drop (when: next|now; TCP is
        closed, the serial line goes silent until cleared), garbage (n_bytes), inject (hex: raw bytes that
        replace the next answer), outlier (count, offset_m), framing (mode: normal|bytewise|merged), clear.
        """
        kind = request.get("kind")
        f = self.faults
        if kind == "beam_break":
            count = int(request.get("count", 1 if "rate" not in request else 0))
            rate = float(request.get("rate", 0.0))
            if count < 0 or not 0.0 <= rate < 1.0:
                raise ValueError("beam_break needs count >= 0 and rate in [0, 1)")
            f.beam_break_count, f.beam_break_rate = count, rate
        elif kind == "no_target":
            self._call_in_loop(self._block_beam)
        elif kind == "slow":
            delay = float(request.get("delay_s", 1.0))
            if not 0 <= delay <= 3600:
                raise ValueError("slow delay_s must be in [0, 3600]")
            f.slow_delay_s = delay
        elif kind == "drop":
            if request.get("when", "next") == "now":
                self._call_in_loop(self._drop_all)
            else:
                f.drop_next_command = True
        elif kind == "garbage":
            f.garbage_bytes = max(4, int(request.get("n_bytes", 32)))
        elif kind == "inject":
            try:
                f.inject = bytes.fromhex(str(request.get("hex", "")))
            except ValueError as exc:
                raise ValueError(f"inject needs 'hex': the bytes as a hex string ({exc})") from exc
            if not f.inject:
                raise ValueError("inject needs 'hex': at least one byte as a hex string")
        elif kind == "outlier":
            f.outlier_count = int(request.get("count", 1))
            f.outlier_offset_m = float(request.get("offset_m", 1e-3))
        elif kind == "framing":
            mode = request.get("mode", "normal")
            if mode not in ("normal", "bytewise", "merged"):
                raise ValueError("framing mode must be normal, bytewise or merged")
            f.framing = mode
        elif kind == "clear":
            return self._ctl_clear(request)
        else:
            raise ValueError(
                f"unknown tracker fault {kind!r}; use beam_break, no_target, slow, drop, garbage, inject, outlier, framing, clear"
            )
        return {"ok": True, "faults": f.to_dict()}

    def _ctl_guide_beam(self, request: dict) -> dict:
        """The operator's hand: catch the beam on SMR `smr_id` and let the tracker lock onto it."""
        smr_id = int(request.get("smr_id", 1))
        if smr_id not in self.cell.smr_ids:
            raise ValueError(f"no SMR {smr_id}; the cell has SMRs {self.cell.smr_ids}")
        if not self._visible(smr_id):
            raise ValueError(f"SMR {smr_id} faces away from the tracker: the beam cannot be caught on it")
        self._call_in_loop(lambda: self._acquire(np.asarray(self.cell.smr_center_tracker(smr_id), dtype=float)))
        return {"smr_id": smr_id}

    def _ctl_clear(self, request: dict) -> dict:
        was_blocked = self.faults.no_target
        self.faults = _Faults()
        if was_blocked:
            self._call_in_loop(self._unblock_beam)
        return {"ok": True, "faults": self.faults.to_dict()}

    def _block_beam(self) -> None:
        self.faults.no_target = True
        if self.state.settings[4]:
            self.broadcast(codec.pack_error(Command.UNKNOWN, self.config.no_target_status))
        self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))

    def _unblock_beam(self) -> None:
        self._track()
        if self._ready():
            self.broadcast(
                codec.pack_status_change(StatusChange.DISTANCE_SET),
                codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
            )

    def _drop_all(self) -> None:
        """TCP connections are closed; the serial line goes silent until the faults are cleared."""
        if self._pty_fds is not None:
            self.faults.line_down = True
        for session in list(self._sessions):
            if not session.is_serial:
                session.shutdown()

    def _ctl_state(self, request: dict) -> dict:
        st = self.state
        return {
            "url": self.url,
            "pty": self.pty_path,
            "clients": len(self._sessions),
            "initialized": st.initialized,
            "locked_smr": st.locked_smr,
            "units": st.units.as_tuple(),
            "coordinate_system": int(st.cs),
            "meas_time_ms": st.meas_time_ms,
            "reflector_id": st.reflector_id,
            "system_settings": list(st.settings),
            "exit_requests": st.exit_requests,
            "commands": dict(st.command_counts),
            "busy_replies": st.busy_replies,
            "faults": self.faults.to_dict(),
        }


def _valid_unit(index: int, value: int) -> bool:
    enums = (codec.LengthUnit, codec.AngleUnit, codec.TemperatureUnit, codec.PressureUnit, codec.HumidityUnit)
    return value in {int(e) for e in enums[index]}


class ServerThread:
    """Run an EmsconServer on its own asyncio loop in a background thread (tests, benchmarks, scripts)."""

    def __init__(self, server: EmsconServer):
        self.server = server
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="emscon-fake", daemon=True)

    def __enter__(self) -> EmsconServer:
        self._thread.start()
        self.run(self.server.start())
        return self.server

    def run(self, coro, timeout: float = 10.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, fn: Callable, *args):
        """Call fn(*args) on the server loop and return its result."""

        async def _wrapper():
            return fn(*args)

        return self.run(_wrapper())

    def __exit__(self, *exc) -> None:
        try:
            self.run(self.server.close())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5)
            self.loop.close()


def main(argv: list[str] | None = None) -> int:
    """Run the fake tracker alone on its own simulated cell (for trying the driver by hand)."""
    import argparse
    import json

    from fakes.cell import SimCellConfig, SimulatedCell

    parser = argparse.ArgumentParser(description="Fake Leica emScon tracker on a simulated cell.")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to bind")
    parser.add_argument("--port", type=int, default=7000, help="TCP port (700 needs root)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell")
    parser.add_argument("--pty", action="store_true", help="also serve on a pseudo-terminal")
    parser.add_argument("--lock", type=int, default=None, help="SMR id locked at start")
    args = parser.parse_args(argv)
    from fakes.launch import is_loopback_host

    if not is_loopback_host(args.host):
        parser.error("--host must be a loopback address (127.0.0.0/8)")

    async def serve() -> None:
        cell = SimulatedCell(SimCellConfig(seed=args.seed))
        server = EmsconServer(cell, args.host, args.port, EmsconServerConfig(initial_lock_smr=args.lock))
        await server.start()
        pty = await server.open_pty() if args.pty else None
        print(json.dumps({"tracker": {"url": server.url, "pty": pty}}), flush=True)
        try:
            await asyncio.Event().wait()
        finally:
            await server.close()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
