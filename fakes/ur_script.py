"""Recognise the control program that ur-rtde 1.6.5 uploads and read what the fake needs from its text.

The fake does not interpret URScript. It checks that a program is ur-rtde's `rtde_control` program of
the pinned build, then reads from the text: the register offsets (injected by the client after two
marker comments), the realtime command ids of the main loop, the command ids `process_cmd` handles,
and the move path the client injects for moveJ/moveL paths. Anything else is refused loudly.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import AsyncIterator
from dataclasses import dataclass

log = logging.getLogger(__name__)

# The build stamp the 1.6.5 script prints when it starts; another stamp means another ur-rtde version.
PINNED_BUILD = "14.02.2024-12:23"
PINNED_CLIENT = "ur-rtde 1.6.5"

_PROGRAM_START = re.compile(r"^(def|sec)\s+(\w+)\s*\(\s*\)\s*:", re.M)
_PROGRAM_END = re.compile(r"^end[ \t]*\r?$", re.M)
_OFFSET = re.compile(r"reg_offset_(float|int)\s*=\s*#[^\n]*register offset\s*\n\s*(\d+)")
_BUILD = re.compile(r'textmsg\("RTDE Control Script Loaded \(([^)]*)\)"\)')
_LOOP_RT = re.compile(r"while keep_running:\s*\n\s*cmd = rtde_cmd\(\)\s*\n\s*if ((?:cmd == \d+(?: or )?)+):")
_HANDLED = re.compile(r"^\s*(?:el)?if cmd == (\d+)\s*:", re.M)
_PATH_BLOCK = re.compile(r"def exec_move_path\(\):.*?# inject move path\s*\n(.*?)^\s*end\s*$", re.S | re.M)
_PATH_PROGRESS = re.compile(r"signal_async_progress\((\d+)\)")
_PATH_MOVE = re.compile(
    r"(movej|movel)\(\s*(p?)\[([^\]]*)\]\s*,\s*a\s*=\s*([-+0-9.eE]+)\s*,\s*v\s*=\s*([-+0-9.eE]+)"
    r"(?:\s*,\s*r\s*=\s*([-+0-9.eE]+))?\s*\)"
)
_REQUIRED_MARKERS = (
    "# HEADER_BEGIN",
    "# HEADER_END",
    "# NODE_CONTROL_LOOP_BEGINS",
    "# NODE_CONTROL_LOOP_ENDS",
)


class UnknownProgramError(ValueError):
    """The uploaded program is not the ur-rtde control program this fake emulates."""


MAX_PENDING_CHARS = 4_000_000  # a client that sends this much without a complete program is dropped


async def read_programs(reader: asyncio.StreamReader, port: str) -> AsyncIterator[str]:
    """Each complete program a client sends, in order, until it closes (or sends MAX_PENDING_CHARS without
    completing one): what the script, primary and secondary ports all read."""
    buffer = ""
    while True:
        chunk = await reader.read(65536)
        if not chunk:
            return
        buffer += chunk.decode("utf-8", errors="replace")
        if len(buffer) > MAX_PENDING_CHARS:
            log.error("%s port: more than 4 MB without a complete program; dropping", port)
            return
        programs, buffer = split_programs(buffer)
        for text in programs:
            yield text


def split_programs(buffer: str) -> tuple[list[str], str]:
    """Cut complete top-level programs (`def name():` ... `end` at column 0) off a stream buffer."""
    programs: list[str] = []
    while True:
        start = _PROGRAM_START.search(buffer)
        if not start:
            # keep only a possible partial header at the end of the buffer
            return programs, buffer[-64:] if len(buffer) > 64 else buffer
        end = _PROGRAM_END.search(buffer, start.end())
        if not end:
            return programs, buffer[start.start() :]
        programs.append(buffer[start.start() : end.end()])
        buffer = buffer[end.end() :]


@dataclass(frozen=True)
class PathSegment:
    """One injected path move: kind movej/movel, target (joints or pose), a, v, r and waypoint index."""

    kind: str  # movej_joints, movej_pose, movel_pose or movel_joints
    target: tuple[float, ...]
    v: float
    a: float
    r: float
    index: int

    def as_tuple(self) -> tuple:
        return (self.kind, self.target, self.v, self.a, self.r, self.index)


@dataclass(frozen=True)
class ControlProgram:
    """What the fake needs to know about an uploaded ur-rtde control program."""

    name: str
    build: str
    offset: int  # register offset (0, or 24 with FLAG_UPPER_RANGE_REGISTERS)
    realtime_commands: frozenset[int]
    handled_commands: frozenset[int]
    path: tuple[tuple, ...]
    size: int

    @classmethod
    def parse(cls, text: str) -> ControlProgram:
        """Recognise and parse the program; raises UnknownProgramError saying what did not match."""
        start = _PROGRAM_START.search(text)
        if not start or start.group(2) != "rtde_control":
            name = start.group(2) if start else "?"
            raise UnknownProgramError(
                f"program '{name}' is not ur-rtde's rtde_control program; this fake only runs the control "
                f"program of {PINNED_CLIENT} (no URScript interpreter)"
            )
        missing = [m for m in _REQUIRED_MARKERS if m not in text]
        if missing:
            raise UnknownProgramError(f"rtde_control program without the markers {missing}")
        build = _BUILD.search(text)
        if not build or build.group(1) != PINNED_BUILD:
            found = build.group(1) if build else "none"
            raise UnknownProgramError(
                f"rtde_control build '{found}' is not the pinned {PINNED_CLIENT} build '{PINNED_BUILD}': "
                "install ur-rtde==1.6.5 or teach fakes/ur_script.py the new program"
            )
        offsets = {kind: int(value) for kind, value in _OFFSET.findall(text)}
        if set(offsets) != {"float", "int"}:
            raise UnknownProgramError("could not find both register offsets (int and float) in the program")
        if offsets["float"] != offsets["int"] or offsets["int"] not in (0, 24):
            raise UnknownProgramError(f"unsupported register offsets {offsets}")
        loop = _LOOP_RT.search(text)
        if not loop:
            raise UnknownProgramError("could not find the realtime command set in the main loop")
        realtime = frozenset(int(n) for n in re.findall(r"\d+", loop.group(1)))
        process = text[text.find("def process_cmd(cmd):") : text.find("# HEADER_END")]
        handled = frozenset(int(n) for n in _HANDLED.findall(process))
        return cls(
            name=start.group(2),
            build=build.group(1),
            offset=offsets["int"],
            realtime_commands=realtime,
            handled_commands=handled,
            path=tuple(s.as_tuple() for s in parse_path(text)),
            size=len(text),
        )


def parse_path(text: str) -> list[PathSegment]:
    """The movej/movel lines ur-rtde injected into exec_move_path, with their progress indices."""
    block = _PATH_BLOCK.search(text)
    if not block:
        raise UnknownProgramError("could not find exec_move_path and its path marker")
    segments: list[PathSegment] = []
    index = 0
    for line in block.group(1).splitlines():
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("textmsg"):
            continue
        progress = _PATH_PROGRESS.fullmatch(line)
        if progress:
            index = int(progress.group(1))
            continue
        move = _PATH_MOVE.fullmatch(line)
        if not move:
            raise UnknownProgramError(f"unsupported line in the injected path: {line!r}")
        kind, is_pose, numbers, a, v, r = move.groups()
        target = tuple(float(x) for x in numbers.split(","))
        if len(target) != 6:
            raise UnknownProgramError(f"path move with a bad target: {line!r}")
        kind = f"{kind}_{'pose' if is_pose else 'joints'}"
        segments.append(PathSegment(kind, target, float(v), float(a), float(r or 0.0), index))
    return segments
