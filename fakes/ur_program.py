"""User URScript programs on the fake controller: their motion subset, compiled, then run cycle by cycle.

A program sent to the primary or secondary port (`def name(): ... end`, as PolyScope saves it or an engineer
writes it) is compiled first, as a real controller does: a statement or a function the fake does not run is
reported as a script error with its line and column, and the program does not start. What runs: `def` / `end`
(functions without motion return values), `global` / `local` variables, `while`, `if` / `elif` / `else`,
`return`, `halt`; movej, movel, movep, movec (pose or joint targets; blends and movec's arc are not modelled:
every motion ends at its target), sleep, sync, textmsg, popup, set_tcp, set_payload / set_target_payload,
get_inverse_kin, get_forward_kin, get_actual_tcp_pose / joint_positions, pose_trans, pose_inv, pose_add, the
digital outputs, a few math functions, and PolyScope's setup calls (accepted, they move nothing). `thread`
blocks are accepted and not run; `$ 3 "Waypoint_1"` lines are labels.

This is the controller's side, written without hil's own program reader (hil.compensation.urscript): a
program hil rewrote is checked by a second, independent reading.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hil.geometry.se3 import invert, pose_to_transform, transform_to_pose

STATEMENTS_PER_CYCLE = 100_000  # a loop this long without motion, sleep or sync is a runtime error
_BLOCK = re.compile(r"^(def|thread)\s+(\w+)\s*\(([^)]*)\)\s*:\s*$")
_CONTROL = re.compile(r"^(while|if|elif)\s*(.+?)\s*:\s*$")
_ASSIGN = re.compile(r"^(?:(global|local)\s+)?([A-Za-z_]\w*)\s*=(?!=)\s*(.+)$")
# Calls PolyScope writes at a program's start that set up I/O, safety and tool electrics: nothing moves.
SETUP_CALLS = frozenset(
    {
        "set_gravity",
        "set_tool_voltage",
        "set_tool_communication",
        "set_tool_output_mode",
        "set_tool_digital_output_mode",
        "set_safety_mode_transition_hardness",
        "set_standard_analog_input_domain",
        "set_tool_analog_input_domain",
        "set_analog_outputdomain",
        "set_input_actions_to_default",
        "modbus_set_runstate_dependent_choice",
        "set_runstate_outputs",
        "set_tool_digital_input_action",
        "set_standard_digital_input_action",
        "set_configurable_digital_input_action",
        "set_analog_out",
        "set_tool_digital_out",
        "set_configurable_digital_out",
    }
)


class ScriptError(Exception):
    """A script error as the controller reports it: where (1-based line, column) and what."""

    def __init__(self, line: int, column: int, message: str):
        super().__init__(f"line {line}, column {column}: {message}")
        self.line, self.column, self.message = line, column, message


class Halt(Exception):  # noqa: N818 - the program's `halt`
    """The program ran `halt`."""


class _Return(Exception):  # noqa: N818 - control flow of `return`
    def __init__(self, value: object):
        self.value = value


@dataclass
class Statement:
    """One statement: its kind, line, parsed expressions and nested blocks."""

    kind: str  # assign, expr, while, if, return, halt, pass
    line: int
    indent: int = 0  # columns before its expression on its line (script errors give the line's column)
    target: str = ""
    scope: str = ""  # global / local / "" for an assignment
    expr: ast.expr | None = None
    body: list[Statement] = field(default_factory=list)
    branches: list[tuple[ast.expr | None, list[Statement]]] = field(default_factory=list)  # if / elif / else


@dataclass
class Function:
    name: str
    params: list[str]
    body: list[Statement]


@dataclass(frozen=True)
class Move:
    """Action: start this motion (joint target or flange pose) and wait for its end."""

    kind: str  # "joint" or "linear"
    target: np.ndarray  # joints (6,) or T_base_flange (4, 4)
    speed: float
    accel: float


@dataclass(frozen=True)
class Wait:
    """Action: wait this many seconds of the controller's clock (0: one cycle, `sync`)."""

    seconds: float


@dataclass(frozen=True)
class Message:
    """Action: a textmsg or popup for the primary clients' log."""

    text: str


Action = Move | Wait | Message
Steps = Generator[Action, None, Any]  # what running a statement, an expression or a call yields and returns


