"""The stable CLI: hil calibrate / diagnose / predict on a simulated campaign, run in process (`hil.cli.main`;
the entry points as processes are tested in test_demo and test_cli_entry_points)."""

import hashlib
import json

import numpy as np
import pandas as pd
import pytest
from calib_data import cell_datasets

from tests.cli_in_process import run_hil

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    d = tmp_path_factory.mktemp("campaign")
    _, train, val = cell_datasets(step_m=0.12, n_val=60, seed=5)
    train.to_csv(d / "train.csv", index=False)
    val.to_csv(d / "val.csv", index=False)
    return d


def test_calibrate_diagnose_predict(campaign, capsys):
    d = campaign
    out = run_hil(
        "calibrate",
        "train.csv",
        "--robot",
        "ur10",
        "-o",
        "kin.json",
        "--residuals",
        "res.csv",
        cwd=d,
        capsys=capsys,
    )
    assert out.returncode == 0, out.stderr
    res = pd.read_csv(d / "res.csv")
    assert list(res.columns) == ["row", "dx_mm", "dy_mm", "dz_mm", "norm_mm", "weight", "outlier"]
    assert len(res) == len(pd.read_csv(d / "train.csv"))
    assert "ridge-igg3" in out.stdout and "lm-soft_l1" in out.stdout and "condition number" in out.stdout
    out = run_hil(
        "diagnose",
        "train.csv",
        "--robot",
        "ur10",
        "--validate",
        "val.csv",
        "-o",
        "model.json",
        "--json",
        "report.json",
        "--html",
        "report.html",
        cwd=d,
        capsys=capsys,
    )
    assert out.returncode == 0, out.stderr

    def strict(constant):  # NaN / Infinity are not JSON
        raise AssertionError(f"report.json holds {constant}")

    report = json.loads((d / "report.json").read_text(), parse_constant=strict)
    model_run = json.loads((d / "model.json").read_text(), parse_constant=strict)["info"]["run"]
    assert model_run["inputs"]["training"]["file"] == "train.csv"
    kin_run = json.loads((d / "kin.json").read_text())["info"]["run"]
    assert kin_run["robot"] == "ur10" and len(kin_run["inputs"]["training"]["sha256"]) == 64
    assert {"effects_added", "stages", "unexplained_structure", "noise_floor_mm"} <= set(report)
    run = report["run"]  # what the report was made from
    assert run["robot"] == "ur10" and run["software"].startswith("hil ")
    assert run["inputs"]["training"]["sha256"] == hashlib.sha256((d / "train.csv").read_bytes()).hexdigest()
    assert run["inputs"]["validation"]["rows_used"] == len(pd.read_csv(d / "val.csv"))
    assert report["effects_added"] and report["effects_added"][0]["name"] == "gravity_compliance"
    for stage in report["stages"]:
        assert stage["on"] in ("heldout", "validate")
        assert {"stage", "mean_mm", "rms_mm", "max_mm", "p95_mm"} <= set(stage)
    page = (d / "report.html").read_text()
    assert "data:image/png;base64," in page and "gravity_compliance" in page
    # the 95 % intervals' coverage: on held-out rows and on the validation campaign, printed and in the page
    assert [c["on"] for c in report["intervals"]] == ["heldout", "validate"]
    assert "Prediction intervals (95 %" in out.stdout and "Prediction intervals (95 %" in page
    # predict applies everything the model holds: on the validation joints it matches the tracker.
    joints = pd.read_csv(d / "val.csv").drop(columns=["x_mm", "y_mm", "z_mm"])
    joints.to_csv(d / "joints.csv", index=False)
    out = run_hil("predict", "model.json", "joints.csv", "-o", "pred.csv", cwd=d, capsys=capsys)
    assert out.returncode == 0, out.stderr
    pred = pd.read_csv(d / "pred.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy()
    meas = pd.read_csv(d / "val.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy()
    rms = np.sqrt(np.mean(np.sum((pred - meas) ** 2, axis=1)))
    val_final = [s for s in report["stages"] if s["on"] == "validate"][-1]["rms_mm"]
    assert rms == pytest.approx(val_final, rel=1e-4)  # CSV rounding only


def test_bad_input_gets_a_clear_error(campaign, capsys):
    d = campaign
    pd.read_csv(d / "train.csv").drop(columns=["z_mm"]).to_csv(d / "broken.csv", index=False)
    out = run_hil("calibrate", "broken.csv", "-o", "x.json", cwd=d, capsys=capsys)
    assert out.returncode == 2 and "z_mm" in out.stderr
    out = run_hil(
        "diagnose", "train.csv", "--json", "r.json", "--families", "gravity,cyclic", cwd=d, capsys=capsys
    )
    assert out.returncode == 2 and "gravity" in out.stderr
    pd.read_csv(d / "train.csv").head(12).to_csv(d / "tiny.csv", index=False)
    out = run_hil("calibrate", "tiny.csv", "-o", "x.json", cwd=d, capsys=capsys)
    assert out.returncode == 2 and "well-spread poses" in out.stderr
