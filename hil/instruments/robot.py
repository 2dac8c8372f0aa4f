"""The `Robot` protocol procedures use, its state record and its typed errors (no vendor imports here).

Every error says what happened and what to do next (`remedy`), so a procedure can stop cleanly and an
operator knows how to continue.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from hil.errors import ActionableError


class RobotError(ActionableError, RuntimeError):
    """Base of every robot driver error; `remedy` tells the operator or procedure what to do next."""

    remedy = "check the robot and its connection, then run the command again"


class ProtectiveStopError(RobotError):
    remedy = (
        "find and clear what stopped the arm, then run the command again (hil unlocks a protective stop 5 s "
        "after it happened and goes on from the last recorded point)"
    )


class EmergencyStopError(RobotError):
    remedy = "make the cell safe and release the emergency stop button, then run the command again"


class ProgramNotRunningError(RobotError):
    remedy = (
        "the controller stopped hil's control program (a program started on the teach pendant, or local "
        "control on an e-Series): put the controller in remote control, then run the command again"
    )


class RobotNotReadyError(RobotError):
    remedy = "power on the arm and release its brakes on the teach pendant, then run the command again"


class RobotTimeoutError(RobotError):
    remedy = "check that the target is reachable and the cell's speed sensible, then run the command again"


class RobotConnectionError(RobotError):
    remedy = (
        "check that the controller is on and reachable at the address the cell config gives (cable, network), "
        "then run the command again"
    )


class StaleDataError(RobotConnectionError):
    remedy = "the controller stopped sending its state: check the network and the controller, then run the command again"


class RobotConfigError(RobotError, ValueError):
    remedy = "fix the requested value (see the message); nothing moved"


@dataclass(frozen=True)
class RobotState:
    """What the controller reports now."""

    connected: bool
    robot_mode: str
    safety_mode: str
    program_running: bool
    protective_stop: bool
    emergency_stop: bool
    timestamp_s: float

    @property
    def ready(self) -> bool:
        return (
            self.connected
            and self.robot_mode == "RUNNING"
            and self.program_running
            and not self.protective_stop
            and not self.emergency_stop
        )


@runtime_checkable
class Robot(Protocol):
    """A six-axis arm as procedures see it. SI units: radians, metres, seconds."""

    def move_joints(self, q: np.ndarray, speed: float | None = None, accel: float | None = None) -> None:
        """Move in joint space to q (6,) and return once the motion has ended."""
        ...

    def move_linear(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        """Move the flange in a straight line to a pose (4x4, or UR pose vector) and return at the end."""
        ...

    def move_path(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        """Move the flange in straight lines through poses (K, 4, 4) in turn, stopping at each (no blending),
        and return at the last one."""
        ...

    def joints(self) -> np.ndarray:
        """Current joint positions (6,) as the controller reports them."""
        ...

    def flange_pose(self) -> np.ndarray:
        """T_base_flange (4, 4) the controller believes (nominal model)."""
        ...

    def wait_settled(self, dwell_s: float | None = None, timeout_s: float | None = None) -> None:
        """Block until the arm is steady, then dwell (vibration dies out before a measurement)."""
        ...

    def stop(self) -> None:
        """Decelerate any motion to rest."""
        ...

    def state(self) -> RobotState:
        """Connection, modes and stop flags."""
        ...

    def recover(self) -> None:
        """Bring the robot back to ready after a stop or lost connection (see each error's remedy)."""
        ...

    def close(self) -> None:
        """Leave the robot stopped and release every connection."""
        ...
