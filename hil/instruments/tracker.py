"""The laser-tracker interface procedures use, its result types and its typed errors.

Nothing here knows about a wire protocol: drivers/emscon.py implements `Tracker` for Leica emScon
trackers, and any other tracker with a driver can run the same procedures. Everything is SI, tracker frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from hil.errors import ActionableError


@dataclass(frozen=True)
class TrackerMeasurement:
    """One averaged stationary measurement of the locked SMR (tracker frame, metres).

    `spread_m` is the sample std-dev over the kept shots (zeros for one shot); `std_m`/`std_total_m` the
    mean of the tracker's own per-shot std-devs; `rejected_shots` the indices of shots dropped as outliers.
    `temperature_c` is the air temperature the tracker used (its weather station or manual input);
    `object_temperature_c` the object probe's reading (the arm's own temperature), None without a probe.
    """

    p_tracker_m: np.ndarray  # (3,) mean of the kept shots
    spread_m: np.ndarray  # (3,) std-dev over the kept shots (ddof=1)
    std_m: np.ndarray  # (3,) tracker-reported std-devs, as lengths
    std_total_m: float
    shots_m: np.ndarray  # (N, 3) every shot as received, rejected ones included
    rejected_shots: tuple[int, ...]
    temperature_c: float
    pressure_hpa: float
    humidity_pct: float
    timestamp_s: float  # UNIX time (UTC) when the last shot arrived
    reflector_id: int | None = None
    object_temperature_c: float | None = None

    @property
    def shots_used(self) -> int:
        return len(self.shots_m) - len(self.rejected_shots)

    def to_dict(self) -> dict:
        """JSON-able record with units in the keys."""
        return {
            "x_m": float(self.p_tracker_m[0]),
            "y_m": float(self.p_tracker_m[1]),
            "z_m": float(self.p_tracker_m[2]),
            "spread_m": [float(v) for v in self.spread_m],
            "std_m": [float(v) for v in self.std_m],
            "std_total_m": float(self.std_total_m),
            "shots": len(self.shots_m),
            "rejected_shots": list(self.rejected_shots),
            "temperature_c": self.temperature_c,
            "pressure_hpa": self.pressure_hpa,
            "humidity_pct": self.humidity_pct,
            "timestamp_s": self.timestamp_s,
            "reflector_id": self.reflector_id,
            "object_temperature_c": self.object_temperature_c,
        }


@dataclass(frozen=True)
class TrackerState:
    """What a procedure needs to know before it asks for a measurement."""

    connected: bool
    initialized: bool
    target_locked: bool  # "ready to measure" (the tracker's traffic light is green)
    reflector_id: int | None = None
    last_error: str | None = None
    details: dict = field(default_factory=dict)


@runtime_checkable
class Tracker(Protocol):
    """A laser tracker as procedures see it."""

    def measure(self, shots: int = 1) -> TrackerMeasurement:
        """Measure the locked SMR `shots` times and average, rejecting outliers."""
        ...

    def point_at(self, p_tracker_m: np.ndarray) -> None:
        """Turn the beam to a point (tracker frame, m) and lock the SMR found there."""
        ...

    def find_target(self, approx_distance_m: float | None = None) -> None:
        """Search around the current beam direction and lock the reflector found."""
        ...

    def state(self) -> TrackerState: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class TrackerStream:
    """Samples of a moving SMR taken while a stream ran: the tracker's own sample times (s, its clock) and
    the positions (tracker frame, m), in time order."""

    t_s: np.ndarray  # (K,)
    p_tracker_m: np.ndarray  # (K, 3)


@runtime_checkable
class StreamingTracker(Tracker, Protocol):
    """A tracker that can also sample a moving SMR at a fixed interval (path measurements)."""

    def check_stream(self, interval_s: float) -> float:
        """Check, without measuring, that the tracker can sample every `interval_s`; returns the interval it
        will use. Raises TrackerError (with the reason) when it cannot."""
        ...

    def start_stream(self, interval_s: float) -> None:
        """Start sampling the locked SMR every `interval_s`; samples gather until stop_stream."""
        ...

    def stop_stream(self) -> TrackerStream:
        """Stop sampling and return every sample since start_stream; NoTargetError if the beam broke."""
        ...


class TrackerError(ActionableError):
    """Base of every tracker failure; `remedy` tells the operator or procedure what to do next."""

    remedy = "check the tracker and its connection, then run the command again"


class NoTargetError(TrackerError):
    """No target locked or the beam was broken."""

    remedy = "clear the line of sight between the tracker and the SMR and bring the beam back to the SMR, then run the command again"


class NotInitializedError(TrackerError):
    """The tracker is not initialized."""

    remedy = "initialize the tracker (hil tracker, or the tracker's own software; its head moves), then run the command again"


class MeteoOutOfRangeError(TrackerError):
    """Temperature, pressure or humidity out of the tracker's range."""

    remedy = "check the air temperature, pressure and humidity given to the tracker and their units"


class TrackerTimeoutError(TrackerError):
    """No answer within the command's timeout."""

    remedy = "check that the tracker is on and not busy with another program, then run the command again"


class TrackerConnectionError(TrackerError):
    """The byte stream could not be opened or was closed."""

    remedy = "check the cable or network and the tracker URL in the cell config, then run the command again"


class TrackerProtocolError(TrackerError):
    """Bytes that are not a valid packet of the protocol; `data` holds the bytes seen."""

    remedy = "check that the tracker URL in the cell config reaches an emScon server (port 700), then run the command again"

    def __init__(self, message: str, data: bytes = b""):
        super().__init__(message)
        self.data = bytes(data)


class TrackerCommandError(TrackerError):
    """The tracker refused a command with a status that has no dedicated error class."""

    remedy = "look the status up in the emScon manual, check the tracker's state, then run the command again"

    def __init__(self, message: str, command: int, status: int):
        super().__init__(message)
        self.command = command
        self.status = status


class OutlierError(TrackerError):
    """Too few shots survived outlier rejection to give a measurement."""

    remedy = "keep the SMR and the robot still (vibration, air flow), then measure again"


class TrackerConfigError(TrackerError, ValueError):
    """A driver setting that cannot work (unknown key, unit or coordinate system, bad time)."""

    remedy = "fix the setting named in the message; nothing was sent to the tracker"
