"""Every remedy an instrument error carries, and every refusal the command line and the runner say, is in the
user's terms: no Python API (`robot.recover()`, `point_at`), no 'the next call', no Python values (None, True)."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from pathlib import Path

import pytest

from hil.errors import ActionableError

ROOT = Path(__file__).resolve().parents[1]
PYTHON_WORDING = re.compile(
    r"\w\(\)|\b[a-z_]+\.[a-z_]+\(|\bcall\b|\bcalls\b|\bretry\b|\bNone\b|\bTrue\b|\bFalse\b|\bkwargs?\b|Error\b|\bdict\b"
)
ERROR_MODULES = (
    "hil.errors",
    "hil.instruments.robot",
    "hil.instruments.tracker",
    "hil.runner.session",
    "hil.commands.errors",
    "hil.station.instruments",
)
REFUSALS = (
    "CliError",
    "SessionSetupError",
    "InputError",
    "CampaignStopped",
    "ParameterError",
    "CellConfigError",
    "from_text",
)


def _error_classes() -> list[type[ActionableError]]:
    found = set()
    for name in ERROR_MODULES:
        module = importlib.import_module(name)
        found |= {c for _, c in inspect.getmembers(module, inspect.isclass) if issubclass(c, ActionableError)}
    return sorted(found, key=lambda c: c.__qualname__)


@pytest.mark.parametrize("error", _error_classes(), ids=lambda c: c.__name__)
def test_every_instrument_error_remedy_is_in_the_users_terms(error):
    assert not PYTHON_WORDING.search(error.remedy), f"{error.__name__}.remedy: {error.remedy!r}"


def _refusal_texts(path: Path):
    """The string literals (f-strings' constant parts) passed to an error a user reads, with their line."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", getattr(node.func, "attr", "")) in REFUSALS
        ):
            for arg in [*node.args, *(k.value for k in node.keywords)]:
                parts = arg.values if isinstance(arg, ast.JoinedStr) else [arg]
                text = "".join(
                    p.value for p in parts if isinstance(p, ast.Constant) and isinstance(p.value, str)
                )
                if text:
                    yield node.lineno, text


SOURCES = sorted([*(ROOT / "hil").rglob("*.py"), *(ROOT / "procedures").glob("*.py")])


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_refusal_is_in_the_users_terms(path):
    bad = [f"line {line}: {text!r}" for line, text in _refusal_texts(path) if PYTHON_WORDING.search(text)]
    assert not bad, "\n".join(bad)


def test_the_wording_check_finds_python_terms():
    for text in (
        "call robot.recover() to rebuild",
        "the next call reconnects",
        "outlier rows None",
        "OutlierError: 2",
    ):
        assert PYTHON_WORDING.search(text), text
    assert not PYTHON_WORDING.search("clear the line of sight, then run the command again")


def test_a_clean_up_that_outlives_its_time_says_so_in_the_users_terms(caplog):
    """After Ctrl-C the robot gets a second to stop and disconnect; a controller that does not answer in time
    is left behind with words that say what that means at the cell, not 'releasing ... did not finish'."""
    import logging
    import threading

    from hil.runner.session import _bounded

    release = threading.Event()
    with caplog.at_level(logging.WARNING, logger="hil"):
        _bounded([("robot", lambda: release.wait(10.0)), ("tracker", lambda: None)], 0.05)
    release.set()
    assert "the robot had not finished closing after 0.1 s" in caplog.text
    assert "the controller stops the arm when its connection drops" in caplog.text
    assert "tracker" not in caplog.text and "going on" not in caplog.text