class Controller(Protocol):
    """What a running program reads of and asks of the controller (the fake implements it)."""

    q_cmd: np.ndarray
    T_flange_tcp: np.ndarray
    payload: tuple[float, tuple[float, ...]]
    digital_out: int

    def _ik(self, T_base_flange: np.ndarray, q_seed: np.ndarray | None = None) -> np.ndarray | None: ...

    def flange_pose_of(self, q: np.ndarray) -> np.ndarray: ...

    def joints_in(
        self, q_wire: np.ndarray
    ) -> np.ndarray: ...  # a program's joints (the controller's) -> kinematic

    def joints_out(self, q: np.ndarray) -> np.ndarray: ...  # kinematic -> as the controller reports them


class UserProgram:
    """A compiled program: its functions and the name of the one that runs."""

    def __init__(self, text: str):
        lines = text.splitlines()
        self.functions: dict[str, Function] = {}
        main: str | None = None
        i = 0
        while i < len(lines):
            code = _code(lines[i])
            if not code:
                i += 1
                continue
            m = _BLOCK.match(code)
            if not m or m.group(1) != "def":
                raise ScriptError(i + 1, 1, f"expected a program 'def name():', got '{code}'")
            func, i = self._function(lines, i)
            self.functions[func.name] = func
            main = main or func.name
        if main is None:
            raise ScriptError(1, 1, "no program (def name(): ... end)")
        self.main = main
        for func in self.functions.values():
            self._check(func.body)

    def _function(self, lines: list[str], start: int) -> tuple[Function, int]:
        m = _BLOCK.match(_code(lines[start]))
        assert m is not None
        params = [p.strip().split("=")[0].strip() for p in m.group(3).split(",") if p.strip()]
        body, end = self._block(lines, start + 1)
        return Function(m.group(2), params, body), end + 1  # the line after its `end`

    def _block(self, lines: list[str], start: int) -> tuple[list[Statement], int]:
        """Statements from `start` to the matching `end` (or else / elif): (statements, index after `end`)."""
        out: list[Statement] = []
        i = start
        while i < len(lines):
            code, number = _code(lines[i]), i + 1
            if not code or code.startswith("$"):
                i += 1
                continue
            if code == "end" or code.startswith(("elif", "else")):
                return out, i
            block = _BLOCK.match(code)
            control = _CONTROL.match(code)
            if block and block.group(1) == "def":
                func, i = self._function(lines, i)
                self.functions[func.name] = func
                continue
            if block:  # a thread: read, not run
                _, end = self._block(lines, i + 1)
                i = end + 1
                continue
            if control and control.group(1) == "while":
                body, end = self._block(lines, i + 1)
                column = len(lines[i]) - len(lines[i].lstrip()) + control.start(2)
                out.append(
                    Statement("while", number, column, expr=_expr(control.group(2), number), body=body)
                )
                i = end + 1
                continue
            if control and control.group(1) == "if":
                st, i = self._if(lines, i, control.group(2))
                out.append(st)
                continue
            st = _simple(code, number)
            assign = _ASSIGN.match(code)
            st.indent = len(lines[i]) - len(lines[i].lstrip()) + (assign.start(3) if assign else 0)
            out.append(st)
            i += 1
        raise ScriptError(len(lines), 1, "missing 'end'")

    def _if(self, lines: list[str], at: int, condition: str) -> tuple[Statement, int]:
        st = Statement("if", at + 1)
        cond: ast.expr | None = _expr(condition, at + 1)
        i = at
        while True:
            body, end = self._block(lines, i + 1)
            st.branches.append((cond, body))
            code = _code(lines[end])
            if code == "end":
                return st, end + 1
            if code.startswith("else"):
                cond, i = None, end
                continue
            m = _CONTROL.match(code)
            if not m:
                raise ScriptError(end + 1, 1, f"cannot read '{code}'")
            cond, i = _expr(m.group(2), end + 1), end

    def _check(self, body: list[Statement]) -> None:
        """Every function a statement calls is one the fake runs or one the program defines."""
        for st in body:
            for node in [st.expr, *[c for c, _ in st.branches]]:
                if node is None:
                    continue
                for sub in ast.walk(node):
                    if isinstance(sub, ast.Call):
                        name = sub.func.id if isinstance(sub.func, ast.Name) else ast.unparse(sub.func)
                        if name not in BUILTINS and name not in self.functions and name not in SETUP_CALLS:
                            raise ScriptError(
                                st.line,
                                st.indent + sub.col_offset + 1,
                                f"the fake controller does not run '{name}'",
                            )
            self._check(st.body)
            for _, branch in st.branches:
                self._check(branch)

    def run(self, host: Controller) -> Iterator[Action]:
        """The program's actions in order; ScriptError (runtime) and Halt end it."""
        return _Run(self, host).call(self.main, [], 0)


