"""UR controller state codes as RTDE reports them (robot mode, safety mode, program runtime state) and the
controller generations the fake plays."""

from __future__ import annotations

from dataclasses import dataclass

ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
}
POWER_OFF, IDLE, RUNNING = 3, 5, 7
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
}
NORMAL, PROTECTIVE_STOP, ROBOT_EMERGENCY_STOP = 1, 3, 7
STOPPING, STOPPED, PLAYING, PAUSING, PAUSED, RESUMING = 0, 1, 2, 3, 4, 5


@dataclass(frozen=True)
class Personality:
    """Controller generation: version replies, control frequency and remote-control gating."""

    name: str
    version: tuple[int, int, int, int]
    frequency_hz: float
    release_date: str

    @property
    def is_eseries(self) -> bool:
        return self.version[0] >= 5

    @property
    def polyscope_reply(self) -> str:
        return f"URSoftware {'.'.join(map(str, self.version))} ({self.release_date})"


PERSONALITIES: dict[str, Personality] = {
    "cb3": Personality("cb3", (3, 15, 7, 106331), 125.0, "Sep 29 2021"),
    "eseries": Personality("eseries", (5, 11, 1, 108318), 500.0, "Mar 22 2021"),
}
