"""Read a URScript program's motions: which targets are constant poses hil can compensate offline, which not.

A program is read as PolyScope saves it (`global Waypoint_1_p=p[...]` with its `Waypoint_1_q`, then
`movej(get_inverse_kin(Waypoint_1_p, qnear=Waypoint_1_q), a=..., v=...)`; a feature's waypoints as
`pose_trans(Plane_1, ...)` of a constant plane) or as an engineer writes it (`movel(p[...], r=0.01)`). A
motion target is *constant* when it evaluates from pose literals, joint lists and variables assigned once from
constants, through `pose_trans`, `pose_inv` and `get_inverse_kin`; anything else (a pose read at run time, a
variable assigned twice, a function's parameter) is reported with its line number and left alone.

Statements are taken in the text's order: that order decides the TCP and payload in force at each motion
(`set_tcp`, `set_payload`, `set_target_payload`) and the previous joints each target's branch is nearest to.
Nothing here runs the program: loops and branches are read once, top to bottom.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field

import numpy as np

from hil.geometry.se3 import invert, pose_to_transform, transform_to_pose

MOTIONS = ("movej", "movel", "movep", "movec")
_CALL = re.compile(r"\b(movej|movel|movep|movec|set_tcp|set_payload|set_target_payload)\s*\(")
_ASSIGN = re.compile(r"^\s*(?:global\s+|local\s+)?([A-Za-z_]\w*)\s*=(?!=)\s*(.+?)\s*$")


class ProgramError(ValueError):
    """The file is not a URScript program hil can read (a .urp, a syntax it cannot parse)."""


@dataclass(frozen=True)
class PoseTarget:
    """A motion target the program gives as a constant pose: where it sits in the text, what it means."""

    line: int  # 1-based line number
    command: str  # movej, movel, movep, movec
    role: str  # "target", or "via" (movec's first point)
    span: tuple[int, int]  # the argument's characters in that line
    T_base_tcp: np.ndarray  # (4, 4) the pose the program asks for, robot base frame, m
    T_flange_tcp: np.ndarray  # (4, 4) the TCP in force (set_tcp), flange frame
    payload_kg: float  # the payload in force (set_payload / set_target_payload)
    q_near: np.ndarray | None  # get_inverse_kin's qnear, when the program gives one

    @property
    def T_base_flange(self) -> np.ndarray:
        return self.T_base_tcp @ invert(self.T_flange_tcp)


@dataclass(frozen=True)
class JointTarget:
    """A motion to a joint list: a taught position, kept as it is (the next target's branch is nearest it)."""

    line: int
    command: str
    q: np.ndarray
    role: str = "target"  # or "via" (movec's first point)


@dataclass(frozen=True)
class RuntimeTarget:
    """A motion whose target the program computes at run time: not compensated, reported."""

    line: int
    command: str
    text: str
    why: str


@dataclass
class ProgramMotions:
    """The program's lines and its motions in text order, and what could not be read as constants."""

    lines: list[str]
    motions: list[PoseTarget | JointTarget] = field(default_factory=list)
    runtime: list[RuntimeTarget] = field(default_factory=list)
    runtime_tcp_lines: list[int] = field(default_factory=list)  # set_tcp of a value known only at run time

    @property
    def pose_targets(self) -> list[PoseTarget]:
        return [m for m in self.motions if isinstance(m, PoseTarget)]


class _NotConstantError(Exception):
    """An expression whose value is known only when the program runs."""


def read_program(text: str, source: str = "program") -> ProgramMotions:
    """The motions of a URScript program's text. ProgramError for a .urp (XML or gzip) or an unreadable call."""
    if text.lstrip().startswith("<") or text.startswith("\x1f\x8b"):
        raise ProgramError(
            f"{source} is a PolyScope .urp program, not URScript: on the teach pendant save the program, then "
            "use the .script file PolyScope writes beside it (same name, .script)"
        )
    lines = text.splitlines()
    code = [_strip_comment(line) for line in lines]
    constants = _Constants(code)
    out = ProgramMotions(lines)
    tcp, payload = np.eye(4), 0.0
    for number, line in enumerate(code, start=1):
        for match in _CALL.finditer(line):
            name = match.group(1)
            open_at = match.end() - 1
            close_at = _closing(line, open_at, source, number)
            args = _split_args(line, open_at + 1, close_at)
            if name == "set_tcp":
                try:
                    tcp = pose_to_transform(constants.pose(_arg_text(line, args[0])))
                except (_NotConstantError, IndexError):
                    out.runtime_tcp_lines.append(number)
                    tcp = np.full((4, 4), np.nan)
            elif name in ("set_payload", "set_target_payload"):
                try:
                    payload = constants.number(_arg_text(line, args[0]))
                except (_NotConstantError, IndexError):
                    payload = np.nan
            else:
                positional = [a for a in args if not re.match(r"\s*\w+\s*=(?!=)", line[a[0] : a[1]])]
                roles = ("via", "target") if name == "movec" else ("target",)
                for role, span in zip(roles, positional, strict=False):
                    out_item = _motion(constants, line, number, name, role, span, tcp, payload)
                    if isinstance(out_item, RuntimeTarget):
                        out.runtime.append(out_item)
                    else:
                        out.motions.append(out_item)
    return out


def _motion(
    constants: _Constants,
    line: str,
    number: int,
    name: str,
    role: str,
    span: tuple[int, int],
    tcp: np.ndarray,
    payload: float,
) -> PoseTarget | JointTarget | RuntimeTarget:
    """One motion argument read: a constant pose, a joint list, or a target known only at run time."""
    text = line[span[0] : span[1]].strip()
    lead = len(line[span[0] : span[1]]) - len(line[span[0] : span[1]].lstrip())
    span = (span[0] + lead, span[0] + lead + len(text))
    try:
        literal = _literal(text)
        saved = _SAVED_WAYPOINT.fullmatch(text) if literal is None else None
        if saved is not None:  # PolyScope's own form, its names read without an expression tree
            pose_name, qnear_name = saved.groups()
            node: ast.expr | None = ast.Call(
                ast.Name("get_inverse_kin"),
                [ast.Name(pose_name)],
                [ast.keyword("qnear", ast.Name(qnear_name))] if qnear_name else [],
            )
        else:
            node = _parse(text) if literal is None else None
        if isinstance(node, ast.Call) and _name(node.func) == "get_inverse_kin":
            pose = constants.pose_of(node.args[0])
            qnear = next((k.value for k in node.keywords if k.arg == "qnear"), None)
            q_near = None if qnear is None else constants.joints_of(qnear)
            T = pose_to_transform(pose)
        else:
            value = literal if node is None else constants.eval(node)
            if isinstance(value, _Joints):
                return JointTarget(number, name, value.q, role)
            if not isinstance(value, _Pose):
                raise _NotConstantError("not a pose")
            T, q_near = pose_to_transform(value.v), None
    except _NotConstantError as exc:
        return RuntimeTarget(number, name, text, str(exc) or "computed at run time")
    if not np.all(np.isfinite(tcp)):
        return RuntimeTarget(number, name, text, "the TCP in force is set at run time")
    if not np.isfinite(payload):
        return RuntimeTarget(number, name, text, "the payload in force is set at run time")
    return PoseTarget(number, name, role, span, T, tcp.copy(), payload, q_near)


@dataclass(frozen=True)
class _Pose:
    v: np.ndarray  # UR pose vector


@dataclass(frozen=True)
class _Joints:
    q: np.ndarray


class _Constants:
    """Variables assigned exactly once in the program from constant expressions, evaluated on demand."""

    def __init__(self, code: list[str]) -> None:
        self.assigned: dict[str, list[str]] = {}
        for line in code:
            m = _ASSIGN.match(line)
            if m and not line.lstrip().startswith(("def ", "thread ", "if ", "while ", "elif ")):
                self.assigned.setdefault(m.group(1), []).append(m.group(2))
        self._busy: set[str] = set()

    def variable(self, name: str) -> object:
        exprs = self.assigned.get(name)
        if not exprs:
            raise _NotConstantError(f"{name} is not assigned in the program")
        if len(exprs) > 1:
            raise _NotConstantError(f"{name} is assigned {len(exprs)} times")
        if name in self._busy:
            raise _NotConstantError(f"{name} refers to itself")
        literal = _literal(exprs[0])
        if literal is not None:
            return literal
        self._busy.add(name)
        try:
            return self.eval(_parse(exprs[0]))
        finally:
            self._busy.discard(name)

    def number(self, text: str) -> float:
        v = self.eval(_parse(text))
        if not isinstance(v, float):
            raise _NotConstantError("not a number")
        return v

    def pose(self, text: str) -> np.ndarray:
        return self.pose_of(_parse(text))

    def pose_of(self, node: ast.expr) -> np.ndarray:
        v = self.eval(node)
        if not isinstance(v, _Pose):
            raise _NotConstantError("not a pose")
        return v.v

    def joints_of(self, node: ast.expr) -> np.ndarray:
        v = self.eval(node)
        if not isinstance(v, _Joints):
            raise _NotConstantError("qnear is not a joint list")
        return v.q

    def eval(self, node: ast.expr) -> object:
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
            return float(node.value)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            v = self.eval(node.operand)
            if isinstance(v, float):
                return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.Name):
            return self.variable(node.id)
        if isinstance(node, ast.Subscript) and _name(node.value) == "p":
            elts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            values = [self.eval(e) for e in elts]
            if len(values) == 6 and all(isinstance(v, float) for v in values):
                return _Pose(np.array(values, float))
        if isinstance(node, ast.List):
            values = [self.eval(e) for e in node.elts]
            if all(isinstance(v, float) for v in values):
                return _Joints(np.array(values, float))
        if isinstance(node, ast.Call) and not node.keywords:
            fn = _name(node.func)
            if fn == "pose_trans" and len(node.args) == 2:
                a, b = (pose_to_transform(self.pose_of(x)) for x in node.args)
                return _Pose(_to_pose(a @ b))
            if fn == "pose_inv" and len(node.args) == 1:
                return _Pose(_to_pose(invert(pose_to_transform(self.pose_of(node.args[0])))))
            raise _NotConstantError(f"{fn}(...) is evaluated at run time")
        raise _NotConstantError(f"'{ast.unparse(node)}' is evaluated at run time")


