"""Leica emScon TPI driver: a `Tracker` over any pyserial URL (socket://host:700, /dev/ttyUSB0, rfc2217://...).

Wire units chosen on connect: metres and radians by default (°C, hPa, %RH for meteo); `length_unit` and
`angle_unit` may select others, and results are converted back, so callers always get SI metres in the
tracker frame. One command is in flight at a time (the server's TCP queue is off by default); answers are
matched by command id while unsolicited status changes and error packets interleave. After a timeout or
a protocol error the stream is resynchronised (drain, then a GetSystemStatus handshake) before the next
command; after a dropped connection the next call reconnects and repeats the connect-time setup.
ExitApplication (which stops the emScon server) is never sent.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import serial

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, CoordinateSystem, Status, StatusChange
from hil.instruments.tracker import (
    MeteoOutOfRangeError,
    NoTargetError,
    NotInitializedError,
    OutlierError,
    TrackerCommandError,
    TrackerConfigError,
    TrackerConnectionError,
    TrackerError,
    TrackerMeasurement,
    TrackerProtocolError,
    TrackerState,
    TrackerStream,
    TrackerTimeoutError,
)

log = logging.getLogger(__name__)

_STATUS_NAMES = {int(s): s.name for s in Status}


def _command_name(command: int) -> str:
    try:
        return Command(command).name
    except ValueError:
        return f"command {command}"


# Events announcing a change of server-side state the driver relies on, by the Set command that causes them.
_WATCHED_EVENTS = {
    Command.SET_UNITS: StatusChange.UNITS_CHANGED,
    Command.SET_COORDINATE_SYSTEM_TYPE: StatusChange.COORDINATE_SYSTEM_TYPE_CHANGED,
    Command.SET_MEASUREMENT_MODE: StatusChange.MEASUREMENT_MODE_CHANGED,
    Command.SET_STATIONARY_MODE_PARAMS: StatusChange.STATIONARY_MODE_PARAMS_CHANGED,
    Command.SET_STATISTIC_MODE: StatusChange.STATISTIC_MODE_CHANGED,
    Command.SET_SYSTEM_SETTINGS: StatusChange.SYSTEM_SETTINGS_CHANGED,
    Command.SET_REFLECTOR: StatusChange.REFLECTOR_CHANGED,
}
_OWN_EVENT_WINDOW_S = 2.0  # an event this soon after our own Set of its kind is taken as its echo


# Names accepted for the wire settings (besides the enum values themselves).
LENGTH_UNITS = {"m": codec.LengthUnit.METER, "mm": codec.LengthUnit.MILLIMETER, "um": codec.LengthUnit.MICRON,
                "in": codec.LengthUnit.INCH, "ft": codec.LengthUnit.FOOT}  # fmt: skip
ANGLE_UNITS = {"rad": codec.AngleUnit.RADIAN, "deg": codec.AngleUnit.DEGREE, "gon": codec.AngleUnit.GON}
COORDINATE_SYSTEMS = {"cartesian": CoordinateSystem.RHR, "spherical": CoordinateSystem.SCC,
                      "spherical_cw": CoordinateSystem.SCW}  # fmt: skip


def _choice(value, names: dict, option: str):
    """An enum value given as itself or by name; a clear error naming the choices otherwise."""
    if isinstance(value, str):
        if value not in names:
            raise TrackerConfigError(f"{option} must be one of {sorted(names)}, got {value!r}")
        return names[value]
    return value


def _serialised(method):
    """Run a public method under the driver's lock: one command in flight, even with several threads."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


def status_error(command: int, status: int, context: str = "") -> TrackerError:
    """The typed error for a non-zero ES_ResultStatus answering `command`."""
    name = _STATUS_NAMES.get(status, "?")
    what = f"{_command_name(command)} failed with status {status} ({name}){': ' + context if context else ''}"
    if status in codec.NO_TARGET_STATUSES:
        return NoTargetError(f"{what}; no target locked or beam broken")
    if status == Status.TRACKER_NOT_INITIALIZED:
        return NotInitializedError(f"{what}; the tracker is not initialized")
    if status == Status.METEO_DATA_OUT_OF_RANGE:
        return MeteoOutOfRangeError(f"{what}; temperature/pressure/humidity out of range")
    return TrackerCommandError(what, command, status)


