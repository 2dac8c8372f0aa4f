"""Dashboard server (port 29999) of the fake UR controller: one request line, one reply line.

Reply wording follows PolyScope's dashboard server as ur-rtde parses it (exact matches for play, stop,
pause and unlock protective stop). On e-Series in local mode, commands that change state are refused.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Protocol

from fakes.ur_modes import Personality

log = logging.getLogger(__name__)

GREETING = "Connected: Universal Robots Dashboard Server"
MAX_LINE = 4096

# Commands that change the robot's state; refused on e-Series while not in remote control.
_REMOTE_ONLY = {
    "power on",
    "power off",
    "brake release",
    "play",
    "stop",
    "pause",
    "unlock protective stop",
    "close safety popup",
    "restart safety",
    "load",
    "shutdown",
}
NOT_REMOTE = "Command is not allowed due to safety reasons"  # [A] wording


class DashboardController(Protocol):
    """What the dashboard reads and commands on the controller (fakes.ur_controller.UrController plays it)."""

    personality: Personality
    remote_control: bool
    serial_number: str
    robot_model_name: str
    loaded_program: str

    @property
    def robot_mode_name(self) -> str: ...

    @property
    def safety_mode_name(self) -> str: ...

    @property
    def program_running(self) -> bool: ...

    @property
    def program_state_name(self) -> str: ...

    @property
    def program_name(self) -> str: ...

    def dashboard_power_on(self) -> str: ...

    def dashboard_power_off(self) -> None: ...

    def dashboard_brake_release(self) -> str: ...

    def dashboard_unlock_protective_stop(self) -> str: ...

    def dashboard_restart_safety(self) -> str: ...

    def dashboard_play(self) -> str: ...

    def dashboard_stop(self) -> None: ...

    def dashboard_pause(self) -> str: ...


async def serve_dashboard(
    controller: DashboardController, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
) -> None:
    """Serve one dashboard client until it quits or disconnects."""
    try:
        writer.write((GREETING + "\n").encode())
        while True:
            raw = await reader.readline()
            if not raw:
                break
            if len(raw) > MAX_LINE:
                break
            line = raw.decode("utf-8", errors="replace").strip()
            if not line:
                continue
            reply = handle_command(controller, line)
            log.debug("dashboard: %r -> %r", line, reply)
            writer.write((reply + "\n").encode())
            await writer.drain()
            if line.lower() == "quit":
                break
    except (ConnectionError, asyncio.LimitOverrunError, ValueError):
        pass
    finally:
        with contextlib.suppress(Exception):
            writer.close()


def handle_command(c: DashboardController, line: str) -> str:
    """The reply line for one dashboard request."""
    lower = line.lower()
    verb = "load" if lower.startswith("load ") else lower
    p = c.personality
    if p.is_eseries and verb in _REMOTE_ONLY and not c.remote_control:
        return NOT_REMOTE
    if lower == "polyscopeversion":
        return p.polyscope_reply
    if lower == "version":
        return ".".join(map(str, p.version))
    if lower == "is in remote control":
        return "true" if c.remote_control else "false"
    if lower == "get serial number":
        return c.serial_number
    if lower == "get robot model":
        return c.robot_model_name
    if lower == "robotmode":
        return f"Robotmode: {c.robot_mode_name}"
    if lower in ("safetymode", "safetystatus"):
        return f"{'Safetymode' if lower == 'safetymode' else 'Safetystatus'}: {c.safety_mode_name}"
    if lower == "programstate":
        return f"{c.program_state_name} {c.program_name}"
    if lower == "running":
        return f"Program running: {'true' if c.program_running else 'false'}"
    if lower == "power on":
        return c.dashboard_power_on()
    if lower == "power off":
        c.dashboard_power_off()
        return "Powering off"
    if lower == "brake release":
        return c.dashboard_brake_release()
    if lower == "unlock protective stop":
        return c.dashboard_unlock_protective_stop()
    if lower == "close safety popup":
        return "closing safety popup"
    if lower == "close popup":
        return "closing popup"
    if lower.startswith("popup "):
        return "showing popup"
    if lower == "restart safety":
        return c.dashboard_restart_safety()
    if lower == "play":
        return c.dashboard_play()
    if lower == "stop":
        c.dashboard_stop()
        return "Stopped"
    if lower == "pause":
        return c.dashboard_pause()
    if verb == "load":
        name = line[5:].strip()
        c.loaded_program = name
        return f"Loading program: {name}"
    if lower == "get loaded program":
        return f"Loaded program: {c.loaded_program}" if c.loaded_program else "No program loaded"
    if lower == "isprogramsaved":
        return f"true {c.program_name}"
    if lower.startswith("addtolog "):
        return "Added log message"
    if lower == "get operational mode":
        return "NONE"
    if lower == "shutdown":
        c.dashboard_power_off()
        return "Shutting down"
    if lower == "quit":
        return "Disconnected"
    return f"could not understand: '{line}'"
