"""Run the `hil` CLI in this process (fast, no interpreter start-up) from a given folder."""

from __future__ import annotations

import os
from types import SimpleNamespace


def hil_in_process(*args: str, cwd, capsys) -> tuple[int, str, str]:
    """`hil ARGS...` run from `cwd`; returns (exit code, stdout, stderr)."""
    from hil.cli import main

    here = os.getcwd()
    os.chdir(cwd)
    try:
        code = main(list(args))
    finally:
        os.chdir(here)
    out = capsys.readouterr()
    return code, out.out, out.err


def run_hil(*args: str, cwd, capsys) -> SimpleNamespace:
    """`hil ARGS...` in process, answered as subprocess.run answers: returncode, stdout, stderr (argparse's
    usage errors, which leave through SystemExit, give its code as the process would)."""
    try:
        code, out, err = hil_in_process(*args, cwd=cwd, capsys=capsys)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
        captured = capsys.readouterr()
        out, err = captured.out, captured.err
    return SimpleNamespace(returncode=code, stdout=out, stderr=err)
