"""The fake emScon tracker's configuration and the server-side state every client shares.

Also the one thing the other parts of the fake ask of a client byte stream (`Client`: send packets), so that
measurement and command code need not know whether the client is a TCP connection or the serial line.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from drivers import emscon_codec as codec
from drivers.emscon_codec import CoordinateSystem, Status


class Client(Protocol):
    """A client byte stream as the command and measurement code sees it."""

    def send(self, *packets: bytes, flush: bool = True) -> None:
        """Queue packets for the client; flush ends the command's output."""


@dataclass(frozen=True)
class Reflector:
    """A reflector the fake offers in GetReflectors."""

    id: int
    name: str
    target_type: int  # ES_TargetType
    surface_offset_m: float = 0.0


MANUAL_METEO_DEFAULT = (20.0, 1013.25, 50.0)  # degC, hPa, %RH a tracker without a monitor starts from


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
    # False: a tracker without a weather monitor. Its refraction (so every distance) follows the meteo the client
    # enters (SetEnvironmentParams), MANUAL_METEO_DEFAULT until then; asking for the monitor is refused.
    weather_monitor: bool = True
    object_probe: bool = True  # an object-temperature probe on the arm (GetObjectTemperature answers)
    # What GetObjectTemperature answers without the probe: not documented, so configurable (NotImplemented).
    no_object_probe_status: int = Status.NOT_IMPLEMENTED
    continuous_modes: bool = (
        True  # False: an older tracker, continuous measurement modes answer NotImplemented
    )
    min_time_separation_ms: int = 1  # fastest continuous-time sampling the fake accepts (1 kHz)


@dataclass
class TrackerState:
    """The server-side state every client shares."""

    units: codec.Units = field(default_factory=codec.Units)
    cs: CoordinateSystem = CoordinateSystem.RHR
    meas_mode: int = 0
    meas_time_ms: int = 1000
    # continuous-time mode: lTimeSeparation (ms), lNumberOfPoints (0: until StopMeasurement), bUseRegion, regionType
    continuous_time: tuple[int, int, int, int] = (100, 0, 0, 0)
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

    @classmethod
    def powered_on(cls, config: EmsconServerConfig) -> TrackerState:
        """A tracker's state as it powers on with `config`: without a weather monitor, its settings say so and
        its refraction starts from MANUAL_METEO_DEFAULT."""
        state = cls(
            initialized=config.initialized,
            search_radius_m=config.search_radius_m,
            search_timeout_ms=config.search_timeout_ms,
        )
        if not config.weather_monitor:
            state.settings[0] = codec.WeatherMonitorStatus.NOT_CONNECTED
            state.manual_meteo = MANUAL_METEO_DEFAULT
        return state


def valid_unit(index: int, value: int) -> bool:
    """Whether `value` is a member of the index-th unit enum of SetUnits (length, angle, temperature, pressure, humidity)."""
    enums = (codec.LengthUnit, codec.AngleUnit, codec.TemperatureUnit, codec.PressureUnit, codec.HumidityUnit)
    return value in {int(e) for e in enums[index]}
