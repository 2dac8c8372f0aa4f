"""Thermal growth as physics: with the links' material in the robot file the thermal term is always in the
model, fitted with the material's coefficient as its prior (hil.model.effects.material_expansion). The
cell's truth is read only to set up the cases."""

from dataclasses import replace

import numpy as np
import pytest
from calib_data import true_effect_model

from hil.analysis.diagnosis.pipeline import run_diagnosis
from hil.geometry.robots import get_robot
from hil.model.effects import physical
from hil.report.json_report import report_dict
from hil.report.text import thermal_text

pytestmark = pytest.mark.timeout(180)


def _rms_mm(model, df):
    err = model.predict(df) - df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))) * 1000)


def _warm_campaigns(seed, warmer_k=4.0, step_m=0.15, **config):
    """A grid (150 mm: 96 poses) while the arm warms, then random poses once it is `warmer_k` warmer than
    any training row."""
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, thermal=True, **config))
    train = simulate_campaign(cell, grid_joints(cell, step_m=step_m, seed=seed))
    hottest = float(train["temperature_c"].max())
    while cell.structure_temperature_c() < hottest + warmer_k:
        cell.advance_time(60.0)
    val = simulate_campaign(cell, held_out_joints(cell, 100, seed=seed + 1))
    return train, val


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_validation_4k_warmer_than_a_short_warm_up_is_predicted_like_a_model_carrying_the_effect(seed):
    # The arm (1e-5 per K, as its robot file says) warms 1.5 K during training: too little for the growth to
    # pass a selection test at alpha; the validation is 4 K warmer than any training row.
    train, val = _warm_campaigns(seed, expansion_per_k=1e-5, warmup_k=20.0, warmup_tau_s=5000.0)
    assert 1.2 < np.ptp(train["temperature_c"]) < 1.8
    assert val["temperature_c"].min() > train["temperature_c"].max() + 4.0
    robot = replace(get_robot("ur10"), expansion_per_k=1e-5)
    report = run_diagnosis(train, robot, df_validate=val)
    assert any(physical(e) for e in report.model.effects)  # in the model whatever the tests say
    thermal = report.thermal
    assert thermal is not None and thermal["material_per_k"] == 1e-5
    assert 0.0 < thermal["data_share"] < 1.0  # the data moved it a little: 1.5 K is little
    assert abs(thermal["fitted_per_k"] - 1e-5) < 3 * thermal["prior_std_per_k"]
    truth = true_effect_model(train, "ur10", ("gravity_compliance", "thermal_expansion"))
    final = [s for s in report.stages if s["on"] == "validate"][-1]["rms_mm"]
    assert final <= 1.1 * _rms_mm(truth, val)
    text = report_dict(report)["thermal"]["text"]
    assert "ppm/K fitted, material 10.0 ppm/K" in text


def test_a_long_warm_up_follows_the_data_against_a_wrong_material():
    # The file says aluminium (23 ppm/K), the arm grows 10 ppm/K and warms ~7 K over a 100 mm grid.
    train, val = _warm_campaigns(3, expansion_per_k=1e-5, warmup_tau_s=1000.0, warmer_k=1.0, step_m=0.1)
    assert np.ptp(train["temperature_c"]) > 5.0
    report = run_diagnosis(train, "ur10", df_validate=val)
    thermal = report.thermal
    assert thermal["material_per_k"] == pytest.approx(23e-6)
    assert thermal["data_led"] and thermal["data_share"] > 0.9
    assert thermal["fitted_per_k"] == pytest.approx(1e-5, rel=0.1)
    assert "thermal_expansion" in {e["name"] for e in report.effects_added}  # measured, so named
    assert "found by this campaign" in thermal_text(thermal)


