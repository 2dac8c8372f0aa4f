"""Instrument plug-ins: robot drivers, tracker drivers and simulated cells found by name through entry points.

A package (this repository's `drivers/` and `fakes/`, or a shop-floor team's own) declares its instruments in
the `hil.instruments` entry-point group of its pyproject.toml, e.g. `ur = "drivers.ur:plugin"`; the named
object has a `kind` ("robot", "tracker" or "simulator") and the methods of the Protocol of that kind below.
The core finds them with importlib.metadata and never imports their packages, so the core stands alone and
a new driver needs no change in hil.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING, Any, Literal, Protocol

from hil.errors import ActionableError

if TYPE_CHECKING:
    from hil.instruments.robot import Robot
    from hil.instruments.tracker import Tracker

GROUP = "hil.instruments"
Kind = Literal["robot", "tracker", "simulator"]
KINDS: tuple[Kind, ...] = ("robot", "tracker", "simulator")

DEFAULT_ROBOT_DRIVER = "ur"  # Universal Robots through ur-rtde (drivers/ur.py)
DEFAULT_TRACKER_DRIVER = "emscon"  # Leica emScon TPI over a pyserial URL (drivers/emscon.py)
DEFAULT_SIMULATOR = "sim"  # the simulated cell (fakes/)


class PluginError(ActionableError, LookupError):
    """An instrument plug-in that is not installed, failed to load or is of another kind: `message`, `remedy`."""

    def __init__(self, message: str, remedy: str):
        super().__init__(message, remedy)

    def text(self) -> str:
        """One "what is wrong; what to do" line, the form the command line splits into its two lines."""
        return f"{self.message}; {self.remedy}"


class PluginOptionError(PluginError, ValueError):
    """An option a plug-in cannot work with (e.g. an unknown effect of the simulated cell): `message`, `remedy`."""


class RobotDriver(Protocol):
    """A robot driver plug-in (kind "robot")."""

    kind: str
    summary: str  # one line for listings: which robots, through what

    def open(self, settings: Mapping[str, Any]) -> Robot:
        """Connect to the robot with the cell's robot settings (`host` and the driver's keys); raises RobotError."""
        ...


class TrackerDriver(Protocol):
    """A tracker driver plug-in (kind "tracker")."""

    kind: str
    summary: str

    def open(self, settings: Mapping[str, Any]) -> Tracker:
        """Connect to the tracker with its settings (`url`, `meas_time_s`, `reflector`, the driver's own keys);
        raises TrackerError (or OSError for an unreachable address)."""
        ...


class ControlChannel(Protocol):
    """The simulated cell's control channel: the hands of a scripted operator and the test's levers."""

    def call(self, cmd: str, **arguments: Any) -> Any: ...

    def close(self) -> None: ...


class RunningCell(Protocol):
    """A simulated cell started by `CellSimulator.launch`: its ready announcement and its control channel."""

    @property
    def info(self) -> dict:
        """The ready line: robot host, model and personality, tracker URL, control address."""
        ...

    @property
    def control(self) -> ControlChannel: ...

    @property
    def host(self) -> str: ...


class CellSimulator(Protocol):
    """A simulated cell plug-in (kind "simulator"): runs a cell in this process (`hil sim`) or in a child
    process (`hil demo`)."""

    kind: str
    summary: str
    description: str  # what `hil sim` does, for its --help

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add every option of the cell process to `parser` (for `hil sim`)."""
        ...

    def add_effects_argument(self, parser: argparse.ArgumentParser) -> None:
        """Add the option that chooses the cell's physical effects (for `hil demo`)."""
        ...

    def check_effects(self, args: argparse.Namespace) -> dict[str, bool]:
        """The effects chosen by the options of `add_effects_argument`; raises PluginOptionError."""
        ...

    def check_arguments(self, args: argparse.Namespace) -> None:
        """Refuse bad options of `add_arguments` with a PluginOptionError, before anything starts."""
        ...

    def serve(self, args: argparse.Namespace, on_ready: Callable[[dict, dict], None] | None = None) -> int:
        """Run the cell of the options of `add_arguments` until SIGINT/SIGTERM; `on_ready(info, truth)` once it
        listens. Raises PluginOptionError on a bad option; returns the exit status."""
        ...

    def launch(
        self,
        robot: str,
        seed: int,
        time_scale: float,
        effects: str,
        host: str | None = None,
        control_port: int = 0,
    ) -> AbstractContextManager[RunningCell]:
        """Start a cell in a child process on a free loopback address (or `host`, with its control channel on
        `control_port`, 0 any: the same cell again at the address a cell.toml names); stopped when the context
        ends."""
        ...

    def connect_control(self, address: str) -> ControlChannel:
        """A client of the control channel at `address` ("host:port", from the cell's ready line)."""
        ...

    def clock(self, control: ControlChannel) -> Callable[[], float]:
        """The cell's own clock, read through `control` (a channel `connect_control` opened; whoever opened it
        closes it), as UNIX seconds: the session's timestamps on this cell, so that the
        same seed and commands give the same times however loaded the machine."""
        ...


def installed() -> dict[str, EntryPoint]:
    """The instrument plug-ins installed in this environment, by name (nothing is imported)."""
    found: dict[str, EntryPoint] = {}
    for point in entry_points(group=GROUP):
        found.setdefault(point.name, point)  # the first distribution on the path wins, as for imports
    return found


def load(name: str, kind: Kind) -> Any:
    """The plug-in object registered as `name`; a PluginError names what is missing and what is installed."""
    found = installed()
    point = found.get(name)
    if point is None:
        known = ", ".join(sorted(found)) or "none"
        raise PluginError(
            f"no instrument plug-in named {name!r} is installed (entry-point group {GROUP}; installed: {known})",
            f"install the package that provides the {kind} {name!r}, or name an installed one",
        )
    plugin = _load(point)
    actual = getattr(plugin, "kind", None)
    if actual != kind:
        raise PluginError(
            f"instrument plug-in {name!r} ({point.value}) is a {actual or 'plug-in without a kind'}, not a {kind}",
            f"name a {kind} plug-in here",
        )
    return plugin


def robot_driver(name: str = DEFAULT_ROBOT_DRIVER) -> RobotDriver:
    """The robot driver plug-in `name`."""
    driver: RobotDriver = load(name, "robot")
    return driver


def tracker_driver(name: str = DEFAULT_TRACKER_DRIVER) -> TrackerDriver:
    """The tracker driver plug-in `name`."""
    driver: TrackerDriver = load(name, "tracker")
    return driver


def cell_simulator(name: str = DEFAULT_SIMULATOR) -> CellSimulator:
    """The simulated cell plug-in `name`."""
    simulator: CellSimulator = load(name, "simulator")
    return simulator


def _load(point: EntryPoint) -> Any:
    """Import the object an entry point names; an import failure becomes a PluginError naming the plug-in."""
    try:
        return point.load()
    except Exception as exc:  # any failure of third-party code at import time
        raise PluginError(
            f"instrument plug-in {point.name!r} ({point.value}) failed to load: {type(exc).__name__}: {exc}",
            "reinstall the package that provides it, or fix the error above",
        ) from exc