def _to_pose(T: np.ndarray) -> np.ndarray:
    return np.asarray(transform_to_pose(T), float)


def _name(node: ast.expr) -> str | None:
    return node.id if isinstance(node, ast.Name) else None


_NUMBER = r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*"
_LITERAL = re.compile(rf"\s*(p?)\[({_NUMBER}(?:,{_NUMBER})*)\]\s*")


# get_inverse_kin(Waypoint_1_p, qnear=Waypoint_1_q), as PolyScope writes each waypoint's motion.
_SAVED_WAYPOINT = re.compile(
    r"\s*get_inverse_kin\(\s*([A-Za-z_]\w*)\s*(?:,\s*qnear\s*=\s*([A-Za-z_]\w*)\s*)?\)\s*"
)


def _literal(text: str) -> _Pose | _Joints | None:
    """A pose literal p[...] of six numbers or a joint list [...] of numbers read without an expression tree
    (a program saved by PolyScope holds two per waypoint; parsing each cost most of reading it), else None."""
    m = _LITERAL.fullmatch(text)
    if m is None:
        return None
    values = np.array([float(v) for v in m.group(2).split(",")])
    if m.group(1):
        return _Pose(values) if len(values) == 6 else None
    return _Joints(values)


def _parse(text: str) -> ast.expr:
    """A URScript expression as a Python expression tree (p[...] reads as a subscript of p, True/False alike)."""
    try:
        return ast.parse(text.strip(), mode="eval").body
    except SyntaxError as exc:
        raise _NotConstantError(f"cannot read '{text.strip()}'") from exc