def test_a_campaign_at_one_temperature_keeps_the_material_and_still_finds_a_drift_in_time():
    # No warm-up: the temperature column is constant, the coefficient stays the material's and the model
    # predicts the growth at another temperature. A base drift in time (the stand settling) is still found by
    # the time-driven thermal_drift candidate.
    from sim_campaigns import grid_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=4, compliance=False))
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=4))
    assert np.ptp(train["temperature_c"]) == 0.0
    drift_m_per_s = np.array([0.36e-6, -0.24e-6, 0.15e-6])  # ~180 um over the campaign's ~400 s
    train[["x_mm", "y_mm", "z_mm"]] += train["t_s"].to_numpy()[:, None] * drift_m_per_s * 1000.0
    report = run_diagnosis(train, "ur10")
    thermal = report.thermal
    assert thermal["fitted_per_k"] == 23e-6 and thermal["data_share"] == 0.0 and not thermal["data_led"]
    assert report.effects_added == [{"name": "thermal_drift", "joint": None}]
    drift = next(e for e in report.model.effects if e.family == "thermal_drift")
    assert drift.state["driver"] == "t_s"
    # tracker frame; on a raster grid time also orders the poses, so the geometry takes a share of it
    cos = drift.params @ drift_m_per_s / np.linalg.norm(drift.params) / np.linalg.norm(drift_m_per_s)
    assert cos > 0.9 and 0.7 < np.linalg.norm(drift.params) / np.linalg.norm(drift_m_per_s) < 1.4
    warm = train.assign(temperature_c=train["temperature_c"] + 5.0)
    shift = np.linalg.norm(report.model.predict(warm) - report.model.predict(train), axis=1)
    points_m = train[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
    reach = np.linalg.norm(points_m - report.model.T_tracker_base[:3, 3], axis=1)  # from the base origin
    assert np.all(shift <= 23e-6 * 5.0 * (reach + 0.2))  # the links grow, the tool does not
    assert np.median(shift) > 23e-6 * 5.0 * 0.3


def test_a_model_carrying_the_material_growth_compensates_targets_without_a_temperature(capsys):
    # Targets without a temperature (a CSV without temperature_c, the loop's targets): compensated at the
    # temperature the growth was fitted around, with a warning that names the option; with one, it applies.
    from calib_data import synthetic

    from hil.commands.compensate import thermal_drivers
    from hil.model.calibrated_model import initial_model
    from hil.model.effects import material_expansion

    _, df, _ = synthetic(n=60, seed=1)
    df["temperature_c"] = np.linspace(20.0, 21.0, len(df))
    model = initial_model("ur10", df)
    model = model.with_effect(material_expansion(model.context(df)[0], model.nominal))
    targets = df.drop(columns=["temperature_c"])
    drivers = thermal_drivers(model, targets, None, None)
    assert np.all(drivers["temperature_c"] == pytest.approx(20.5))
    err = capsys.readouterr().err
    assert "have no temperature" in err and "--temperature-c" in err
    np.testing.assert_allclose(
        model.predict(targets), model.predict(df.assign(temperature_c=20.5)), atol=1e-12
    )
    hot = thermal_drivers(model, targets, 30.0, None)["temperature_c"]
    assert np.all(hot == 30.0) and "outside" not in capsys.readouterr().err  # no run record: no range known


def test_a_temperature_term_no_material_gives_is_rejected_as_growth_with_both_values():
    # The links shrink 20 ppm per K of the recorded temperature (no metal does: the temperature follows
    # something else): no growth of the links, never the material's 23 ppm/K, and the report says so with both.
    from calib_data import synthetic

    from hil.data.dataset import joints_rad
    from hil.model.effects import growth_direction
    from hil.report.text import conclusion

    truth, df, _ = synthetic(n=200, seed=3)
    dT = np.random.default_rng(3).uniform(-2.5, 2.5, len(df))
    df["temperature_c"] = 21.0 + dT
    G = growth_direction(truth["model"], joints_rad(df)) @ truth["T_tracker_base"][:3, :3].T
    df[["x_mm", "y_mm", "z_mm"]] += -20e-6 * dT[:, None] * G * 1000.0
    report = run_diagnosis(df, "ur10")
    thermal = report.thermal
    assert thermal["data_per_k"] == pytest.approx(-20e-6, abs=3e-6)
    assert (
        thermal["fitted_per_k"] == 0.0 and thermal["standing"] == "rejected" and thermal["prior_contradicted"]
    )
    assert "thermal_expansion" not in {e["name"] for e in report.effects_added}
    assert "held at the material" not in conclusion(report)
    assert f"{thermal['data_per_k'] * 1e6:.1f} ppm/K, against the material's 23.0 ppm/K" in conclusion(report)
    assert "rejected" in thermal_text(thermal)


def test_a_plausible_coefficient_far_from_the_files_material_is_the_datas():
    # A carbon-fibre arm (1.5 ppm/K) described as aluminium (23 ppm/K), warming 7 K: the data's value stands.
    train, _ = _warm_campaigns(5, expansion_per_k=1.5e-6, warmup_tau_s=1000.0, warmer_k=0.0, step_m=0.1)
    report = run_diagnosis(train, "ur10")
    assert report.thermal["fitted_per_k"] == pytest.approx(1.5e-6, abs=1.5e-6) and report.thermal["data_led"]