@dataclass
class EmsconConfig:
    """Connection and connect-time settings of the emScon driver."""

    url: str = "socket://192.168.0.1:700"
    length_unit: codec.LengthUnit = codec.LengthUnit.METER
    angle_unit: codec.AngleUnit = codec.AngleUnit.RADIAN
    coordinate_system: CoordinateSystem = CoordinateSystem.RHR
    meas_time_s: float = 1.0  # stationary averaging time of one shot (SetStationaryModeParams)
    use_adm: bool = False
    reflector: str | int | None = None  # name or id to select on connect; None keeps the current one
    extended_statistics: bool = False  # results as SingleMeasResult2 (204 B) instead of SingleMeasResult
    auto_initialize: bool = True  # send Initialize on connect when the tracker is not initialized
    command_timeout_s: float = 10.0
    initialize_timeout_s: float = 120.0
    motion_timeout_s: float = 30.0  # GoPosition / FindReflector answer when the motion/search ends
    measurement_margin_s: float = 5.0  # StartMeasurement timeout = meas_time_s + this
    poll_s: float = 0.02  # read granularity; bounds how late a timeout is noticed
    baudrate: int = 115200  # only for real serial lines
    outlier_k: float = 5.0  # shots farther than k * median distance from the median point are outliers
    outlier_floor_m: float = 50e-6  # ...but never closer than this
    busy_retry_s: float = 0.02

    @classmethod
    def from_mapping(cls, values: dict) -> EmsconConfig:
        """Build from a cell configuration section (e.g. parsed TOML/JSON); unknown keys are an error."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise TrackerConfigError(f"unknown emScon settings {unknown}; known: {sorted(known)}")
        return cls(**values)

    def __post_init__(self) -> None:
        self.length_unit = _choice(self.length_unit, LENGTH_UNITS, "length_unit")
        self.angle_unit = _choice(self.angle_unit, ANGLE_UNITS, "angle_unit")
        self.coordinate_system = _choice(self.coordinate_system, COORDINATE_SYSTEMS, "coordinate_system")
        if not 0 < self.meas_time_s <= 3600:
            raise TrackerConfigError(f"meas_time_s must be in (0, 3600] s, got {self.meas_time_s}")
        if self.coordinate_system not in codec.SUPPORTED_SYSTEMS:
            raise TrackerConfigError(
                f"coordinate_system must be RHR, SCC or SCW, got {self.coordinate_system!r}"
            )


class EmsconTracker:
    """Leica emScon tracker driver implementing hil.instruments.tracker.Tracker."""

    def __init__(self, config: EmsconConfig):
        self.config = config
        self.units = codec.Units(length=config.length_unit, angle=config.angle_unit)
        self._lock = threading.RLock()
        self._port: serial.SerialBase | None = None
        self._splitter = codec.FrameSplitter()
        self._needs_resync = False
        self._ready = False  # connect-time setup done on the current port
        self.reflectors: dict[int, str] = {}
        self.tracker_info: dict = {}
        self.last_results: list[codec.MeasResultPacket] = []
        self.reflector_id: int | None = None
        self.initialized = False
        self.meas_ready: bool | None = None  # from MeasStatus SSC 25/26/27
        self.last_async_error: codec.ErrorPacket | None = None
        self.events: deque = deque(maxlen=100)  # (time, packet) of unsolicited traffic
        self._last_distance_m: float | None = None
        self.has_object_probe: bool | None = None  # unknown until GetObjectTemperature was asked once
        self._own_events: list[tuple[int, float]] = []  # (change, expiry) echoes expected of our own Sets
        self._settings_stale = False  # another client changed units/CS/mode: redo the connect-time setup
        self.foreign_setting_changes = 0
        self._deadline_cap: float | None = None
        self._streaming = False  # a continuous-time stream runs: its result packets are gathered
        self._stream_packets: list[codec.MultiMeasPacket] = []
        self._stream_error: codec.ErrorPacket | None = None

    # ---- lifecycle ---------------------------------------------------------------------------------------
    @_serialised
    def connect(self) -> EmsconTracker:
        """Open the byte stream and run the connect-time setup (idempotent)."""
        self._ensure_ready()
        return self

    def __enter__(self) -> EmsconTracker:
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    @_serialised
    def close(self) -> None:
        """Close the byte stream (never sends ExitApplication)."""
        if self._port is not None:
            with contextlib.suppress(OSError, serial.SerialException):
                self._port.close()
        self._port = None
        self._ready = False

    @property
    def connected(self) -> bool:
        return self._port is not None

    def _open(self) -> None:
        self.close()
        try:
            self._port = serial.serial_for_url(
                self.config.url, timeout=self.config.poll_s, baudrate=self.config.baudrate
            )
        except (OSError, ValueError, serial.SerialException) as exc:
            raise TrackerConnectionError(f"cannot open {self.config.url}: {exc}") from exc
        self._splitter.reset()
        self._needs_resync = False

    def _ensure_ready(self) -> None:
        if self._port is None:
            self._open()
        if self._settings_stale:
            log.warning("another client changed the tracker's settings: applying ours again")
            self._settings_stale = False
            self._ready = False
        if not self._ready:
            self._setup()
            self._ready = True

    def _setup(self) -> None:
        """Connect-time settings: units, init, measurement mode, CS, system settings, reflector."""
        cfg = self.config
        self._exchange(Command.SET_UNITS, *self.units.as_tuple())
        status = self._exchange(Command.GET_SYSTEM_STATUS)[0].values
        self.initialized = status[1] == codec.TrackerProcessorStatus.INITIALIZED
        self.tracker_info = self._read_tracker_info()
        if not self.initialized and cfg.auto_initialize:
            log.info("tracker not initialized: sending Initialize (the head moves)")
            self._exchange(Command.INITIALIZE, timeout=cfg.initialize_timeout_s)
            self.initialized = True
        self._exchange(Command.SET_MEASUREMENT_MODE, codec.MeasMode.STATIONARY)
        self._exchange(Command.SET_STATIONARY_MODE_PARAMS, round(cfg.meas_time_s * 1000), int(cfg.use_adm))
        self._exchange(Command.SET_COORDINATE_SYSTEM_TYPE, cfg.coordinate_system)
        settings = list(self._exchange(Command.GET_SYSTEM_SETTINGS)[0].values)
        wanted = list(settings)
        wanted[1] = 0  # bApplyTransformationParams: results in the raw tracker frame
        wanted[2] = 0  # bApplyStationOrientationParams
        wanted[4] = 1  # bSendUnsolicitedMessages: beam breaks arrive as error packets
        wanted[5] = 0  # bSendReflectorPositionData: no position stream
        wanted[6] = 0  # bTryMeasurementMode
        if wanted != settings:
            self._exchange(Command.SET_SYSTEM_SETTINGS, *wanted)
        self._exchange(Command.SET_STATISTIC_MODE, int(cfg.extended_statistics), 0)
        answers = self._exchange(Command.GET_REFLECTORS)
        self.reflectors = {a.values[1]: codec.decode_name(a.values[4]) for a in answers}
        if cfg.reflector is not None:
            rid = self._reflector_id(cfg.reflector)
            self._exchange(Command.SET_REFLECTOR, rid)
        self.reflector_id = self._exchange(Command.GET_REFLECTOR)[0].values[0]
        self._refresh_lock_state()

    def _read_tracker_info(self) -> dict:
        """Type, name, serial number and range of the tracker ({} if the server does not know the command)."""
        try:
            v = self._exchange(Command.GET_TRACKER_INFO)[0].values
        except TrackerCommandError as exc:
            log.info("GetTrackerInfo not available: %s", exc)
            return {}
        return {
            "tracker_type": v[0],
            "name": codec.decode_name(v[1]),
            "serial_number": v[2],
            "software_version": self._software_version(),
            "has_adm": bool(v[4]),
            "max_distance_m": float(self.units.length_from_wire(v[8])),
            "min_distance_m": float(self.units.length_from_wire(v[9])),
            "faces": v[11],
        }

    def _software_version(self) -> str:
        """The emScon server's software version, which a campaign keys the tracker by ("" when not known)."""
        try:
            return codec.decode_name(self._exchange(Command.GET_SYSTEM_SOFTWARE_VERSION)[0].values[0])
        except TrackerCommandError:
            return ""

    def _reflector_id(self, wanted: str | int) -> int:
        if isinstance(wanted, int):
            if wanted not in self.reflectors:
                raise ValueError(f"reflector id {wanted} unknown; the tracker has {self.reflectors}")
            return wanted
        for rid, name in self.reflectors.items():
            if name == wanted:
                return rid
        raise ValueError(f"reflector {wanted!r} unknown; the tracker has {sorted(self.reflectors.values())}")

    def _refresh_lock_state(self) -> None:
        last_status, info = self._exchange(Command.GET_MEASUREMENT_STATUS_INFO)[0].values
        self.meas_ready = bool(info & codec.MSI_REFLECTOR_FOUND)
        self.initialized = bool(info & codec.MSI_INITIALIZED)

    # ---- byte stream -------------------------------------------------------------------------------------
    @property
    def _open_port(self) -> serial.SerialBase:
        """The byte stream; every exchange runs after the connect-time setup has opened it."""
        if self._port is None:
            raise TrackerConnectionError(f"{self.config.url} is not open")
        return self._port

    def _lost(self, exc: Exception) -> TrackerConnectionError:
        url = self.config.url
        self.close()
        return TrackerConnectionError(f"connection to {url} lost: {exc}")

    def _write(self, data: bytes) -> None:
        try:
            self._open_port.write(data)
        except (OSError, serial.SerialException) as exc:
            raise self._lost(exc) from exc

    def _read_packet(self, deadline: float, what: str) -> codec.ServerPacket:
        """The next whole packet from the stream, or TrackerTimeoutError at `deadline`."""
        while True:
            if time.monotonic() >= deadline:  # checked first: a flood of events cannot outlast the timeout
                self._needs_resync = True
                raise TrackerTimeoutError(f"{what} did not come within the timeout")
            try:
                packet = self._splitter.pop()
            except codec.CodecError as exc:
                self._needs_resync = True
                self._splitter.reset()
                raise TrackerProtocolError(
                    f"framing error while waiting for {what}: {exc}", exc.data
                ) from exc
            if packet is not None:
                return self._decode(packet, what)
            try:
                data = self._open_port.read(self._splitter.bytes_needed())
            except (OSError, serial.SerialException) as exc:
                raise self._lost(exc) from exc
            self._splitter.extend(data)

    def _drain_pending(self, what: str) -> None:
        """Take in what the tracker sent before this command (events, a lost-lock error from the last move):
        noted as unsolicited, so an old error packet is never read as the answer to the new command."""
        while True:
            try:
                waiting = self._open_port.in_waiting
            except (OSError, serial.SerialException) as exc:
                raise self._lost(exc) from exc
            if not waiting:
                break
            try:
                self._splitter.extend(self._open_port.read(waiting))
            except (OSError, serial.SerialException) as exc:
                raise self._lost(exc) from exc
        while True:
            try:
                packet = self._splitter.pop()
            except codec.CodecError as exc:
                self._needs_resync = True
                self._splitter.reset()
                raise TrackerProtocolError(f"framing error before {what}: {exc}", exc.data) from exc
            if packet is None:
                return
            decoded = self._decode(packet, what)
            if isinstance(decoded, codec.ErrorPacket | codec.StatusChangePacket):
                self._note_unsolicited(decoded)
            elif not isinstance(decoded, codec.MultiMeasPacket):  # stream samples are gathered by _decode
                log.debug("dropping a stale %s received before %s", type(decoded).__name__, what)

    def _decode(self, packet: bytes, what: str) -> codec.ServerPacket:
        try:
            decoded = codec.decode_server_packet(packet)
        except codec.CodecError as exc:
            self._needs_resync = True
            raise TrackerProtocolError(f"bad packet while waiting for {what}: {exc}", exc.data) from exc
        if isinstance(decoded, codec.MultiMeasPacket):
            if self._streaming:
                self._stream_packets.append(decoded)
            else:
                log.debug("dropping a continuous-mode result nobody waits for")
        return decoded

    def _note_unsolicited(self, packet) -> None:
        self.events.append((time.time(), packet))
        if isinstance(packet, codec.StatusChangePacket):
            if packet.change in _WATCHED_EVENTS.values():
                self._note_setting_change(packet.change)
            if packet.change == StatusChange.MEAS_STATUS_READY:
                self.meas_ready = True
            elif packet.change == StatusChange.MEAS_STATUS_NOT_READY:
                self.meas_ready = False
        elif isinstance(packet, codec.ErrorPacket):
            self.last_async_error = packet
            if self._streaming and packet.command == Command.START_MEASUREMENT:
                self._stream_error = packet
            if packet.status in codec.NO_TARGET_STATUSES:
                self.meas_ready = False

    def _note_setting_change(self, change: int) -> None:
        """Our own Set's echo, or a change by another client (then our settings must be applied again)."""
        now = time.monotonic()
        self._own_events = [(c, t) for c, t in self._own_events if t > now]
        for i, (c, _) in enumerate(self._own_events):
            if c == change:
                del self._own_events[i]
                return
        self._settings_stale = True
        self.foreign_setting_changes += 1

    def _resync(self) -> None:
        """Bring the stream back in step: drain stale bytes, then handshake with GetSystemStatus."""
        deadline = self._deadline(self.config.command_timeout_s)
        self._needs_resync = False
        ping = codec.pack_command(Command.GET_SYSTEM_STATUS)
        while True:
            self._drain(deadline)
            self._write(ping)
            try:
                while True:
                    packet = self._read_packet(deadline, "the resync handshake")
                    if isinstance(packet, codec.AnswerPacket) and packet.command == Command.GET_SYSTEM_STATUS:
                        break
                    if isinstance(packet, codec.StatusChangePacket | codec.ErrorPacket):
                        self._note_unsolicited(packet)
            except TrackerProtocolError:
                continue  # garbage in the stream: drain again
            except TrackerTimeoutError:
                self._needs_resync = True
                raise
            if packet.status != Status.SERVER_BUSY:
                self._needs_resync = False
                return
            time.sleep(self.config.busy_retry_s)

    def _drain(self, deadline: float) -> None:
        """Discard input until the line has been quiet for one poll period."""
        self._splitter.reset()
        while time.monotonic() < deadline:
            try:
                data = self._open_port.read(4096) if self._open_port.in_waiting else b""
            except (OSError, serial.SerialException) as exc:
                raise self._lost(exc) from exc
            if not data:
                time.sleep(self.config.poll_s)
                try:
                    if not self._open_port.in_waiting:
                        return
                except (OSError, serial.SerialException) as exc:
                    raise self._lost(exc) from exc

    # ---- command exchange --------------------------------------------------------------------------------
    def _exchange(self, command: Command, *params, timeout: float | None = None, result: bool = False):
        """Send one command and wait for its answer(s) (and, with `result`, the measurement result).

        Returns the list of answer packets (GetReflectors: one per reflector), plus the result packet
        when `result` is set: (answers, result). Non-zero statuses raise their typed error.
        """
        if command == Command.EXIT_APPLICATION:
            raise ValueError("ExitApplication stops the emScon server; the driver never sends it")
        if self._port is None:
            self._open()
        if self._needs_resync:
            self._resync()
        deadline = self._deadline(self.config.command_timeout_s if timeout is None else timeout)
        what = f"the answer to {_command_name(command)}"
        data = codec.pack_command(command, *params)
        self._drain_pending(what)
        self._write(data)
        answers: list[codec.AnswerPacket] = []
        expected = 1
        measurement = None
        refused = False
        try:
            while True:
                packet = self._read_packet(deadline, what)
                if isinstance(packet, codec.AnswerPacket):
                    if packet.command != command:
                        log.debug("dropping a stale answer to %s", _command_name(packet.command))
                        continue
                    if packet.status == Status.SERVER_BUSY:
                        time.sleep(self.config.busy_retry_s)
                        self._write(data)
                        continue
                    if packet.status != Status.ALL_OK:
                        refused = True  # a refused command owes nothing more
                        raise status_error(command, packet.status)
                    answers.append(packet)
                    if command in _WATCHED_EVENTS:
                        self._own_events.append(
                            (_WATCHED_EVENTS[command], time.monotonic() + _OWN_EVENT_WINDOW_S)
                        )
                    if command == Command.GET_REFLECTORS:
                        if packet.values is None:
                            raise TrackerProtocolError(
                                "GetReflectors answered without a reflector count", packet.raw
                            )
                        expected = max(1, packet.values[0])
                elif isinstance(packet, codec.MeasResultPacket):
                    if not result:
                        log.debug("dropping a measurement result nobody waits for")
                        continue
                    if packet.status != Status.ALL_OK:
                        raise status_error(command, packet.status, "measurement result")
                    measurement = packet
                elif isinstance(packet, codec.ErrorPacket):
                    self._note_unsolicited(packet)
                    if packet.command == command or (result and packet.status in codec.NO_TARGET_STATUSES):
                        raise status_error(command, packet.status, "error packet")
                elif isinstance(packet, codec.StatusChangePacket):
                    self._note_unsolicited(packet)
                if len(answers) >= expected and (not result or measurement is not None):
                    return (answers, measurement) if result else answers
        except TrackerError:
            if not refused and (len(answers) < expected or (result and measurement is None)):
                self._needs_resync = True  # whatever is still owed may arrive later: resync first
            raise

    def _deadline(self, timeout_s: float) -> float:
        """Deadline of one exchange: its own timeout, capped by the public call's when it is retrying."""
        deadline = time.monotonic() + timeout_s
        return deadline if self._deadline_cap is None else min(deadline, self._deadline_cap)

    def _call(self, command: Command, *params, **kwargs):
        """Public-method entry: connect (or reconnect) as needed, then exchange.

        Units, CS and modes are server-side state shared by every client. If another client changed them
        while this command was on its way (its "...Changed" event arrived before the answer), the values
        exchanged may be in the other client's units: apply our settings again and repeat the command.
        """
        call_deadline = time.monotonic() + (kwargs.get("timeout") or self.config.command_timeout_s)
        try:
            for _attempt in range(3):
                self._ensure_ready()
                changes_before = self.foreign_setting_changes
                answer = self._exchange(command, *params, **kwargs)
                if self.foreign_setting_changes == changes_before:
                    return answer
                log.warning(
                    "tracker settings changed by another client during %s: repeating it",
                    _command_name(command),
                )
                self._deadline_cap = call_deadline  # setup and repeat must fit in the command's own timeout
        finally:
            self._deadline_cap = None
        raise TrackerError(
            "another client keeps changing the tracker's units/settings", "stop the other client, then retry"
        )

    # ---- Tracker API -------------------------------------------------------------------------------------
    @_serialised
    def measure(self, shots: int = 1) -> TrackerMeasurement:
        """`shots` stationary measurements of the locked SMR, averaged after rejecting outliers."""
        if not isinstance(shots, int) or shots < 1:
            raise ValueError(f"shots must be a positive integer, got {shots!r}")
        cfg = self.config
        timeout = cfg.meas_time_s + cfg.measurement_margin_s
        # Kept as received, raw bytes included, shot by shot: if the line drops at shot k, the shots
        # already taken stay readable in `last_results` (for records and debugging).
        packets: list = []
        self.last_results = packets
        for _ in range(shots):
            packets.append(self._call(Command.START_MEASUREMENT, timeout=timeout, result=True)[1])
        timestamp = time.time()
        cs = cfg.coordinate_system
        values = np.array([p.values for p in packets])
        for p in packets:
            if not np.all(
                np.isfinite([*p.values, *p.std, p.std_total, p.temperature, p.pressure, p.humidity])
            ):
                self._needs_resync = True
                raise TrackerProtocolError("measurement result with non-finite values", p.raw)
        shots_m = codec.wire_to_cartesian(values, cs, self.units)
        std_m = codec.spherical_std_to_cartesian_m(np.array([p.std for p in packets]), values, cs, self.units)
        std_total_m = self.units.length_from_wire(np.array([p.std_total for p in packets]))
        keep = self._inliers(shots_m, float(np.mean(std_total_m)))
        rejected = tuple(int(i) for i in np.flatnonzero(~keep))
        if keep.sum() < max(1, math.ceil(shots / 2)):
            raise OutlierError(
                f"{len(rejected)} of {shots} shots are outliers: the target moved or the beam wavered"
            )
        if rejected:
            log.warning("rejected %d of %d shots as outliers: %s", len(rejected), shots, rejected)
        kept = shots_m[keep]
        last = packets[-1]
        p_mean = kept.mean(axis=0)
        self._last_distance_m = float(np.linalg.norm(p_mean))
        object_temperature_c = self.object_temperature()
        return TrackerMeasurement(
            p_tracker_m=p_mean,
            spread_m=kept.std(axis=0, ddof=1) if len(kept) > 1 else np.zeros(3),
            std_m=std_m[keep].mean(axis=0),
            std_total_m=float(std_total_m[keep].mean()),
            shots_m=shots_m,
            rejected_shots=rejected,
            temperature_c=float(self.units.temperature_from_wire(last.temperature)),
            pressure_hpa=float(self.units.pressure_from_wire(last.pressure)),
            humidity_pct=float(last.humidity),
            timestamp_s=timestamp,
            reflector_id=self.reflector_id,
            object_temperature_c=object_temperature_c,
        )

    # ---- continuous-time stream (StreamingTracker) ------------------------------------------------------
    def _stream_mode(self, interval_s: float) -> int:
        """Continuous-time mode with a sample every interval_s (whole ms); returns the separation in ms."""
        ms = round(float(interval_s) * 1000.0)
        if not (math.isfinite(interval_s) and 1 <= ms <= 60_000):
            raise TrackerConfigError(
                f"stream interval {interval_s} s: give 0.001 .. 60 s (whole milliseconds)"
            )
        try:
            self._call(Command.SET_CONTINUOUS_TIME_MODE_PARAMS, ms, 0, 0, 0)
            self._call(Command.SET_MEASUREMENT_MODE, codec.MeasMode.CONTINUOUS_TIME)
        except TrackerCommandError as exc:
            raise TrackerCommandError(
                f"the tracker cannot sample a moving SMR every {ms} ms (continuous time mode refused: {exc})",
                exc.command,
                exc.status,
            ) from exc
        return ms

    @_serialised
    def check_stream(self, interval_s: float) -> float:
        """Set continuous-time mode up and back to stationary: the tracker accepts it, nothing is measured."""
        try:
            ms = self._stream_mode(interval_s)
        finally:
            self._call(Command.SET_MEASUREMENT_MODE, codec.MeasMode.STATIONARY)
        return ms / 1000.0

    @_serialised
    def start_stream(self, interval_s: float) -> None:
        """Continuous-time mode, then StartMeasurement: MultiMeasResult packets gather until stop_stream."""
        self._stream_packets = []
        self._stream_error = None
        try:
            self._stream_mode(interval_s)
            self._streaming = True
            self._call(Command.START_MEASUREMENT)
        except TrackerError:
            self._streaming = False
            with contextlib.suppress(TrackerError):
                self._call(Command.SET_MEASUREMENT_MODE, codec.MeasMode.STATIONARY)
            raise

    @_serialised
    def stop_stream(self) -> TrackerStream:
        """StopMeasurement (the samples sent before it arrive first), back to stationary mode, the samples."""
        try:
            self._call(Command.STOP_MEASUREMENT)
        finally:
            self._streaming = False
            self._call(Command.SET_MEASUREMENT_MODE, codec.MeasMode.STATIONARY)
        packets, self._stream_packets = self._stream_packets, []
        ok = [
            (t, v)
            for p in packets
            if p.status == Status.ALL_OK
            for t, v, st in zip(p.times_s, p.values, p.sample_status, strict=True)
            if st == 0
        ]
        if self._stream_error is not None:
            error, self._stream_error = self._stream_error, None
            raise status_error(
                Command.START_MEASUREMENT, error.status, f"the beam broke after {len(ok)} samples"
            )
        t = np.array([s[0] for s in ok], float)
        values = np.array([s[1] for s in ok], float).reshape(-1, 3)
        p = codec.wire_to_cartesian(values, self.config.coordinate_system, self.units) if len(ok) else values
        order = np.argsort(t, kind="stable")
        return TrackerStream(t[order], np.asarray(p, float).reshape(-1, 3)[order])

    def _inliers(self, shots_m: np.ndarray, std_total_m: float) -> np.ndarray:
        """Mask of shots within max(k * median distance, floor, 4 * reported std) of the median point."""
        if len(shots_m) < 3:
            return np.ones(len(shots_m), dtype=bool)
        distance = np.linalg.norm(shots_m - np.median(shots_m, axis=0), axis=1)
        limit = max(
            self.config.outlier_k * float(np.median(distance)), self.config.outlier_floor_m, 4 * std_total_m
        )
        return distance <= limit

    @_serialised
    def point_at(self, p_tracker_m) -> None:
        """GoPosition to a tracker-frame point (m); raises NoTargetError if no SMR is locked there."""
        p = np.asarray(p_tracker_m, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"point_at needs a finite (3,) point in metres, got {p_tracker_m!r}")
        wire = codec.cartesian_to_wire(p, self.config.coordinate_system, self.units)
        self._call(Command.GO_POSITION, *map(float, wire), 1, timeout=self.config.motion_timeout_s)
        self._refresh_lock_state()
        if not self.meas_ready:
            raise NoTargetError(f"no reflector locked after aiming at {p.tolist()} m")
        self._last_distance_m = float(np.linalg.norm(p))

    @_serialised
    def find_target(self, approx_distance_m: float | None = None) -> None:
        """FindReflector around the current direction at about `approx_distance_m` (default: last distance)."""
        distance = approx_distance_m or self._last_distance_m
        if distance is None or not distance > 0:
            raise ValueError("find_target needs approx_distance_m (no previous measurement to take it from)")
        self._call(
            Command.FIND_REFLECTOR,
            float(self.units.length_to_wire(distance)),
            timeout=self.config.motion_timeout_s,
        )
        self._refresh_lock_state()
        if not self.meas_ready:
            raise NoTargetError(f"no reflector found at about {distance:.3f} m")

    @_serialised
    def state(self) -> TrackerState:
        """Ask the tracker for its state (connects if needed)."""
        try:
            status = self._call(Command.GET_SYSTEM_STATUS)[0].values
            self._refresh_lock_state()
        except TrackerConnectionError as exc:
            return TrackerState(connected=False, initialized=False, target_locked=False, last_error=str(exc))
        error = self.last_async_error
        return TrackerState(
            connected=True,
            initialized=self.initialized,
            target_locked=bool(self.meas_ready),
            reflector_id=self.reflector_id,
            last_error=None if error is None else f"command {error.command} status {error.status}",
            details={
                "tracker_processor_status": status[1],
                "laser_status": status[2],
                "adm_status": status[3],
                "server_version": f"{status[4]}.{status[5]}.{status[6]}",
                "weather_monitor_status": status[7],
                "serial_number": status[9],
                "reflectors": dict(self.reflectors),
                "tracker_info": dict(self.tracker_info),
            },
        )

    @_serialised
    def environment(self) -> tuple[float, float, float]:
        """(temperature_c, pressure_hpa, humidity_pct) the tracker currently uses."""
        t, p, h = self._call(Command.GET_ENVIRONMENT_PARAMS)[0].values
        return self.units.temperature_from_wire(t), self.units.pressure_from_wire(p), h

    @_serialised
    def object_temperature(self) -> float | None:
        """The object probe's temperature (°C), None when the tracker has no probe (asked once, then remembered)."""
        if self.has_object_probe is False:
            return None
        try:
            (t,) = self._call(Command.GET_OBJECT_TEMPERATURE)[0].values
        except TrackerCommandError as exc:
            # Which status a tracker without the probe answers is not documented: any refusal without a
            # dedicated error class means "no object temperature".
            log.info("no object temperature: %s", exc)
            self.has_object_probe = False
            return None
        t_c = float(self.units.temperature_from_wire(t))
        if not math.isfinite(t_c):
            self._needs_resync = True
            raise TrackerProtocolError("object temperature is not finite")
        self.has_object_probe = True
        return t_c

    @_serialised
    def set_environment(self, temperature_c: float, pressure_hpa: float, humidity_pct: float) -> None:
        """Manual meteo input (trackers without a weather monitor); MeteoOutOfRangeError when implausible."""
        self._call(
            Command.SET_ENVIRONMENT_PARAMS,
            self.units.temperature_to_wire(temperature_c),
            self.units.pressure_to_wire(pressure_hpa),
            float(humidity_pct),
        )

    @_serialised
    def initialize(self) -> None:
        """Run the tracker's initialization (the head moves; can take tens of seconds)."""
        self._call(Command.INITIALIZE, timeout=self.config.initialize_timeout_s)
        self.initialized = True


class EmsconDriver:
    """The `emscon` instrument plug-in (entry point in pyproject.toml): Leica trackers through emScon TPI."""

    kind = "tracker"
    summary = "Leica laser trackers through emScon TPI over a pyserial URL"

    def open(self, settings: Mapping[str, Any]) -> EmsconTracker:
        """Connect with the tracker settings (`url`, `meas_time_s`, `reflector` and EmsconConfig's keys);
        a failed connect leaves nothing open."""
        tracker = EmsconTracker(EmsconConfig.from_mapping(dict(settings)))
        try:
            tracker.connect()
        except BaseException:
            tracker.close()
            raise
        return tracker


plugin = EmsconDriver()
