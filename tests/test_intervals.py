"""Prediction intervals (hil.model.intervals): the contract (P respected, wider off the training poses and
outside the temperature span, an old model refused with a remedy) and their coverage on a simulated cell's
later, warmer validation poses (a loose bound; benchmarks/intervals.py checks the goal over many cells)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from sim_campaigns import grid_joints, held_out_joints

from fakes.campaign import simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.diagnosis.pipeline import run_diagnosis
from hil.data.dataset import points_m
from hil.model.calibrated_model import CalibratedModel
from hil.model.intervals import IntervalError
from hil.model.prediction_intervals import prediction_intervals
from tests.cli_in_process import run_hil

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def warm_cell():
    """A diagnosed UR10 cell whose hall warms: a 150 mm grid, then random poses 2 K warmer than any of it."""
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=3, thermal=True))
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=3))
    hottest = float(train["temperature_c"].max())
    while cell.structure_temperature_c() < hottest + 2.0:
        cell.advance_time(60.0)
    val = simulate_campaign(cell, held_out_joints(cell, 100, seed=4))
    report = run_diagnosis(train, "ur10", df_validate=val)
    return train, val, report


def test_probability_is_respected(warm_cell):
    train, _, report = warm_cell
    r = {p: prediction_intervals(report.model, train, p).radius_m for p in (0.5, 0.9, 0.95, 0.99)}
    assert np.all(r[0.5] < r[0.9]) and np.all(r[0.9] <= r[0.95]) and np.all(r[0.95] <= r[0.99])
    # the held-out rows the factor is read from: about P of them inside (conformal, >= P)
    for cov in report.intervals[:1]:
        assert cov["on"] == "heldout" and 0.95 <= cov["covered"] <= 0.99
    for p in (0.0, 1.0, 1.5):
        with pytest.raises(IntervalError, match="between 0 and 1"):
            prediction_intervals(report.model, train, p)
    n = report.model.spread.n_heldout
    with pytest.raises(IntervalError, match=f"{n} held-out rows support at most"):
        prediction_intervals(report.model, train, 1.0 - 0.1 / n)


def test_wider_off_the_training_poses(warm_cell):
    train, _, report = warm_cell
    at = train.iloc[:20].copy()
    off = at.copy()
    off["q1_rad"] = off["q1_rad"] + 2.0  # the arm turned away from the grid, where no training pose was
    off["q4_rad"] = off["q4_rad"] + 1.0
    iv_at = prediction_intervals(report.model, at)
    iv_off = prediction_intervals(report.model, off)
    spread = report.model.spread
    assert np.all(iv_off.extrapolation.joint_distance_m > spread.tested_distance_m)
    assert np.all(iv_off.radius_m > 1.1 * iv_at.radius_m)
    assert any("farther from the training poses" in note for note in iv_off.notes)


def test_wider_outside_the_temperatures(warm_cell):
    train, _, report = warm_cell
    at = train.iloc[:20].copy()
    span = report.model.spread.temperature_span_c
    assert span is not None
    warm = at.assign(temperature_c=span.high + 5.0)
    warmer = at.assign(temperature_c=span.high + 10.0)
    r_at = prediction_intervals(report.model, at).radius_m
    r_warm = prediction_intervals(report.model, warm).radius_m
    r_warmer = prediction_intervals(report.model, warmer).radius_m
    assert np.all(r_warm > r_at) and np.all(r_warmer > r_warm)
    # rows without a temperature are taken as anywhere in the span, and the caller is told
    iv = prediction_intervals(report.model, at.drop(columns=["temperature_c"]))
    assert any("without temperature_c" in note for note in iv.notes)


def test_coverage_on_later_warmer_validation(warm_cell):
    _, val, report = warm_cell
    iv = prediction_intervals(report.model, val, 0.95)
    err = np.linalg.norm(report.model.predict(val) - points_m(val), axis=1)
    covered = float(np.mean(err <= iv.radius_m))
    rms = float(np.sqrt(np.mean(err**2)))
    assert 0.85 <= covered <= 1.0
    assert np.median(iv.radius_m) <= 3.0 * rms  # sharp, not merely wide
    on_val = report.intervals[-1]
    assert on_val["on"] == "validate" and on_val["covered"] == pytest.approx(covered)


def test_model_file_round_trip_and_old_format_refused(warm_cell, tmp_path, capsys):
    train, val, report = warm_cell
    report.model.save(tmp_path / "model.json")
    again = CalibratedModel.load(tmp_path / "model.json")
    assert np.allclose(
        prediction_intervals(again, val).radius_m, prediction_intervals(report.model, val).radius_m
    )
    data = json.loads((tmp_path / "model.json").read_text())
    assert data["format"] == "hil-calibrated-model/2"
    data["format"] = "hil-calibrated-model/1"
    del data["spread"]
    (tmp_path / "old.json").write_text(json.dumps(data))
    old = CalibratedModel.load(tmp_path / "old.json")
    assert np.allclose(old.predict(val), report.model.predict(val))  # the old model still predicts
    with pytest.raises(IntervalError, match="hil-calibrated-model/1.*hil diagnose"):
        prediction_intervals(old, val)
    val.drop(columns=["x_mm", "y_mm", "z_mm"]).to_csv(tmp_path / "joints.csv", index=False)
    out = run_hil(
        "predict", "old.json", "joints.csv", "-o", "p.csv", "--interval", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode != 0 and "no prediction spread" in out.stderr and "hil diagnose" in out.stderr
    assert not (tmp_path / "p.csv").exists()
    out = run_hil("predict", "old.json", "joints.csv", "-o", "p.csv", cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    out = run_hil(
        "predict",
        "model.json",
        "joints.csv",
        "-o",
        "p.csv",
        "--force",
        "--interval",
        "0.9",
        cwd=tmp_path,
        capsys=capsys,
    )
    assert out.returncode == 0, out.stderr
    pred = pd.read_csv(tmp_path / "p.csv")
    expected = prediction_intervals(report.model, val, 0.9).radius_mm
    assert np.allclose(pred["interval_mm"].to_numpy(), expected, rtol=1e-6)


def test_compensate_gives_each_target_its_interval(warm_cell, tmp_path, capsys):
    _, val, report = warm_cell
    report.model.save(tmp_path / "model.json")
    targets = val.iloc[:8][["x_mm", "y_mm", "z_mm", "temperature_c"]]
    targets.to_csv(tmp_path / "targets.csv", index=False)
    out = run_hil("compensate", "model.json", "targets.csv", "-o", "q.csv", cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    got = pd.read_csv(tmp_path / "q.csv")
    assert np.all(np.isfinite(got["interval_mm"])) and "within error_mm + interval_mm" in out.stdout
    # the interval is the model's at the compensated joints, at their temperature
    at = got[[f"q{j}_rad" for j in range(1, 7)]].assign(
        temperature_c=targets["temperature_c"].to_numpy(), smr=1
    )
    expected = prediction_intervals(report.model, at, 0.95).radius_mm
    assert np.allclose(got["interval_mm"].to_numpy(), expected, rtol=1e-6)
    data = json.loads((tmp_path / "model.json").read_text())
    data["format"] = "hil-calibrated-model/1"
    del data["spread"]
    (tmp_path / "old.json").write_text(json.dumps(data))
    out = run_hil("compensate", "old.json", "targets.csv", "-o", "q_old.csv", cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    assert "no intervals" in out.stderr and "hil diagnose" in out.stderr
    assert "interval_mm" not in pd.read_csv(tmp_path / "q_old.csv").columns
