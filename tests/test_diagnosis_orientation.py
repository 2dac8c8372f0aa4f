"""Diagnosis uses every equation the data has: a 6-DoF probe's orientations reveal an effect its positions
cannot show, and the batched screening reproduces the per-candidate refit on those 6-coordinate rows.

Its orientation intervals (hil.model.intervals, AngleSpread): a 6-DoF probe's rows get interval_deg, the angle
about the predicted orientation that holds the measured one with probability P; rows without orientation get
none; a model file from before the orientation's spread is refused, never given one from the positions'."""

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from calib_data import ANGLE_NOISE_RAD, wrist_cyclic_campaign, wrist_cyclic_campaigns

from hil.analysis.diagnosis.cautions import CalibrationNote
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
from hil.data.dataset import ORIENTATION_COLUMNS, orientations
from hil.geometry.se3 import rotation_log
from hil.model.calibrated_model import CalibratedModel
from hil.model.intervals import IntervalError
from hil.model.prediction_intervals import prediction_intervals
from hil.report.text import intervals_text
from tests.cli_in_process import run_hil

pytestmark = pytest.mark.timeout(180)

CYCLIC = DiagnosisOptions(families=("cyclic",))  # only the cyclic errors are candidates


@pytest.fixture(scope="module")
def probe_cell():
    """The diagnosed 6-DoF probe campaign (`wrist_cyclic_campaign`: 250 poses) and 150 later poses of the
    same arm."""
    train, val = wrist_cyclic_campaigns((250, 150), seed=4)
    return train, val, run_diagnosis(train, "ur10", df_validate=val, options=CYCLIC)


def _names(report):
    return [(e["name"], e["joint"]) for e in report.effects_added]


@pytest.mark.timeout(
    480
)  # its setup builds the module's 6-DoF diagnosis: 27 s alone, 180 s on a loaded CI box
def test_an_effect_seen_only_in_the_probe_orientation_is_selected_with_orientations_and_not_without(
    probe_cell,
):
    df, _, with_rot = probe_cell
    assert ("cyclic", 6) in _names(with_rot)
    positions = df.drop(columns=list(ORIENTATION_COLUMNS))
    positions.attrs = dict(df.attrs)
    without = run_diagnosis(positions, "ur10", options=CYCLIC)
    assert ("cyclic", 6) not in _names(without)
    # the batched screening on 6-coordinate rows (positions and weighted rotations) is the refit's answer
    slow = run_diagnosis(df, "ur10", options=replace(CYCLIC, screening="refit"))
    assert _names(slow) == _names(with_rot)
    for x, y in zip(with_rot.final_round, slow.final_round, strict=True):
        assert (x.name, x.joint, x.passed) == (y.name, y.joint, y.passed)
        assert x.gain_mm2 == pytest.approx(y.gain_mm2, rel=1e-7, abs=1e-12)


def test_orientations_far_noisier_than_stated_are_left_out_of_the_tests_and_the_verdict_says_so():
    df = wrist_cyclic_campaign(angle_noise_rad=3 * ANGLE_NOISE_RAD)  # the probe reads 3x worse than stated
    report = run_diagnosis(df, "ur10", options=CYCLIC)
    assert ("cyclic", 6) not in _names(report)
    notes = [c.text for c in report.verdict["cautions"] if isinstance(c, CalibrationNote)]
    assert any("tested on positions only" in t for t in notes)
    # no orientation spread was measured: the intervals give no angle for these rows, and say why
    iv = prediction_intervals(report.model, df)
    assert iv.angle_rad is None
    assert any("no interval_deg" in n and "left them out" in n for n in iv.notes)


def _angle_errors_rad(model: CalibratedModel, df: pd.DataFrame) -> np.ndarray:
    R_measured = orientations(df)
    assert R_measured is not None
    R_predicted = model.predict_rotation(df)
    return np.linalg.norm(rotation_log(R_measured @ np.swapaxes(R_predicted, 1, 2)), axis=1)


def test_orientation_intervals_cover_later_poses_and_are_sharp(probe_cell):
    _, val, report = probe_cell
    iv = prediction_intervals(report.model, val, 0.95)
    assert iv.angle_rad is not None and iv.angle_rad.shape == (len(val),)
    err = _angle_errors_rad(report.model, val)
    covered = float(np.mean(err <= iv.angle_rad))
    rms = float(np.sqrt(np.mean(err**2)))
    assert 0.85 <= covered <= 1.0
    assert np.median(iv.angle_rad) <= 3.0 * rms  # sharp, not merely wide
    # a higher probability, a wider angle; read off the same held-out rows as the positions' radius
    wider = prediction_intervals(report.model, val, 0.99).angle_rad
    assert wider is not None and np.all(wider >= iv.angle_rad)
    angles = report.model.spread.orientation
    assert angles is not None and angles.n_heldout == report.model.spread.n_heldout


