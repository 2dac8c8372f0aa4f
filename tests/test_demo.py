"""`hil demo` end to end: the procedures through the drivers on hil sim, then diagnosis and reports;
a second run resumes the campaign and measures nothing again (a second full demo: `make soak`)."""

import json
import sqlite3
import subprocess
import sys
import tomllib

import pytest
from test_report_html import PYTHON_REPR, visible_text

from tests.cli_in_process import hil_in_process

pytestmark = pytest.mark.sim  # `hil demo` starts the simulated cell


def _demo_args(out) -> list[str]:
    # The whole job at a small size (200 mm grid, 20 validation poses, 3 loop targets, a 20-pose active round,
    # 50x simulated time, the smallest tool fit): every stage runs and the gravity compliance is still found;
    # `make demo` runs it full.
    small = [
        "--step-mm",
        "200",
        "--validate",
        "20",
        "--loop-targets",
        "3",
        "--active-poses",
        "20",
        "--time-scale",
        "50",
        "--tool-check-poses",
        "6",
        "--tool-validation-poses",
        "4",
    ]
    return [sys.executable, "-m", "hil", "demo", *small, "--out", str(out)]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """`hil demo` run once as a process (the entry point as a user runs it); its folder and output."""
    out = tmp_path_factory.mktemp("demo")
    done = subprocess.run(_demo_args(out), capture_output=True, text=True, timeout=380)
    return out, done


@pytest.mark.timeout(400)
def test_demo_runs_the_procedures_through_the_drivers_and_finds_compliance(demo):
    tmp_path, out = demo
    assert out.returncode == 0, out.stderr[-3000:] + out.stdout[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert {e["name"] for e in report["effects_added"]} == {"gravity_compliance"}
    cell = tomllib.loads(
        (tmp_path / "cell.toml").read_text()
    )  # written once; every stage's cell came back there
    assert (
        out.stdout.count(f"wrote {tmp_path / 'cell.toml'}") == 1
        and f"same address as {tmp_path / 'cell.toml'}" in out.stdout
    )
    restart = next(line for line in out.stdout.splitlines() if "starts it again" in line)
    assert (
        f"hil sim --host {cell['robot']['host']} --control-port {cell['simulator']['control'].rsplit(':', 1)[1]}"
        in restart
    )
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
    # the JSON holds what the HTML shows: the round's record, the measured loop, the tool fit
    (round1,) = report["active_loop"]["rounds"]
    assert round1["undecided"] and round1["measured"]["poses"] > 0 and report["active_loop"]["stop"]
    assert report["measured_loop"]["targets"] == 3 and "nests_flange_mm" in report["tool_fit"]
    # the tool fit's declared measurements as the engine judged them, in mm and degrees
    judged = {o["measurement"]: o for o in report["outcomes"] if o["procedure"] == "tool_fit"}
    assert judged["circle_residual"]["outcome"] == "pass" and judged["circle_residual"][
        "limit"
    ] == pytest.approx(0.03)
    assert judged["validation_rms"]["outcome"] == "not judged" and judged["hole_angle_error"]["unit"] == "deg"
    assert "Judged measurements" in (tmp_path / "report.html").read_text()
    # the whole page in words: the tool fit, the rounds, the outcomes and the loop show no Python value
    shown = visible_text((tmp_path / "report.html").read_text())
    assert not sorted({m.group(0) for m in PYTHON_REPR.finditer(shown)}), shown[:3000]


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_demo_run_again_resumes_and_measures_nothing_twice(demo):
    """The resume of a whole demo. By default the resume of each procedure's campaign is checked in
    test_procedures_sim (grid sampling again measures nothing) and test_pseudo_target_sim (the loop)."""
    tmp_path, first = demo
    assert first.returncode == 0, first.stderr[-3000:]
    with sqlite3.connect(tmp_path / "campaign.sqlite") as db:
        (count,) = db.execute("select count(*) from measurements").fetchone()
    again = subprocess.run(_demo_args(tmp_path), capture_output=True, text=True, timeout=380)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resuming" in again.stdout
    with sqlite3.connect(tmp_path / "campaign.sqlite") as db:
        assert db.execute("select count(*) from measurements").fetchone() == (count,)


def test_demo_refuses_an_unknown_effect(tmp_path, capsys):
    code, _, err = hil_in_process(
        "demo", "--effects", "gravity", "--out", str(tmp_path), cwd=tmp_path, capsys=capsys
    )
    assert code != 0 and "unknown effect" in err


def test_demo_refuses_too_small_a_tool_fit_before_starting_a_cell(tmp_path, capsys):
    code, _, err = hil_in_process(
        "demo", "--tool-check-poses", "3", "--out", str(tmp_path), cwd=tmp_path, capsys=capsys
    )
    assert code == 2 and "at least 6 check poses" in err
    assert not (tmp_path / "campaign.sqlite").exists()
