"""`hil demo` end to end: the procedures through the drivers on hil sim, then diagnosis and reports;
a second run resumes the campaign and measures nothing again."""

import json
import sqlite3
import subprocess
import sys
import tomllib

import pytest


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_demo_runs_the_procedures_through_the_drivers_and_finds_compliance(tmp_path):
    args = [sys.executable, "-m", "hil", "demo", "--step-mm", "150", "--validate", "40", "--out", str(tmp_path)]
    out = subprocess.run(args, capture_output=True, text=True, timeout=380)
    assert out.returncode == 0, out.stderr[-3000:] + out.stdout[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert {e["name"] for e in report["effects_added"]} == {"gravity_compliance"}
    cell = tomllib.loads((tmp_path / "cell.toml").read_text())  # written once; every stage's cell came back there
    assert out.stdout.count(f"wrote {tmp_path / 'cell.toml'}") == 1 and f"same address as {tmp_path / 'cell.toml'}" in out.stdout
    restart = next(line for line in out.stdout.splitlines() if "starts it again" in line)
    assert f"hil sim --host {cell['robot']['host']} --control-port {cell['simulator']['control'].rsplit(':', 1)[1]}" in restart
    for name in ("cell.toml", "campaign.sqlite", "grid.csv", "validate.csv", "report.html", "model.json"):
        assert (tmp_path / name).stat().st_size > 0
    for step in ("registration", "tool fit", "grid sampling", "measured pseudo-target loop"):
        assert step in out.stdout
    stages = {line.split()[0]: float(line.split()[-4]) for line in out.stdout.splitlines()
              if line.strip().startswith(("uncompensated", "model-based", "measured loop"))}  # fmt: skip
    assert set(stages) == {"uncompensated", "model-based", "measured"}, out.stdout[-2000:]
    # mean measured errors, mm: the model removes most of it, the measured loop ends near the ~0.013 mm floor
    assert stages["model-based"] < 0.2 * stages["uncompensated"] and stages["measured"] < 0.03
    assert "Measured pseudo-target loop" in (tmp_path / "report.html").read_text()
    assert "active loop ended after 1 round(s)" in out.stdout  # the grid leaves questions open: one round
    assert "Active loop: the measurements that decide" in (tmp_path / "report.html").read_text()
    with sqlite3.connect(tmp_path / "campaign.sqlite") as db:
        (count,) = db.execute("select count(*) from measurements").fetchone()
    again = subprocess.run(args, capture_output=True, text=True, timeout=380)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resuming" in again.stdout
    with sqlite3.connect(tmp_path / "campaign.sqlite") as db:
        assert db.execute("select count(*) from measurements").fetchone() == (count,)


def test_demo_refuses_an_unknown_effect(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "hil", "demo", "--effects", "gravity", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0 and "unknown effect" in out.stderr