def _strip_comment(line: str) -> str:
    """The line without its # comment (a # inside a string stays); PolyScope's `$ 3 "Waypoint_1"` lines blank."""
    if line.lstrip().startswith("$"):
        return ""
    if "#" not in line:
        return line
    quoted = False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif ch == "#" and not quoted:
            return line[:i]
    return line


_BRACKET = re.compile(r"[()\[\]]")
_SEPARATOR = re.compile(r"[(),\[\]]")


def _closing(line: str, open_at: int, source: str, number: int) -> int:
    depth = 0
    for m in _BRACKET.finditer(line, open_at):
        depth += 1 if m.group() in "([" else -1
        if depth == 0:
            return m.start()
    raise ProgramError(f"{source}:{number}: a motion call that does not close on its line: {line.strip()}")


def _split_args(line: str, start: int, end: int) -> list[tuple[int, int]]:
    """Spans of the top-level arguments between start and end (exclusive)."""
    spans, depth, at = [], 0, start
    for m in _SEPARATOR.finditer(line, start, end):
        ch = m.group()
        if ch == "," and depth == 0:
            spans.append((at, m.start()))
            at = m.start() + 1
        elif ch != ",":
            depth += 1 if ch in "([" else -1
    if line[at:end].strip():
        spans.append((at, end))
    return spans


def _arg_text(line: str, span: tuple[int, int]) -> str:
    return line[span[0] : span[1]]
