"""The primary (30001) and secondary (30002) ports of the fake controller: programs in, robot messages out.

A client that connects gets the version message first, as from a real controller; then every robot message
the controller emits: the text of a program's textmsg / popup, and a runtime exception (line, column, text)
when a program it was sent has a script error or fails while it runs. Framing (big-endian): int32 package
length (header included), uint8 package type 20 (robot message), uint64 timestamp (µs), int8 source, uint8
message type (0 text, 3 version, 10 runtime exception). The periodic robot-state packages (type 16) a real
controller streams are not sent.

`ProgramRunner` runs one user program (fakes.ur_program) on the controller's cycle: it starts each motion
on the controller's motion planner and takes the next action when the motion has ended.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np

from fakes.ur_motion import JointMove, LinearMove, Motion
from fakes.ur_program import Action, Controller, Halt, Message, Move, ScriptError, UserProgram, Wait
from fakes.ur_script import read_programs


class ProgramHost(Controller, Protocol):
    """What the primary ports and a running program need of the controller (fakes.ur_controller has it)."""

    cell: Any  # the simulated cell: its clock, `time_s`
    model: Any  # the nominal model: the controller's beliefs
    motion: Motion | None
    q_cmd: np.ndarray
    primary: PrimaryClients
    personality: Any

    def receive_program(self, text: str) -> None: ...

    def _start_motion(self, motion: Motion, is_async: bool, count: bool = True) -> None: ...


log = logging.getLogger("fakes.ur_controller")

ROBOT_MESSAGE = 20
MESSAGE_TEXT, MESSAGE_VERSION, MESSAGE_RUNTIME_EXCEPTION = 0, 3, 10
SOURCE_CONTROLLER = -2  # [A] the source byte a real controller puts on program messages
BUILD_DATE = "01-01-2024, 00:00:00"


def robot_message(message_type: int, body: bytes, source: int = SOURCE_CONTROLLER) -> bytes:
    """One robot-message package: header, timestamp, source, type, body."""
    payload = struct.pack(">QbB", int(time.time() * 1e6), source, message_type) + body
    return struct.pack(">iB", 5 + len(payload), ROBOT_MESSAGE) + payload


def version_message(version: tuple[int, ...]) -> bytes:
    """The version message a client gets first: project name, major, minor, bugfix, build, build date."""
    major, minor, bugfix, build = (*version, 0, 0, 0, 0)[:4]
    name = "URControl"
    body = struct.pack(">b", len(name)) + name.encode() + struct.pack(">BBii", major, minor, bugfix, build)
    return robot_message(MESSAGE_VERSION, body + BUILD_DATE.encode(), source=-1)


def text_message(text: str) -> bytes:
    return robot_message(MESSAGE_TEXT, text.encode("utf-8"))


def runtime_exception(error: ScriptError) -> bytes:
    return robot_message(
        MESSAGE_RUNTIME_EXCEPTION, struct.pack(">ii", error.line, error.column) + error.message.encode()
    )


def parse_robot_messages(data: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """Complete robot messages (message type, body) cut off a client's byte stream, and the rest."""
    out = []
    while len(data) >= 5:
        length, kind = struct.unpack(">iB", data[:5])
        if len(data) < length:
            break
        if kind == ROBOT_MESSAGE:
            _, _, message_type = struct.unpack(">QbB", data[5:15])
            out.append((message_type, data[15:length]))
        data = data[length:]
    return out, data


class PrimaryClients:
    """The writers of every client connected to the primary or secondary port."""

    def __init__(self) -> None:
        self.writers: set[asyncio.StreamWriter] = set()
        self.messages: list[str] = []  # what was sent, for the control channel and tests

    def broadcast(self, package: bytes, what: str) -> None:
        self.messages.append(what)
        for writer in list(self.writers):
            if writer.is_closing():
                self.writers.discard(writer)
                continue
            writer.write(package)

    async def serve(
        self, controller: ProgramHost, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Version first, then programs in (each handed to the controller) while messages go out."""
        writer.write(version_message(tuple(controller.personality.version)))
        self.writers.add(writer)
        try:
            async for text in read_programs(reader, "primary"):
                controller.receive_program(text)
        except ConnectionError:
            pass
        finally:
            self.writers.discard(writer)
            with contextlib.suppress(Exception):
                writer.close()


class ProgramRunner:
    """One user program running on the controller, one action at a time."""

    def __init__(self, controller: ProgramHost, program: UserProgram):
        self.controller = controller
        self.actions: Iterator[Action] = program.run(controller)
        self.moving = False
        self.wait_until: float | None = None
        self.done = False

    def cycle(self) -> None:
        """Take actions until one needs time (a motion, a sleep) or the program ends."""
        c = self.controller
        if self.moving:
            if c.motion is not None:
                return
            self.moving = False
        if self.wait_until is not None:
            if c.cell.time_s < self.wait_until:
                return
            self.wait_until = None
        while not self.done:
            try:
                action = next(self.actions)
            except StopIteration:
                self.done = True
                return
            except Halt:
                self.done = True
                return
            except ScriptError as exc:
                self.done = True
                c.primary.broadcast(runtime_exception(exc), f"runtime exception: {exc}")
                log.error("program stopped: %s", exc)
                return
            if isinstance(action, Message):
                c.primary.broadcast(text_message(action.text), action.text)
            elif isinstance(action, Wait):
                self.wait_until = c.cell.time_s + action.seconds
                return
            elif isinstance(action, Move):
                self._start(action)
                return

    def _start(self, move: Move) -> None:
        c = self.controller
        motion: Motion
        if move.kind == "joint":
            motion = JointMove(c.q_cmd, np.asarray(move.target, float), move.speed, move.accel)
        else:
            motion = LinearMove(c.model, c.q_cmd, np.asarray(move.target, float), move.speed, move.accel)
        c._start_motion(motion, is_async=False)
        self.moving = True