def _code(line: str) -> str:
    """The line without comment and indentation."""
    quoted = False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif ch == "#" and not quoted:
            return line[:i].strip()
    return line.strip()


def _expr(text: str, line: int) -> ast.expr:
    try:
        return ast.parse(text.strip(), mode="eval").body
    except SyntaxError as exc:
        raise ScriptError(line, (exc.offset or 1), f"syntax error in '{text.strip()}'") from exc


def _simple(code: str, number: int) -> Statement:
    if code == "halt":
        return Statement("halt", number)
    if code.startswith("return"):
        rest = code[len("return") :].strip()
        return Statement("return", number, expr=_expr(rest, number) if rest else None)
    if code.startswith("run "):  # starting a thread: threads are not run
        return Statement("pass", number)
    m = _ASSIGN.match(code)
    if m:
        return Statement(
            "assign", number, target=m.group(2), scope=m.group(1) or "", expr=_expr(m.group(3), number)
        )
    node = _expr(code, number)
    if not isinstance(node, ast.Call):
        raise ScriptError(number, 1, f"the fake controller does not run the statement '{code}'")
    return Statement("expr", number, expr=node)


class _Run:
    """One execution of a program: its globals, the call stack's locals, the host."""

    def __init__(self, program: UserProgram, host: Controller):
        self.program, self.host = program, host
        self.globals: dict[str, Any] = {}
        self.budget = STATEMENTS_PER_CYCLE

    def call(self, name: str, args: list[Any], line: int) -> Steps:
        """Run a function of the program; its `return` value is the generator's value."""
        func = self.program.functions[name]
        local = dict(zip(func.params, args, strict=False))
        try:
            yield from self.block(func.body, local)
        except _Return as r:
            return r.value
        return None

    def block(self, body: list[Statement], local: dict[str, Any]) -> Steps:
        for st in body:
            self.budget -= 1
            if self.budget <= 0:
                raise ScriptError(st.line, 1, "a loop ran without motion, sleep or sync")
            if st.kind == "assign":
                assert st.expr is not None
                value = yield from self.value(st.expr, local, st.line)
                if st.scope == "global" or (
                    st.scope == "" and st.target in self.globals and st.target not in local
                ):
                    self.globals[st.target] = value
                else:
                    local[st.target] = value
            elif st.kind == "expr":
                assert st.expr is not None
                yield from self.value(st.expr, local, st.line)
            elif st.kind == "while":
                while True:
                    cond = yield from self.value(st.expr, local, st.line)  # type: ignore[arg-type]
                    if not cond:
                        break
                    yield from self.block(st.body, local)
            elif st.kind == "if":
                for cond_node, branch in st.branches:
                    cond = True if cond_node is None else (yield from self.value(cond_node, local, st.line))
                    if cond:
                        yield from self.block(branch, local)
                        break
            elif st.kind == "return":
                value = None if st.expr is None else (yield from self.value(st.expr, local, st.line))
                raise _Return(value)
            elif st.kind == "halt":
                raise Halt()

    def value(self, node: ast.expr, local: dict[str, Any], line: int) -> Steps:
        """Evaluate an expression (a generator: a called function or builtin may yield actions)."""
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.Name):
            if node.id in local:
                return local[node.id]
            if node.id in self.globals:
                return self.globals[node.id]
            raise ScriptError(line, node.col_offset + 1, f"variable '{node.id}' is not defined")
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "p":
            elts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            values: list[float] = []
            for e in elts:
                values.append(float((yield from self.value(e, local, line))))
            if len(values) != 6:
                raise ScriptError(line, node.col_offset + 1, "a pose has 6 numbers")
            return _Pose(np.array(values))
        if isinstance(node, ast.Subscript):
            seq = yield from self.value(node.value, local, line)
            index = yield from self.value(node.slice, local, line)
            return (seq.v if isinstance(seq, _Pose) else seq)[int(index)]
        if isinstance(node, ast.List | ast.Tuple):
            items: list[Any] = []
            for e in node.elts:
                items.append((yield from self.value(e, local, line)))
            return items
        if isinstance(node, ast.UnaryOp):
            v = yield from self.value(node.operand, local, line)
            return {ast.USub: lambda x: -x, ast.UAdd: lambda x: x, ast.Not: lambda x: not x}[type(node.op)](v)
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            a = yield from self.value(node.left, local, line)
            b = yield from self.value(node.right, local, line)
            return _BINARY[type(node.op)](a, b)
        if isinstance(node, ast.BoolOp):
            result = isinstance(node.op, ast.And)
            for e in node.values:
                v = yield from self.value(e, local, line)
                if isinstance(node.op, ast.And) and not v:
                    return False
                if isinstance(node.op, ast.Or) and v:
                    return True
            return result
        if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _COMPARE:
            a = yield from self.value(node.left, local, line)
            b = yield from self.value(node.comparators[0], local, line)
            return _COMPARE[type(node.ops[0])](a, b)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            args: list[Any] = []
            for e in node.args:
                args.append((yield from self.value(e, local, line)))
            kwargs: dict[str, Any] = {}
            for k in node.keywords:
                kwargs[str(k.arg)] = yield from self.value(k.value, local, line)
            name = node.func.id
            if name in self.program.functions:
                return (yield from self.call(name, args, line))
            if name in SETUP_CALLS:
                return None
            try:
                result = BUILTINS[name](self, *args, **kwargs)
            except (TypeError, ValueError, IndexError) as exc:
                raise ScriptError(line, node.col_offset + 1, f"{name}: {exc}") from exc
            if isinstance(result, Iterator):
                return (yield from result)
            return result
        raise ScriptError(line, getattr(node, "col_offset", 0) + 1, f"cannot evaluate '{ast.unparse(node)}'")


