"""The suite's own bookkeeping: a test module that opens sockets or starts the simulated cell carries the
`sim` mark (so `pytest -m 'not sim'` runs no socket test), and `pytestmark` is assigned once per module (a
second assignment silently replaces the first, as it once dropped `sim`)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

# Importing one of these means the module talks over sockets or starts the simulated cell.
SOCKET_MODULES = {
    "socket",
    "asyncio",
    "fakes.launch",
    "fakes.sim",
    "fakes.sim_process",
    "fakes.emscon_server",
    "fakes.ur_rtde_server",
    "fakes.control_client",
    "rtde_control",
    "rtde_receive",
    "rfc2217_bridge",
    "sim_session",
    "tests.sim_session",
    "tests.rfc2217_bridge",
}
# Calling one of these starts the simulated cell or a fake server.
SOCKET_CALLS = {"sim_cell", "running_cell", "session_on", "ServerThread", "EmsconServer", "Rfc2217Bridge"}
# `hil <command>` run as a process that starts the simulated cell.
CELL_COMMANDS = {"demo", "sim"}


def socket_uses(tree: ast.Module) -> list[str]:
    """What in a test module's source opens sockets or starts the simulated cell (empty: nothing)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if a.name in SOCKET_MODULES]
        elif isinstance(node, ast.ImportFrom) and node.module in SOCKET_MODULES:
            found.append(f"from {node.module} import")
        elif isinstance(node, ast.ImportFrom) and node.module in ("fakes", "tests"):
            found += [
                f"from {node.module} import {a.name}"
                for a in node.names
                if f"{node.module}.{a.name}" in SOCKET_MODULES
            ]
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
            if name in SOCKET_CALLS:
                found.append(f"{name}(...)")
        elif isinstance(node, ast.List | ast.Tuple):
            words = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
            if any(a == "hil" and b in CELL_COMMANDS for a, b in zip(words, words[1:], strict=False)):
                found.append(f"hil {words[words.index('hil') + 1]} as a process")
    return found


def pytestmark_assignments(tree: ast.Module) -> list[ast.expr]:
    """The values assigned to the module-level `pytestmark`, in order."""
    values = []
    for node in tree.body:
        targets = (
            node.targets
            if isinstance(node, ast.Assign)
            else [node.target]
            if isinstance(node, ast.AnnAssign)
            else []
        )
        if any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in targets):
            values.append(node.value)  # type: ignore[attr-defined]
    return [v for v in values if v is not None]


def marks_in(value: ast.expr) -> set[str]:
    """The names of `pytest.mark.NAME` (called or not) in a pytestmark value."""
    names = set()
    for node in ast.walk(value):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Attribute)
            and node.value.attr == "mark"
        ):
            names.add(node.attr)
    return names


MODULES = sorted(TESTS.glob("test_*.py"))


@pytest.mark.parametrize("path", MODULES, ids=[p.name for p in MODULES])
def test_a_module_that_opens_sockets_is_marked_sim(path):
    tree = ast.parse(path.read_text(), str(path))
    assigned = pytestmark_assignments(tree)
    assert len(assigned) <= 1, f"{path.name} assigns pytestmark {len(assigned)} times: the last one wins"
    uses = socket_uses(tree)
    if uses:
        assert assigned and "sim" in marks_in(assigned[-1]), (
            f"{path.name} opens sockets or starts the simulated cell ({', '.join(sorted(set(uses)))}) "
            "but its pytestmark lacks pytest.mark.sim"
        )


def test_the_scan_finds_what_it_looks_for():
    """The scan itself can fail: it sees each kind of use, a double assignment and a missing mark."""
    source = """
import pytest
from fakes.launch import sim_cell
pytestmark = pytest.mark.sim
pytestmark = pytest.mark.timeout(30)
def test_x():
    subprocess.run([sys.executable, "-m", "hil", "demo"])
"""
    tree = ast.parse(source)
    assert socket_uses(tree) == ["from fakes.launch import", "hil demo as a process"]
    assigned = pytestmark_assignments(tree)
    assert len(assigned) == 2 and marks_in(assigned[-1]) == {"timeout"} and marks_in(assigned[0]) == {"sim"}
    assert socket_uses(ast.parse("import socket\nwith running_cell(p) as c: pass")) == [
        "import socket",
        "running_cell(...)",
    ]
    assert socket_uses(ast.parse("import numpy\nmain(['sim', '--host', '10.0.0.1'])")) == []
    assert marks_in(ast.parse("[pytest.mark.sim, pytest.mark.timeout(400)]", mode="eval").body) == {
        "sim",
        "timeout",
    }
