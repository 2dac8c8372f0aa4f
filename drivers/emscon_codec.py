"""Leica emScon TPI wire format: enums, packet layouts, pack/unpack and the incremental frame splitter.

Pure functions and tables only (no I/O), shared by the driver (drivers/emscon.py) and the fake tracker
(fakes/emscon_server.py) so that both directions use one source of truth for every layout. Everything is
little-endian with 4-byte packing and no padding (so `struct` with '<' is exact); `long` is 4 bytes.
Every packet starts with int32 total size (header included) and int32 data type.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

HEADER = struct.Struct("<ii")  # lPacketSize (total, header included), ES_DataType
HEADER_SIZE = HEADER.size
COMMAND_HEAD = struct.Struct("<iii")  # size, type=0, command
ANSWER_HEAD = struct.Struct("<iiii")  # size, type=0, command, status
RESULT_HEAD = struct.Struct("<iii")  # size, type, status (result packets have no command field)
MIN_PACKET_SIZE = 12  # the smallest packet on the wire (a command without parameters, an SSC)
MAX_PACKET_SIZE = 64 * 1024  # Leica's sample reads into a 64 KiB buffer; anything larger is a desync


class DataType(IntEnum):
    """ES_DataType: the header `type` field."""

    COMMAND = 0
    ERROR = 1
    SINGLE_MEAS_RESULT = 2
    MULTI_MEAS_RESULT = 3
    STATIONARY_PROBE_MEAS_RESULT = 4
    CONTINUOUS_PROBE_MEAS_RESULT = 5
    NIVEL_RESULT = 6
    REFLECTOR_POS_RESULT = 7
    SYSTEM_STATUS_CHANGE = 8
    SINGLE_MEAS_RESULT2 = 9
    MULTI_MEAS_RESULT2 = 10
    PROBE_POS_RESULT = 11


class Command(IntEnum):
    """ES_Command ids of the subset a stationary-point runner uses."""

    EXIT_APPLICATION = 0  # stops the emScon server: never sent by the driver
    GET_SYSTEM_STATUS = 1
    GET_TRACKER_STATUS = 2
    SET_TEMPERATURE_RANGE = 3
    GET_TEMPERATURE_RANGE = 4
    SET_UNITS = 5
    GET_UNITS = 6
    INITIALIZE = 7
    SWITCH_LASER = 11
    SET_STATION_ORIENTATION_PARAMS = 12
    GET_STATION_ORIENTATION_PARAMS = 13
    SET_TRANSFORMATION_PARAMS = 14
    GET_TRANSFORMATION_PARAMS = 15
    SET_ENVIRONMENT_PARAMS = 20
    GET_ENVIRONMENT_PARAMS = 21
    SET_REFRACTION_PARAMS = 22
    GET_REFRACTION_PARAMS = 23
    SET_MEASUREMENT_MODE = 24
    GET_MEASUREMENT_MODE = 25
    SET_COORDINATE_SYSTEM_TYPE = 26
    GET_COORDINATE_SYSTEM_TYPE = 27
    SET_STATIONARY_MODE_PARAMS = 28
    GET_STATIONARY_MODE_PARAMS = 29
    SET_CONTINUOUS_TIME_MODE_PARAMS = 30
    GET_CONTINUOUS_TIME_MODE_PARAMS = 31
    SET_REFLECTOR = 40
    GET_REFLECTOR = 41
    GET_REFLECTORS = 42
    SET_SEARCH_PARAMS = 43
    GET_SEARCH_PARAMS = 44
    SET_SYSTEM_SETTINGS = 47
    GET_SYSTEM_SETTINGS = 48
    START_MEASUREMENT = 49
    STOP_MEASUREMENT = 52
    CHANGE_FACE = 53
    GO_BIRD_BATH = 54
    GO_POSITION = 55
    GO_POSITION_HVD = 56
    POINT_LASER = 58
    POINT_LASER_HVD = 59
    FIND_REFLECTOR = 63
    UNKNOWN = 64
    GET_DIRECTION = 66
    SET_STATISTIC_MODE = 80
    GET_STATISTIC_MODE = 81
    GET_TP_INFO = 90
    GO_BIRD_BATH2 = 95
    GET_FACE = 98
    SET_LONG_SYSTEM_PARAMETER = 120
    GET_LONG_SYSTEM_PARAMETER = 121
    GET_MEASUREMENT_STATUS_INFO = 122
    GET_CURRENT_PRISM_POSITION = 124
    SET_DOUBLE_SYSTEM_PARAMETER = 125
    GET_DOUBLE_SYSTEM_PARAMETER = 126
    GET_OBJECT_TEMPERATURE = 127
    CLEAR_COMMAND_QUEUE = 130
    GET_TRACKER_INFO = 132
    GET_SYSTEM_SOFTWARE_VERSION = 142


class Status(IntEnum):
    """ES_ResultStatus values the driver and the fake act on (any other value is passed through as int)."""

    ALL_OK = 0
    SERVER_BUSY = 1
    NOT_IMPLEMENTED = 2
    WRONG_PARAMETER = 3
    WRONG_PARAMETER1 = 4
    WRONG_PARAMETER2 = 5
    WRONG_PARAMETER3 = 6
    PARAMETER1_OUT_OF_RANGE_NOK = 12
    WRONG_CURRENT_REFLECTOR = 23
    NO_WEATHERMONITOR_FOUND = 27
    UNKNOWN = 36
    NO_DISTANCE_SET = 37
    NO_TRACKER_CONNECTED = 38
    TRACKER_NOT_INITIALIZED = 39
    METEO_DATA_OUT_OF_RANGE = 57
    MEASUREMENT_STATUS_NOT_READY = 10004
    NO_STATIONARY_RESULT = 10009
    SYSTEM_NOT_READY_FOR_MEASUREMENT = 10014


# Statuses that mean "no target locked / beam broken / not ready to measure" (fact sheet §4.1).
NO_TARGET_STATUSES = frozenset(
    {
        Status.NO_DISTANCE_SET,
        Status.MEASUREMENT_STATUS_NOT_READY,
        Status.NO_STATIONARY_RESULT,
        Status.SYSTEM_NOT_READY_FOR_MEASUREMENT,
    }
)


class StatusChange(IntEnum):
    """ES_SystemStatusChange values of unsolicited events the fake sends and the driver tracks."""

    DISTANCE_SET = 0
    LASER_WARMED_UP = 1
    ENVIRONMENT_PARAMS_CHANGED = 2
    REFRACTION_PARAMS_CHANGED = 3
    SEARCH_PARAMS_CHANGED = 4
    UNITS_CHANGED = 6
    REFLECTOR_CHANGED = 7
    SYSTEM_SETTINGS_CHANGED = 8
    TEMPERATURE_RANGE_CHANGED = 9
    COORDINATE_SYSTEM_TYPE_CHANGED = 12
    STATION_ORIENTATION_PARAMS_CHANGED = 15
    TRANSFORMATION_PARAMS_CHANGED = 16
    MEASUREMENT_MODE_CHANGED = 17
    STATIONARY_MODE_PARAMS_CHANGED = 18
    CONTINUOUS_TIME_MODE_PARAMS_CHANGED = 19
    STATISTIC_MODE_CHANGED = 24
    MEAS_STATUS_NOT_READY = 25
    MEAS_STATUS_BUSY = 26
    MEAS_STATUS_READY = 27
    MEASUREMENT_COUNT_REACHED = 28
    IS_FACE1 = 30
    IS_FACE2 = 31
    INITIALIZATION_STATUS_CHANGED = 151
    TP_CONNECTION_CLOSING = 997
    SERVER_CLOSING = 998


class MeasMode(IntEnum):
    STATIONARY = 0
    CONTINUOUS_TIME = (
        1  # a sample every lTimeSeparation ms, streamed as MultiMeasResult until StopMeasurement
    )


class CoordinateSystem(IntEnum):
    """ES_CoordinateSystemType; RHR, SCW and SCC are the ones with documented component definitions."""

    RHR = 0
    LHRX = 1
    LHRY = 2
    LHRZ = 3
    CCW = 4
    CCC = 5
    SCW = 6
    SCC = 7


class TrackerStatus(IntEnum):
    NOT_READY = 0
    BUSY = 1
    READY = 2


class LaserStatus(IntEnum):
    LASER_READY = 3
    LASER_OFF = 5


class TrackerProcessorStatus(IntEnum):
    NO_TP_FOUND = 0
    COMPENSATION_SET = 4
    INITIALIZED = 5


class WeatherMonitorStatus(IntEnum):
    NOT_CONNECTED = 0
    READ_ONLY = 1
    READ_AND_CALCULATE_REFRACTIONS = 2


class StatisticMode(IntEnum):
    STANDARD = 0
    EXTENDED = 1


class LengthUnit(IntEnum):
    METER = 0
    MILLIMETER = 1
    MICRON = 2
    FOOT = 3
    YARD = 4
    INCH = 5


class AngleUnit(IntEnum):
    RADIAN = 0
    DEGREE = 1
    GON = 2


class TemperatureUnit(IntEnum):
    CELSIUS = 0
    FAHRENHEIT = 1


class PressureUnit(IntEnum):
    MBAR = 0
    HPASCAL = 1
    KPASCAL = 2
    MMHG = 3
    PSI = 4
    INH2O = 5
    INHG = 6


class HumidityUnit(IntEnum):
    RH = 0


LTS_AT901_LR = 15  # ES_LTSensorType of the fake (AT901 long range)
SP_TCP_COMMAND_QUEUE_SIZE = 200  # ES_SystemParameter: 0 = queue off (the default)
MSI_REFLECTOR_FOUND = 2048  # ES_MSI bits of GetMeasurementStatusInfo
MSI_INITIALIZED = 65536
MSI_TRACKER_FOUND = 1

# Leica's conversion factors: value_in_unit = value_in_base * factor (base: m, rad, mbar).
LENGTH_PER_METRE = {
    LengthUnit.METER: 1.0,
    LengthUnit.MILLIMETER: 1000.0,
    LengthUnit.MICRON: 1.0e6,
    LengthUnit.FOOT: 3.280839895,
    LengthUnit.YARD: 1.093613298,
    LengthUnit.INCH: 39.37007874,
}
ANGLE_PER_RADIAN = {AngleUnit.RADIAN: 1.0, AngleUnit.DEGREE: 180.0 / math.pi, AngleUnit.GON: 200.0 / math.pi}
PRESSURE_PER_MBAR = {
    PressureUnit.MBAR: 1.0,
    PressureUnit.HPASCAL: 1.0,
    PressureUnit.KPASCAL: 0.1,
    PressureUnit.MMHG: 1.0 / 1.33322,
    PressureUnit.PSI: 1.0 / 68.94757,
    PressureUnit.INH2O: 1.0 / 2.49082,
    PressureUnit.INHG: 1.0 / 33.86379,
}


@dataclass(frozen=True)
class Units:
    """The server-side unit selection (SetUnits), with conversions between SI and wire values."""

    length: LengthUnit = LengthUnit.METER
    angle: AngleUnit = AngleUnit.RADIAN
    temperature: TemperatureUnit = TemperatureUnit.CELSIUS
    pressure: PressureUnit = PressureUnit.HPASCAL
    humidity: HumidityUnit = HumidityUnit.RH

    def as_tuple(self) -> tuple[int, int, int, int, int]:
        return (
            int(self.length),
            int(self.angle),
            int(self.temperature),
            int(self.pressure),
            int(self.humidity),
        )

    @classmethod
    def from_tuple(cls, values: tuple[int, ...]) -> Units:
        """Build from the 5 wire ints; raises ValueError naming the first unknown enum value."""
        return cls(
            LengthUnit(values[0]),
            AngleUnit(values[1]),
            TemperatureUnit(values[2]),
            PressureUnit(values[3]),
            HumidityUnit(values[4]),
        )

    def length_to_wire(self, metres):
        return metres * LENGTH_PER_METRE[self.length]

    def length_from_wire(self, value):
        return value / LENGTH_PER_METRE[self.length]

    def angle_to_wire(self, radians):
        return radians * ANGLE_PER_RADIAN[self.angle]

    def angle_from_wire(self, value):
        return value / ANGLE_PER_RADIAN[self.angle]

    def temperature_to_wire(self, celsius: float) -> float:
        return celsius * 1.8 + 32.0 if self.temperature == TemperatureUnit.FAHRENHEIT else celsius

    def temperature_from_wire(self, value: float) -> float:
        return (value - 32.0) / 1.8 if self.temperature == TemperatureUnit.FAHRENHEIT else value

    def pressure_to_wire(self, hpa: float) -> float:
        return hpa * PRESSURE_PER_MBAR[self.pressure]

    def pressure_from_wire(self, value: float) -> float:
        return value / PRESSURE_PER_MBAR[self.pressure]


SPHERICAL_SYSTEMS = (CoordinateSystem.SCC, CoordinateSystem.SCW)
SUPPORTED_SYSTEMS = (CoordinateSystem.RHR, CoordinateSystem.SCW, CoordinateSystem.SCC)


def cartesian_to_wire(p_m: np.ndarray, cs: CoordinateSystem, units: Units) -> np.ndarray:
    """Tracker-frame Cartesian metres (..., 3) to (dVal1, dVal2, dVal3) in the given CS and units.

    Spherical: (Hz, V, D) with V the zenith angle and D the slope distance; SCC counts Hz counter-clockwise
    from +X towards +Y, SCW clockwise (Hz_cw = -Hz_ccw).
    """
    p_m = np.asarray(p_m, dtype=float)
    if cs == CoordinateSystem.RHR:
        return units.length_to_wire(p_m)
    if cs not in SPHERICAL_SYSTEMS:
        raise ValueError(f"coordinate system {cs!r} is not supported (use RHR, SCC or SCW)")
    d = np.linalg.norm(p_m, axis=-1)
    hz = np.arctan2(p_m[..., 1], p_m[..., 0])
    v = np.arccos(np.clip(p_m[..., 2] / np.where(d > 0, d, 1.0), -1.0, 1.0))
    if cs == CoordinateSystem.SCW:
        hz = -hz
    return np.stack([units.angle_to_wire(hz), units.angle_to_wire(v), units.length_to_wire(d)], axis=-1)


def wire_to_cartesian(values: np.ndarray, cs: CoordinateSystem, units: Units) -> np.ndarray:
    """Inverse of cartesian_to_wire: (dVal1, dVal2, dVal3) in CS/units to tracker-frame metres (..., 3)."""
    values = np.asarray(values, dtype=float)
    if cs == CoordinateSystem.RHR:
        return units.length_from_wire(values)
    if cs not in SPHERICAL_SYSTEMS:
        raise ValueError(f"coordinate system {cs!r} is not supported (use RHR, SCC or SCW)")
    hz = units.angle_from_wire(values[..., 0])
    v = units.angle_from_wire(values[..., 1])
    d = units.length_from_wire(values[..., 2])
    if cs == CoordinateSystem.SCW:
        hz = -hz
    return np.stack([d * np.sin(v) * np.cos(hz), d * np.sin(v) * np.sin(hz), d * np.cos(v)], axis=-1)


def spherical_std_to_cartesian_m(
    std_wire: np.ndarray, values_wire: np.ndarray, cs: CoordinateSystem, units: Units
) -> np.ndarray:
    """Per-component std-devs in metres: lengths as they are; spherical angle stds as arc lengths."""
    std_wire = np.asarray(std_wire, dtype=float)
    if cs == CoordinateSystem.RHR:
        return units.length_from_wire(std_wire)
    v = units.angle_from_wire(values_wire[..., 1])
    d = units.length_from_wire(values_wire[..., 2])
    s_hz = units.angle_from_wire(std_wire[..., 0]) * d * np.abs(np.sin(v))
    s_v = units.angle_from_wire(std_wire[..., 1]) * d
    return np.stack([s_hz, s_v, units.length_from_wire(std_wire[..., 2])], axis=-1)


def cartesian_std_to_wire(
    sigma_m: np.ndarray, p_m: np.ndarray, cs: CoordinateSystem, units: Units
) -> np.ndarray:
    """Inverse of spherical_std_to_cartesian_m for the fake: metres per component to wire std-devs."""
    sigma_m = np.asarray(sigma_m, dtype=float)
    if cs == CoordinateSystem.RHR:
        return units.length_to_wire(sigma_m)
    d = float(np.linalg.norm(p_m))
    horizontal = float(np.linalg.norm(np.asarray(p_m)[:2]))
    s_hz = sigma_m[0] / horizontal if horizontal > 0 else 0.0
    s_v = sigma_m[1] / d if d > 0 else 0.0
    return np.array([units.angle_to_wire(s_hz), units.angle_to_wire(s_v), units.length_to_wire(sigma_m[2])])


# ---- layouts ---------------------------------------------------------------------------------------------
# Parameters after the 12-byte command head (CT) and values after the 16-byte answer head (RT).
_EMPTY = struct.Struct("<")
# Keyed by Command; looked up by the raw int of a packet (an IntEnum member hashes and compares as its int).
COMMAND_PARAMS: dict[int, struct.Struct] = {
    Command.SET_TEMPERATURE_RANGE: struct.Struct("<i"),
    Command.SWITCH_LASER: struct.Struct("<i"),
    Command.SET_STATION_ORIENTATION_PARAMS: struct.Struct("<6d"),
    Command.SET_TRANSFORMATION_PARAMS: struct.Struct("<7d"),
    Command.SET_REFRACTION_PARAMS: struct.Struct("<2d"),
    Command.GO_BIRD_BATH2: struct.Struct("<i"),
    Command.SET_LONG_SYSTEM_PARAMETER: struct.Struct("<2i"),
    Command.GET_LONG_SYSTEM_PARAMETER: struct.Struct("<i"),
    Command.SET_DOUBLE_SYSTEM_PARAMETER: struct.Struct("<id"),
    Command.GET_DOUBLE_SYSTEM_PARAMETER: struct.Struct("<i"),
    Command.CLEAR_COMMAND_QUEUE: struct.Struct("<i"),
    Command.SET_UNITS: struct.Struct("<5i"),
    Command.SET_ENVIRONMENT_PARAMS: struct.Struct("<3d"),
    Command.SET_MEASUREMENT_MODE: struct.Struct("<i"),
    Command.SET_COORDINATE_SYSTEM_TYPE: struct.Struct("<i"),
    Command.SET_STATIONARY_MODE_PARAMS: struct.Struct("<2i"),
    # lTimeSeparation (ms), lNumberOfPoints (0: until StopMeasurement), bUseRegion, regionType
    Command.SET_CONTINUOUS_TIME_MODE_PARAMS: struct.Struct("<4i"),
    Command.SET_REFLECTOR: struct.Struct("<i"),
    Command.SET_SEARCH_PARAMS: struct.Struct("<di"),
    Command.SET_SYSTEM_SETTINGS: struct.Struct("<9i"),
    Command.GO_POSITION: struct.Struct("<3di"),
    Command.GO_POSITION_HVD: struct.Struct("<3di"),
    Command.POINT_LASER: struct.Struct("<3d"),
    Command.POINT_LASER_HVD: struct.Struct("<3d"),
    Command.FIND_REFLECTOR: struct.Struct("<d"),
    Command.SET_STATISTIC_MODE: struct.Struct("<2i"),
}
ANSWER_VALUES: dict[int, struct.Struct] = {
    Command.GET_TEMPERATURE_RANGE: struct.Struct("<i"),
    Command.GET_STATION_ORIENTATION_PARAMS: struct.Struct("<6d"),
    Command.GET_TRANSFORMATION_PARAMS: struct.Struct("<7d"),
    Command.GET_REFRACTION_PARAMS: struct.Struct("<2d"),
    Command.GET_TP_INFO: struct.Struct("<10i"),
    Command.GET_FACE: struct.Struct("<i"),
    Command.GET_LONG_SYSTEM_PARAMETER: struct.Struct("<2i"),
    Command.GET_CURRENT_PRISM_POSITION: struct.Struct("<3d"),
    Command.GET_DOUBLE_SYSTEM_PARAMETER: struct.Struct("<id"),
    Command.GET_OBJECT_TEMPERATURE: struct.Struct("<d"),
    # type, name, serial, compensation id, has ADM/overview camera/nivel, nivel mount offset, max/min
    # distance, max data rate, faces, Hz/V angle range, accuracy model, LCP firmware major/minor
    Command.GET_TRACKER_INFO: struct.Struct("<i64s5i3d2i2d3i"),
    Command.GET_SYSTEM_SOFTWARE_VERSION: struct.Struct("<64s"),
    Command.GET_SYSTEM_STATUS: struct.Struct("<10i"),
    Command.GET_TRACKER_STATUS: struct.Struct("<i"),
    Command.GET_UNITS: struct.Struct("<5i"),
    Command.GET_ENVIRONMENT_PARAMS: struct.Struct("<3d"),
    Command.GET_MEASUREMENT_MODE: struct.Struct("<i"),
    Command.GET_COORDINATE_SYSTEM_TYPE: struct.Struct("<i"),
    Command.GET_STATIONARY_MODE_PARAMS: struct.Struct("<2i"),
    Command.GET_CONTINUOUS_TIME_MODE_PARAMS: struct.Struct("<4i"),
    Command.GET_REFLECTOR: struct.Struct("<i"),
    Command.GET_REFLECTORS: struct.Struct("<3id64s"),
    Command.GET_SEARCH_PARAMS: struct.Struct("<di"),
    Command.GET_SYSTEM_SETTINGS: struct.Struct("<9i"),
    Command.GET_DIRECTION: struct.Struct("<2d"),
    Command.GET_STATISTIC_MODE: struct.Struct("<2i"),
    Command.GET_MEASUREMENT_STATUS_INFO: struct.Struct("<2i"),
}
SINGLE_MEAS_RESULT = struct.Struct("<2i17d")  # after the 12-byte result head; 156 bytes in total
SINGLE_MEAS_RESULT2 = struct.Struct("<2i23d")  # 204 bytes in total
REFLECTOR_POS_RESULT = struct.Struct("<3d")  # 36 bytes in total
# MultiMeasResult (type 3): after the 12-byte result head lNumberOfResults, measMode, bIsTryMode, dTemperature,
# dPressure, dHumidity (48 bytes with the head), then lNumberOfResults MeasValueT of 36 bytes each: status,
# lTime1 (s), lTime2 (us), dVal1..3
MULTI_MEAS_HEAD = struct.Struct("<3i3d")
MEAS_VALUE = struct.Struct("<3i3d")
ERROR_BODY = struct.Struct("<ii")  # command, status; 16 bytes in total
STATUS_CHANGE_BODY = struct.Struct("<i")  # 12 bytes in total


def command_params(command: int) -> struct.Struct:
    return COMMAND_PARAMS.get(command, _EMPTY)


def answer_values(command: int) -> struct.Struct:
    return ANSWER_VALUES.get(command, _EMPTY)


def encode_name(name: str, chars: int = 32) -> bytes:
    """Fixed-length UTF-16LE, NUL-padded (emScon `unsigned short name[32]`)."""
    raw = name.encode("utf-16-le")[: 2 * (chars - 1)]
    return raw.ljust(2 * chars, b"\0")


def decode_name(raw: bytes) -> str:
    return raw.decode("utf-16-le", errors="replace").split("\0", 1)[0]


# ---- packets ---------------------------------------------------------------------------------------------
class CodecError(ValueError):
    """A packet that cannot be what it claims to be; carries the offending bytes."""

    def __init__(self, message: str, data: bytes, packets: list[bytes] | None = None):
        super().__init__(f"{message} (bytes: {data[:64].hex(' ')}{' ...' if len(data) > 64 else ''})")
        self.data = bytes(data)
        self.packets = packets or []  # whole packets cut before the error (FrameSplitter.feed)


@dataclass(frozen=True)
class CommandPacket:
    """Client to server: a command with its (possibly empty) parameter tuple."""

    command: int
    params: tuple
    raw: bytes


@dataclass(frozen=True)
class AnswerPacket:
    """Server to client: the answer to `command`; `values` is None when status != 0 or when short."""

    command: int
    status: int
    values: tuple | None
    raw: bytes


@dataclass(frozen=True)
class ErrorPacket:
    command: int
    status: int
    raw: bytes


@dataclass(frozen=True)
class StatusChangePacket:
    change: int
    raw: bytes


@dataclass(frozen=True)
class MeasResultPacket:
    """A stationary result (type 2 or 9): values/std/apriori in wire CS and units, meteo in wire units."""

    data_type: int
    status: int
    meas_mode: int
    is_try_mode: bool
    values: tuple[float, float, float]
    std: tuple[float, float, float]
    std_total: float
    apriori_std: tuple[float, float, float]
    apriori_std_total: float
    temperature: float
    pressure: float
    humidity: float
    raw: bytes


@dataclass(frozen=True)
class ReflectorPosPacket:
    status: int
    values: tuple[float, float, float]
    raw: bytes


@dataclass(frozen=True)
class MultiMeasPacket:
    """A continuous-mode result (type 3): samples in wire CS and units, their tracker times, meteo in wire units."""

    status: int
    meas_mode: int
    is_try_mode: bool
    temperature: float
    pressure: float
    humidity: float
    sample_status: tuple[int, ...]
    times_s: tuple[float, ...]  # lTime1 + lTime2 * 1e-6 (seconds, microseconds)
    values: tuple[tuple[float, float, float], ...]
    raw: bytes


@dataclass(frozen=True)
class OtherPacket:
    """A packet of a type this codec does not interpret (skipped by size, as Leica's parser does)."""

    data_type: int
    raw: bytes


ServerPacket = (
    AnswerPacket
    | ErrorPacket
    | StatusChangePacket
    | MeasResultPacket
    | MultiMeasPacket
    | ReflectorPosPacket
    | OtherPacket
)


def pack_command(command: int, *params) -> bytes:
    body = command_params(command).pack(*params)
    return COMMAND_HEAD.pack(COMMAND_HEAD.size + len(body), DataType.COMMAND, int(command)) + body


def pack_answer(command: int, status: int, *values) -> bytes:
    """An answer; on failure (or without values) the value block is zero-filled to full size."""
    layout = answer_values(command)
    body = layout.pack(*values) if values else bytes(layout.size)
    return ANSWER_HEAD.pack(ANSWER_HEAD.size + len(body), DataType.COMMAND, int(command), int(status)) + body


def pack_error(command: int, status: int) -> bytes:
    return HEADER.pack(16, DataType.ERROR) + ERROR_BODY.pack(int(command), int(status))


def pack_status_change(change: int) -> bytes:
    return HEADER.pack(12, DataType.SYSTEM_STATUS_CHANGE) + STATUS_CHANGE_BODY.pack(int(change))


def pack_single_meas_result(
    status: int,
    values,
    std,
    std_total: float,
    apriori_std,
    apriori_std_total: float,
    meteo: tuple[float, float, float],
    extended: bool = False,
    meas_mode: int = MeasMode.STATIONARY,
    try_mode: bool = False,
) -> bytes:
    """SingleMeasResult (type 2, 156 B) or, with extended statistics, SingleMeasResult2 (type 9, 204 B).

    Pointing errors and covariances are sent as zero (the fake models neither).
    """
    v, s, a = (tuple(float(x) for x in t) for t in (values, std, apriori_std))
    if extended:
        fields = (
            *v,
            *s,
            std_total,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            *a,
            apriori_std_total,
            0.0,
            0.0,
            0.0,
            *meteo,
        )
        body = SINGLE_MEAS_RESULT2.pack(int(meas_mode), int(try_mode), *fields)
        data_type = DataType.SINGLE_MEAS_RESULT2
    else:
        fields = (*v, *s, std_total, 0.0, 0.0, 0.0, *a, apriori_std_total, *meteo)
        body = SINGLE_MEAS_RESULT.pack(int(meas_mode), int(try_mode), *fields)
        data_type = DataType.SINGLE_MEAS_RESULT
    return RESULT_HEAD.pack(RESULT_HEAD.size + len(body), data_type, int(status)) + body


def pack_reflector_pos(status: int, values) -> bytes:
    body = REFLECTOR_POS_RESULT.pack(*(float(x) for x in values))
    return RESULT_HEAD.pack(RESULT_HEAD.size + len(body), DataType.REFLECTOR_POS_RESULT, int(status)) + body


def pack_multi_meas_result(
    status: int,
    samples: list[tuple[float, tuple[float, float, float]]],
    meteo: tuple[float, float, float],
    meas_mode: int = MeasMode.CONTINUOUS_TIME,
) -> bytes:
    """MultiMeasResult (type 3): (time in s, values in wire units) per sample, each with status 0."""
    body = MULTI_MEAS_HEAD.pack(len(samples), int(meas_mode), 0, *(float(m) for m in meteo))
    for t_s, v in samples:
        seconds = math.floor(t_s)
        micros = min(round((t_s - seconds) * 1e6), 999_999)
        body += MEAS_VALUE.pack(0, int(seconds), int(micros), *(float(x) for x in v))
    return RESULT_HEAD.pack(RESULT_HEAD.size + len(body), DataType.MULTI_MEAS_RESULT, int(status)) + body


def _check_header(packet: bytes) -> tuple[int, int]:
    if len(packet) < HEADER_SIZE:
        raise CodecError(f"packet of {len(packet)} bytes is shorter than the 8-byte header", packet)
    size, data_type = HEADER.unpack_from(packet)
    if size != len(packet):
        raise CodecError(f"header says {size} bytes but the packet has {len(packet)}", packet)
    return size, data_type


def _need(packet: bytes, size: int, what: str) -> None:
    if len(packet) < size:
        raise CodecError(f"{what} needs {size} bytes, got {len(packet)}", packet)


def decode_server_packet(packet: bytes) -> ServerPacket:
    """Decode one complete server-to-client packet; raises CodecError when it cannot be what it claims."""
    size, data_type = _check_header(packet)
    if data_type == DataType.COMMAND:
        _need(packet, ANSWER_HEAD.size, "a command answer")
        _, _, command, status = ANSWER_HEAD.unpack_from(packet)
        layout = answer_values(command)
        values = None
        if status == Status.ALL_OK and size >= ANSWER_HEAD.size + layout.size:
            values = layout.unpack_from(packet, ANSWER_HEAD.size)
        elif status == Status.ALL_OK and layout.size:
            raise CodecError(
                f"answer to command {command} is {size} bytes, expected {16 + layout.size}", packet
            )
        return AnswerPacket(command, status, values, packet)
    if data_type == DataType.ERROR:
        _need(packet, 16, "an error packet")
        command, status = ERROR_BODY.unpack_from(packet, HEADER_SIZE)
        return ErrorPacket(command, status, packet)
    if data_type == DataType.SYSTEM_STATUS_CHANGE:
        _need(packet, 12, "a status change")
        return StatusChangePacket(STATUS_CHANGE_BODY.unpack_from(packet, HEADER_SIZE)[0], packet)
    if data_type in (DataType.SINGLE_MEAS_RESULT, DataType.SINGLE_MEAS_RESULT2):
        extended = data_type == DataType.SINGLE_MEAS_RESULT2
        layout = SINGLE_MEAS_RESULT2 if extended else SINGLE_MEAS_RESULT
        _need(packet, RESULT_HEAD.size + layout.size, "a single measurement result")
        status = RESULT_HEAD.unpack_from(packet)[2]
        f = layout.unpack_from(packet, RESULT_HEAD.size)
        mode, try_mode, d = f[0], f[1], f[2:]
        apriori_at = 13 if extended else 10
        return MeasResultPacket(
            data_type=data_type,
            status=status,
            meas_mode=mode,
            is_try_mode=bool(try_mode),
            values=tuple(d[0:3]),
            std=tuple(d[3:6]),
            std_total=d[6],
            apriori_std=tuple(d[apriori_at : apriori_at + 3]),
            apriori_std_total=d[apriori_at + 3],
            temperature=d[-3],
            pressure=d[-2],
            humidity=d[-1],
            raw=packet,
        )
    if data_type == DataType.MULTI_MEAS_RESULT:
        head = RESULT_HEAD.size + MULTI_MEAS_HEAD.size
        _need(packet, head, "a multi measurement result")
        status = RESULT_HEAD.unpack_from(packet)[2]
        n, mode, try_mode, t, p, h = MULTI_MEAS_HEAD.unpack_from(packet, RESULT_HEAD.size)
        if n < 0 or size != head + n * MEAS_VALUE.size:
            raise CodecError(f"a multi measurement result of {n} samples cannot be {size} bytes", packet)
        rows = [MEAS_VALUE.unpack_from(packet, head + i * MEAS_VALUE.size) for i in range(n)]
        return MultiMeasPacket(
            status=status,
            meas_mode=mode,
            is_try_mode=bool(try_mode),
            temperature=t,
            pressure=p,
            humidity=h,
            sample_status=tuple(r[0] for r in rows),
            times_s=tuple(r[1] + r[2] * 1e-6 for r in rows),
            values=tuple((r[3], r[4], r[5]) for r in rows),
            raw=packet,
        )
    if data_type == DataType.REFLECTOR_POS_RESULT:
        _need(packet, 36, "a reflector position result")
        status = RESULT_HEAD.unpack_from(packet)[2]
        return ReflectorPosPacket(status, REFLECTOR_POS_RESULT.unpack_from(packet, 12), packet)
    return OtherPacket(data_type, packet)


def decode_client_packet(packet: bytes) -> CommandPacket:
    """Decode one client-to-server packet (always a command); CodecError when malformed."""
    size, data_type = _check_header(packet)
    if data_type != DataType.COMMAND:
        raise CodecError(f"client sent data type {data_type}, only commands (0) are allowed", packet)
    _need(packet, COMMAND_HEAD.size, "a command")
    command = COMMAND_HEAD.unpack_from(packet)[2]
    layout = command_params(command)
    if size != COMMAND_HEAD.size + layout.size:
        raise CodecError(f"command {command} must be {12 + layout.size} bytes, got {size}", packet)
    return CommandPacket(command, layout.unpack_from(packet, COMMAND_HEAD.size), packet)


class FrameSplitter:
    """Incremental length-framed reader: feed any byte chunks, get whole packets back.

    Survives packets split anywhere (even inside the header) and several packets in one chunk. A size
    field outside [MIN_PACKET_SIZE, max_size] means the stream is out of step: CodecError, buffer kept
    for the caller to report and then `reset()`.
    """

    def __init__(self, max_size: int = MAX_PACKET_SIZE):
        self.max_size = max_size
        self._buffer = bytearray()

    def __len__(self) -> int:
        return len(self._buffer)

    def bytes_needed(self) -> int:
        """How many more bytes complete the next packet (or its size field); at least 1."""
        if len(self._buffer) < 4:
            return 4 - len(self._buffer)
        size = int.from_bytes(self._buffer[:4], "little", signed=True)
        if not MIN_PACKET_SIZE <= size <= self.max_size:
            return 1
        return max(1, size - len(self._buffer))

    def extend(self, data: bytes) -> None:
        self._buffer.extend(data)

    def pop(self) -> bytes | None:
        """Cut the next whole packet off the buffer, or None if it is not complete yet."""
        if len(self._buffer) < 4:
            return None
        size = int.from_bytes(self._buffer[:4], "little", signed=True)
        if not MIN_PACKET_SIZE <= size <= self.max_size:
            raise CodecError(f"implausible packet size {size}", bytes(self._buffer))
        if len(self._buffer) < size:
            return None
        packet = bytes(self._buffer[:size])
        del self._buffer[:size]
        return packet

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes and return every packet now complete (CodecError.packets keeps those cut before)."""
        self._buffer.extend(data)
        packets: list[bytes] = []
        while True:
            try:
                packet = self.pop()
            except CodecError as exc:
                exc.packets = packets
                raise
            if packet is None:
                return packets
            packets.append(packet)

    def reset(self) -> bytes:
        """Drop the buffered bytes (after a framing error) and return them."""
        dropped = bytes(self._buffer)
        self._buffer.clear()
        return dropped