@dataclass(frozen=True)
class _Pose:
    v: np.ndarray


_BINARY: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Mod: lambda a, b: a % b,
}
_COMPARE: dict[type, Callable[[Any, Any], bool]] = {
    ast.Eq: lambda a, b: a == b,
    ast.NotEq: lambda a, b: a != b,
    ast.Lt: lambda a, b: a < b,
    ast.LtE: lambda a, b: a <= b,
    ast.Gt: lambda a, b: a > b,
    ast.GtE: lambda a, b: a >= b,
}


def _transform(x: Any) -> np.ndarray:
    if not isinstance(x, _Pose):
        raise ValueError("expected a pose p[...]")
    return pose_to_transform(x.v)


def _pose(T: np.ndarray) -> _Pose:
    return _Pose(np.asarray(transform_to_pose(T), float))


def _target(run: _Run, x: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(joints, T_base_flange): a motion's target as joints (a list) or as a flange pose (a TCP pose)."""
    if isinstance(x, _Pose):
        return None, _transform(x) @ invert(run.host.T_flange_tcp)
    q = np.asarray(x, float)
    if q.shape != (6,):
        raise ValueError("a target is a pose p[...] or six joint positions")
    return run.host.joints_in(q), None


def _movej(run: _Run, target: Any, a: float = 1.4, v: float = 1.05, t: float = 0.0, r: float = 0.0) -> Steps:
    q, T = _target(run, target)
    if q is None:
        q = run.host._ik(T)  # type: ignore[arg-type]
        if q is None:
            raise ValueError("inverse kinematics failed: the pose is out of reach")
    run.budget = STATEMENTS_PER_CYCLE
    yield Move("joint", q, float(v), float(a))


def _movel(run: _Run, target: Any, a: float = 1.2, v: float = 0.25, t: float = 0.0, r: float = 0.0) -> Steps:
    q, T = _target(run, target)
    if T is None:
        T = run.host.flange_pose_of(q)  # type: ignore[arg-type]
    run.budget = STATEMENTS_PER_CYCLE
    yield Move("linear", T, float(v), float(a))


def _movep(run: _Run, target: Any, a: float = 1.2, v: float = 0.25, r: float = 0.0) -> Steps:
    return _movel(run, target, a, v)


def _movec(
    run: _Run, via: Any, to: Any, a: float = 1.2, v: float = 0.25, r: float = 0.0, mode: int = 0
) -> Steps:
    _target(run, via)  # checked: the arc through it is not modelled
    return _movel(run, to, a, v)


def _sleep(run: _Run, t: float) -> Steps:
    run.budget = STATEMENTS_PER_CYCLE
    yield Wait(float(t))


def _sync(run: _Run) -> Steps:
    run.budget = STATEMENTS_PER_CYCLE
    yield Wait(0.0)


def _textmsg(run: _Run, s1: Any, s2: Any = "") -> Steps:
    yield Message(f"{_text(s1)}{_text(s2)}")


def _popup(
    run: _Run,
    s: Any,
    title: str = "Popup",
    warning: bool = False,
    error: bool = False,
    blocking: bool = False,
) -> Steps:
    yield Message(f"{title}: {_text(s)}")


def _text(x: Any) -> str:
    return "p[" + ", ".join(f"{v:g}" for v in x.v) + "]" if isinstance(x, _Pose) else str(x)


def _set_tcp(run: _Run, pose: Any) -> None:
    run.host.T_flange_tcp = _transform(pose)


def _set_payload(run: _Run, m: float, cog: Any = None, *rest: Any) -> None:
    run.host.payload = (float(m), tuple(float(c) for c in (cog or (0.0, 0.0, 0.0))))


def _get_inverse_kin(
    run: _Run,
    x: Any,
    qnear: Any = None,
    maxPositionError: float = 1e-10,
    maxOrientationError: float = 1e-10,
    tcp: Any = None,
) -> list[float]:
    T_tcp = run.host.T_flange_tcp if tcp is None else _transform(tcp)
    seed = None if qnear is None else run.host.joints_in(np.asarray(qnear, float))
    q = run.host._ik(_transform(x) @ invert(T_tcp), seed)
    if q is None:
        raise ValueError("inverse kinematics failed: the pose is out of reach")
    return [float(v) for v in run.host.joints_out(q)]


def _get_forward_kin(run: _Run, q: Any = None, tcp: Any = None) -> _Pose:
    joints = run.host.q_cmd if q is None else run.host.joints_in(np.asarray(q, float))
    T_tcp = run.host.T_flange_tcp if tcp is None else _transform(tcp)
    return _pose(run.host.flange_pose_of(joints) @ T_tcp)


def _set_digital_out(run: _Run, n: int, b: bool) -> None:
    mask = 1 << int(n)
    run.host.digital_out = (run.host.digital_out | mask) if b else (run.host.digital_out & ~mask)


BUILTINS: dict[str, Callable[..., Any]] = {
    "movej": _movej,
    "movel": _movel,
    "movep": _movep,
    "movec": _movec,
    "sleep": _sleep,
    "sync": _sync,
    "textmsg": _textmsg,
    "popup": _popup,
    "set_tcp": _set_tcp,
    "set_payload": _set_payload,
    "set_target_payload": _set_payload,
    "set_standard_digital_out": _set_digital_out,
    "get_inverse_kin": _get_inverse_kin,
    "get_forward_kin": _get_forward_kin,
    "get_actual_tcp_pose": lambda run: _get_forward_kin(run),
    "get_target_tcp_pose": lambda run: _get_forward_kin(run),
    "get_actual_joint_positions": lambda run: [float(v) for v in run.host.joints_out(run.host.q_cmd)],
    "get_target_joint_positions": lambda run: [float(v) for v in run.host.joints_out(run.host.q_cmd)],
    "pose_trans": lambda run, a, b: _pose(_transform(a) @ _transform(b)),
    "pose_inv": lambda run, a: _pose(invert(_transform(a))),
    "pose_add": lambda run, a, b: _pose(_pose_add(_transform(a), _transform(b))),
    "sqrt": lambda run, x: math.sqrt(x),
    "sin": lambda run, x: math.sin(x),
    "cos": lambda run, x: math.cos(x),
    "d2r": lambda run, x: math.radians(x),
    "r2d": lambda run, x: math.degrees(x),
    "to_str": lambda run, x: _text(x),
}


def _pose_add(Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """URScript pose_add: positions added, rotations composed (b's rotation applied after a's, base axes)."""
    T = np.eye(4)
    T[:3, 3] = Ta[:3, 3] + Tb[:3, 3]
    T[:3, :3] = Tb[:3, :3] @ Ta[:3, :3]
    return T