def test_the_report_shows_the_orientation_intervals_coverage_on_the_validation_rows(probe_cell):
    _, val, report = probe_cell
    shown = [c for c in report.intervals if c.get("quantity") == "orientation"]
    assert len(shown) == 1 and shown[0]["on"] == "validate" and shown[0]["rows"] == len(val)
    iv = prediction_intervals(report.model, val, shown[0]["probability"])
    err = _angle_errors_rad(report.model, val)
    assert shown[0]["covered"] == pytest.approx(float(np.mean(err <= iv.angle_rad)))
    assert shown[0]["rms_deg"] == pytest.approx(float(np.rad2deg(np.sqrt(np.mean(err**2)))))
    assert shown[0]["median_interval_deg"] == pytest.approx(float(np.median(iv.angle_deg)))
    text = intervals_text(report.intervals)
    assert text is not None and f"{100 * shown[0]['covered']:.1f} % of {len(val)} validation rows" in text
    assert "measured orientation" in text and "deg" in text
    # the positions' entries are as before: held-out, then validation
    assert [c["on"] for c in report.intervals if "quantity" not in c] == ["heldout", "validate"]


def test_orientation_interval_grows_off_the_training_poses(probe_cell):
    train, _, report = probe_cell
    at = train.iloc[:20].copy()
    off = at.assign(q1_rad=at["q1_rad"] + 2.0, q4_rad=at["q4_rad"] + 1.0)
    a_at = prediction_intervals(report.model, at).angle_rad
    a_off = prediction_intervals(report.model, off).angle_rad
    assert a_at is not None and a_off is not None
    # here the held-out folds show no growth with distance (the geometry is right everywhere), so what
    # widens it is the parameters' covariance through the orientation's derivative: pose by pose, not
    # monotonic in the distance, but wider on the whole
    assert report.model.spread.orientation.joint_rate_rad2_per_m >= 0.0
    assert np.mean(a_off) > np.mean(a_at) and np.max(a_off) > np.max(a_at)


def test_predict_writes_interval_deg_only_for_rows_with_orientation(probe_cell, tmp_path, capsys):
    _, val, report = probe_cell
    report.model.save(tmp_path / "model.json")
    val.to_csv(tmp_path / "probe.csv", index=False)
    val.drop(columns=list(ORIENTATION_COLUMNS)).to_csv(tmp_path / "points.csv", index=False)
    out = run_hil(
        "predict", "model.json", "probe.csv", "-o", "p.csv", "--interval", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode == 0, out.stderr
    assert "interval_deg" in out.stdout
    pred = pd.read_csv(tmp_path / "p.csv")
    iv = prediction_intervals(CalibratedModel.load(tmp_path / "model.json"), val)
    assert iv.angle_deg is not None
    assert np.allclose(pred["interval_deg"].to_numpy(), iv.angle_deg, rtol=1e-6)
    # the orientation written is the predicted one, the one the interval is about
    R_written = orientations(pred)
    assert R_written is not None
    gap = rotation_log(R_written @ np.swapaxes(report.model.predict_rotation(val), 1, 2))
    assert np.max(np.linalg.norm(gap, axis=1)) < 1e-8
    out = run_hil(
        "predict", "model.json", "points.csv", "-o", "q.csv", "--interval", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode == 0, out.stderr
    pred = pd.read_csv(tmp_path / "q.csv")
    assert "interval_mm" in pred.columns and "interval_deg" not in pred.columns


def test_a_model_from_before_orientation_intervals_is_refused_for_orientation_rows(
    probe_cell, tmp_path, capsys
):
    _, val, report = probe_cell
    report.model.save(tmp_path / "model.json")
    data = json.loads((tmp_path / "model.json").read_text())
    del data["spread"]["orientation"], data["spread"]["orientation_reason"]  # as the file was written then
    (tmp_path / "old.json").write_text(json.dumps(data))
    old = CalibratedModel.load(tmp_path / "old.json")
    with pytest.raises(IntervalError, match="no orientation spread.*hil diagnose"):
        prediction_intervals(old, val)
    positions_only = val.drop(columns=list(ORIENTATION_COLUMNS))
    assert np.allclose(  # its positions' intervals are what they were
        prediction_intervals(old, positions_only).radius_m,
        prediction_intervals(report.model, val).radius_m,
    )
    val.to_csv(tmp_path / "probe.csv", index=False)
    out = run_hil(
        "predict", "old.json", "probe.csv", "-o", "p.csv", "--interval", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode != 0 and "hil diagnose" in out.stderr
    assert not (tmp_path / "p.csv").exists()
