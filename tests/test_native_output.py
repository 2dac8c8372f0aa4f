"""What native libraries print while instruments are connected stays out of the terminal: it is logged (the
campaign log) and shown with --verbose; Python's own output still reaches the terminal. A Ctrl-C says what
happened and the command that resumes."""

from __future__ import annotations

import subprocess
import sys

from hil.cli import _interrupted

SCRIPT = """
import logging, os, sys
from hil.commands.native_output import capture_native_output
seen = []
logging.getLogger("hil.native").addHandler(type("H", (logging.Handler,), {"emit": lambda self, r: seen.append(r.getMessage())})())
logging.getLogger("hil.native").setLevel(logging.INFO)
with capture_native_output(verbose=sys.argv[1] == "verbose"):
    os.write(2, b"RTDEControlInterface Exception: Timeout connecting to UR dashboard server.\\n")
    os.write(1, b"native chatter on stdout\\n")
    print("python says hello")
    print("python warns", file=sys.stderr)
print("logged:", seen)
"""


def _run(mode: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, timeout=60)


def test_native_output_is_logged_not_shown():
    done = _run("quiet")
    assert done.returncode == 0, done.stderr
    assert (
        "RTDEControlInterface" not in done.stderr and "native chatter" not in done.stdout.split("logged:")[0]
    )
    assert "python says hello" in done.stdout and "python warns" in done.stderr
    assert "Timeout connecting to UR dashboard server." in done.stdout.split("logged:")[1]
    assert "native chatter on stdout" in done.stdout.split("logged:")[1]


def test_native_output_is_shown_with_verbose():
    done = _run("verbose")
    assert "[native] RTDEControlInterface Exception: Timeout connecting" in done.stderr


def test_ctrl_c_says_what_happened_and_how_to_resume():
    text = _interrupted(
        "run", ["run", "registration", "--cell", "cell.toml", "--campaign", "my job.sqlite"]
    ).render("run")
    first, second = text.splitlines()
    assert first == "hil run: interrupted (Ctrl-C): the robot was stopped and every recorded point is kept"
    assert (
        second
        == "  what to do: resume with: hil run registration --cell cell.toml --campaign 'my job.sqlite'"
    )
    assert "run it again: hil campaign show x" in _interrupted("campaign", ["campaign", "show", "x"]).render(
        "campaign"
    )
