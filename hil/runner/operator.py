"""The operator: the person who seats SMRs and guides the tracker's beam during manual steps.

Procedures ask for a manual step with an `OperatorStep` and wait until it is done; they cannot tell
whether a person at a console (`ConsoleOperator`) or a script (`ScriptedOperator`, in tests and the demo)
carries it out.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TextIO


class OperatorAbortError(RuntimeError):
    """The operator declined a manual step; the procedure stops (what was recorded stays recorded)."""


@dataclass(frozen=True)
class OperatorStep:
    """One manual step: the instruction shown, and what it means in machine terms for a script.

    action: "place_smr" (put SMR `smr` at `location`: "nest1".."nestK", "hole1".."hole7", "face"),
    "lock_beam" (guide the tracker's beam onto SMR `smr` until it locks), "unmount_tool" (take the tool off
    the flange, keeping the robot still), "mount_tool" (put it back on its dowel, keeping the robot still) or
    "confirm" (anything else).
    face_point_m: where on the flange face the SMR should rest (x, y in the flange frame), for "face".
    drawing_svg: a drawing of where the step happens (SVG text), shown with the instruction where a screen can
    show it (the operator console); a terminal shows the text alone.
    """

    text: str
    action: str = "confirm"
    smr: int | None = None
    location: str | None = None
    face_point_m: tuple[float, float] | None = None
    drawing_svg: str | None = None


class Operator(Protocol):
    def perform(self, step: OperatorStep) -> None:
        """Carry out the step, returning once it is done; raise OperatorAbortError to stop the procedure."""
        ...

    def close(self) -> None:
        """Let go of what the operator holds (a simulated cell's control channel); the session's end calls it."""
        ...


class ConsoleOperator:
    """Prints the instruction and waits for Enter; 'q' aborts the procedure."""

    def __init__(self, stdin: TextIO | None = None, stdout: TextIO | None = None):
        self.stdin = stdin or sys.stdin
        self.stdout = stdout or sys.stdout

    def perform(self, step: OperatorStep) -> None:
        self.stdout.write(f"\n>>> {step.text}\n    press Enter when done (q + Enter to stop): ")
        self.stdout.flush()
        answer = self.stdin.readline()
        if answer == "" or answer.strip().lower() in ("q", "quit", "stop"):
            raise OperatorAbortError(f"the operator stopped at: {step.text}")

    def close(self) -> None:
        """A person at the console holds nothing."""


class ScriptedOperator:
    """Carries out steps with functions per action (e.g. moving the simulated SMR through the cell's
    control channel); keeps a transcript of what it was asked. `release`: what `close` lets go of (the
    channel the actions use), once."""

    def __init__(
        self, actions: dict[str, Callable[[OperatorStep], None]], release: Callable[[], None] | None = None
    ):
        self.actions = actions
        self.transcript: list[OperatorStep] = []
        self._release = release

    def close(self) -> None:
        release, self._release = self._release, None
        if release is not None:
            release()

    def perform(self, step: OperatorStep) -> None:
        self.transcript.append(step)
        action = self.actions.get(step.action)
        if action is None and step.action != "confirm":
            raise OperatorAbortError(f"the scripted operator cannot do {step.action!r}: {step.text}")
        if action is not None:
            action(step)
