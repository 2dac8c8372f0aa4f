"""The installed `hil` console script runs as a process (the commands themselves are tested in process,
through `hil.cli.main`; `python -m hil` as a process: test_demo, test_campaign_faults)."""

import subprocess
import sys
from pathlib import Path

import pytest

from tests.cell_fixtures import sim_cell_toml


def test_the_hil_console_script_runs_a_command(tmp_path):
    script = Path(sys.executable).with_name("hil")
    if not script.exists():
        pytest.skip("the hil console script is not installed next to this interpreter (pip install -e .)")
    good = tmp_path / "cell.toml"
    good.write_text(sim_cell_toml())
    ok = subprocess.run(
        [str(script), "cell", "check", str(good)], capture_output=True, text=True, timeout=120
    )
    assert ok.returncode == 0 and "the configuration is valid" in ok.stdout and "ur10" in ok.stdout, ok.stderr
    broken = tmp_path / "broken.toml"
    broken.write_text("[robot\nmodel = ")
    out = subprocess.run(
        [str(script), "cell", "check", str(broken)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2 and "not valid TOML" in out.stderr and "broken.toml" in out.stderr
