"""The command line imports a command's module only when that command runs: `hil --help` and `hil calibrate`
load no simulator, no driver, no procedure and no plotting library (a state check on sys.modules)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from calib_data import synthetic

from hil.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]
# the plug-ins, the procedures, plotting, and the hardware libraries (ur-rtde's modules, pyserial)
NEVER_AT_START = (
    "fakes", "drivers", "procedures", "matplotlib",
    "ur_rtde", "rtde_control", "rtde_receive", "rtde_io", "dashboard_client", "script_client", "serial",
)  # fmt: skip

# Runs `hil ARGS` in a fresh interpreter, then prints the top-level packages it imported, as JSON.
PROBE = """
import json, sys
from hil.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})), file=sys.stderr)
"""


def _imported(*args: str, cwd: Path = ROOT) -> set[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=120
    )
    return set(json.loads(done.stderr.strip().splitlines()[-1]))


def test_help_imports_no_instrument_procedure_or_heavy_library():
    imported = _imported("--help")
    assert not imported & set(NEVER_AT_START), sorted(imported & set(NEVER_AT_START))
    assert not imported & {"numpy", "scipy", "pandas", "sklearn"}, sorted(imported)
    assert "hil" in imported  # the probe did run the command line


def test_calibrate_imports_no_simulator_driver_or_plotting(tmp_path):
    _, dataset, _ = synthetic(n=60, seed=3)
    dataset.to_csv(tmp_path / "data.csv", index=False)
    imported = _imported("calibrate", "data.csv", "--robot", "ur10", "-o", "model.json", cwd=tmp_path)
    assert (tmp_path / "model.json").exists()  # it calibrated
    assert not imported & set(NEVER_AT_START), sorted(imported & set(NEVER_AT_START))


def test_the_static_command_table_matches_each_command_module():
    full = build_parser()
    lazy = build_parser(load=[])
    for parser in (full, lazy):
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        helps = {action.dest: action.help for action in sub._choices_actions}
        assert helps == {name: help_line for name, (_, help_line) in COMMANDS.items()}
