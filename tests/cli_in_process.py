"""Run the `hil` CLI in this process (fast, no interpreter start-up) from a given folder."""

from __future__ import annotations

import os


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
