"""`hil demo` end to end on a small campaign: offline diagnosis, then the live loop through hil sim."""

import json
import subprocess
import sys

import pandas as pd
import pytest


@pytest.mark.sim  # the live loop starts a simulated cell
@pytest.mark.timeout(180)
def test_demo_finds_compliance_and_predicts_live_measurements(tmp_path):
    args = [sys.executable, "-m", "hil", "demo", "--step-mm", "150", "--validate", "40", "--live", "2"]
    out = subprocess.run([*args, "--out", str(tmp_path)], capture_output=True, text=True, timeout=170)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert {e["name"] for e in report["effects_added"]} == {"gravity_compliance"}
    live = pd.read_csv(tmp_path / "live.csv")
    assert len(live) == 2 and "live prediction error" in out.stdout
    for name in ("grid.csv", "validate.csv", "report.html", "model.json"):
        assert (tmp_path / name).stat().st_size > 0


def test_demo_refuses_an_unknown_effect(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "hil", "demo", "--effects", "gravity", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0 and "unknown effect" in out.stderr
