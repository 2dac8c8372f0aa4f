"""Run the `hil` CLI in this process (fast, no interpreter start-up) from a given folder."""

from __future__ import annotations

import os
from types import SimpleNamespace


def hil_in_process(*args: str, cwd, capsys) -> tuple[int, str, str]:
    """`hil ARGS...` run from `cwd`; returns (exit code, stdout, stderr) as the process would end."""
    from hil.cli import main

    here = os.getcwd()
    os.chdir(cwd)
    try:
        code = main(list(args))
    except SystemExit as exc:  # argparse's usage errors and --help leave through SystemExit
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
    finally:
        os.chdir(here)
    out = capsys.readouterr()
    return code, out.out, out.err


def run_hil(*args: str, cwd, capsys) -> SimpleNamespace:
    """`hil ARGS...` in process, answered as subprocess.run answers: returncode, stdout, stderr."""
    code, out, err = hil_in_process(*args, cwd=cwd, capsys=capsys)
    return SimpleNamespace(returncode=code, stdout=out, stderr=err)
