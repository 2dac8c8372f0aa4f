"""The tracker's scale error from a wrong air temperature (about 1 ppm per K, centred on the tracker) as a
rival of the links' growth (centred on the base, along the links): the model applies it, and the diagnosis
tells the two apart on a cell whose tracker keeps a fixed air temperature while the hall warms."""

from dataclasses import replace

import numpy as np
import pytest

from hil.analysis.diagnosis.drift_monitor import drift_text
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
from hil.geometry.robots import get_robot
from hil.model.effects import EFFECT_FAMILIES, make_effect
from hil.report.html import render_html
from hil.report.text import conclusion

pytestmark = pytest.mark.timeout(180)


def test_a_tracker_scale_stretches_the_points_about_the_tracker_and_its_jacobian_says_so():
    from calib_data import synthetic

    from hil.analysis.calibration.solve import Problem
    from hil.model.calibrated_model import initial_model

    _, df, _ = synthetic(n=40, seed=2)
    df["temperature_c"] = np.linspace(20.0, 24.0, len(df))
    plain = initial_model("ur10", df)
    eff = make_effect("tracker_scale")
    assert eff.prepare(plain.context(df)[0], plain.nominal)
    eff.params = np.array([-0.93e-6])
    model = plain.with_effect(eff)
    dT = df["temperature_c"].to_numpy() - 22.0
    np.testing.assert_allclose(model.predict(df), plain.predict(df) * (1 - 0.93e-6 * dT)[:, None], atol=1e-12)
    p, J = Problem.from_frame(model, df).evaluate(model)

    def central(k: int, h: float) -> np.ndarray:
        dx = np.zeros(len(model.param_names))
        dx[k] = h
        return (model.apply_increment(dx).predict(df) - model.apply_increment(-dx).predict(df)) / (2 * h)

    np.testing.assert_allclose(J[:, :3, -1], central(-1, 1e-7), atol=1e-9)
    # every other parameter's motion is stretched with the points (here theta1's: the ppm shows)
    np.testing.assert_allclose(J[:, :3, 0], central(0, 1e-6), rtol=1e-7, atol=1e-10)
    assert eff.coefficient_unit() == "1/K" and "air_error_k_per_K" in eff.summary(
        model.context(df)[0], plain.nominal
    )


def _campaign(tracker_air_c, seed=0, **config):
    """An 80 mm grid while the arm and the hall's air warm ~9 K, with three reference poses (the nearest to
    the base, the farthest, one between) re-measured every 15 grid points, the tracker 4 m away; `config`:
    further SimCellConfig fields."""
    from sim_campaigns import grid_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell
    from hil.geometry.kinematics import forward_kinematics

    cfg = SimCellConfig(
        robot="ur10",
        seed=seed,
        thermal=True,
        compliance=False,
        tracker_air_c=tracker_air_c,
        tracker_distance_m=4.0,
        **config,
    )
    cell = SimulatedCell(cfg)
    q = grid_joints(cell, step_m=0.08, seed=seed)
    reach = np.linalg.norm(forward_kinematics(cell.nominal, q)[:, :3, 3], axis=1)
    refs = q[[np.argmin(reach), np.argmax(reach), np.argsort(reach)[len(q) // 2]]]
    rounds = [np.vstack([refs, q[k : k + 15]]) for k in range(0, len(q), 15)]
    train = simulate_campaign(cell, np.vstack([*rounds, refs]))
    steps = [["reference"] * 3 + ["grid"] * (len(r) - 3) for r in rounds] + [["reference"] * 3]
    train["step_id"] = np.concatenate(steps)  # as a campaign export labels the drift monitor's rows
    return cell, train


# This cell's arm is rigid (no gravity compliance): described without its link masses, so the model carries
# no gravity yield either. With the masses, the always-present yield of joints 2 and 3 (0.09 +- 0.04 and 0.2 +-
# 0.09 urad/(N m) here) takes enough of the tracker's stretch that the scale misses its full-fit test by a
# hair (seed 0: p 5e-5 against 4.5e-5, where the free form's run passed at 4e-5 against 4e-5; seed 1 misses
# too, seed 2 passes).
RIGID_UR10 = replace(get_robot("ur10"), link_masses_kg=None)


def test_a_fixed_air_temperature_in_a_warming_hall_is_told_apart_from_the_arms_growth():
    cell, train = _campaign(tracker_air_c=20.0)
    assert np.ptp(train["temperature_c"]) > 8.0
    report = run_diagnosis(train, RIGID_UR10)
    assert {e["name"] for e in report.effects_added} == {"thermal_expansion", "tracker_scale"}
    scale = next(e for e in report.model.effects if e.family == "tracker_scale")
    assert scale.params[0] == pytest.approx(-0.93e-6, rel=0.25)  # the hall's air warms as the arm does
    assert report.thermal["fitted_per_k"] == pytest.approx(23e-6, rel=0.05)  # the growth is the arm's
    # The stuck air reading puts the scale in as physics, and the data find it (not its prior).
    assert report.tracker_air["standing"] == "found" and report.tracker_air["data_share"] > 0.9
    # Without the rival (an export that does not record the air, no scale among the candidates), the arm's
    # growth takes the tracker's stretch for its own.
    others = tuple(f for f in EFFECT_FAMILIES if f != "tracker_scale")
    unrecorded = train.drop(columns="air_temperature_c")
    alone = run_diagnosis(unrecorded, RIGID_UR10, options=DiagnosisOptions(families=others))
    assert alone.tracker_air is None
    assert abs(alone.thermal["fitted_per_k"] - 23e-6) > 2 * abs(report.thermal["fitted_per_k"] - 23e-6)
    # The drift monitor's reference poses: the far one moves most, with the temperature (growth and scale).
    drift = report.drift
    assert (
        drift is not None
        and len(drift["poses"]) == 3
        and drift["visits"] == 3 * len(drift["poses"][0]["t_s"])
    )
    far = max(drift["poses"], key=lambda s: s["norm_mm"][-1])
    near = min(drift["poses"], key=lambda s: s["norm_mm"][-1])
    dT = np.asarray(far["temperature_c"]) - far["temperature_c"][0]
    assert np.corrcoef(dT, far["norm_mm"])[0, 1] > 0.95 and far["norm_mm"][-1] > 1.5 * near["norm_mm"][-1] > 0
    assert drift["span_k"] > 8.0 and "Drift monitor: 3 reference pose(s)" in drift_text(drift)
    page = render_html(report)
    assert "Drift monitor: reference poses re-measured" in page and "Thermal growth of the links" in page
    assert "Tracker scale from a stuck air reading" in page and "the data show it" in conclusion(report)


def test_a_fixed_air_reading_in_a_hall_whose_air_stays_put_is_tested_and_rejected():
    # The arm warms 9 K, the hall's air stays at the 20 degC the station reads: the reading looks stuck, so the
    # scale enters as physics, and this campaign (revisits over 9 K) finds none: held at zero, not assumed.
    _, train = _campaign(tracker_air_c=20.0, air_warmup_fraction=0.0)
    report = run_diagnosis(train, RIGID_UR10)
    air = report.tracker_air
    assert air is not None and air["standing"] == "rejected" and air["data_led"]
    (scale,) = [e for e in report.model.effects if e.family == "tracker_scale"]
    assert scale.held and scale.params[0] == 0.0 and air["fitted_per_k"] == 0.0
    assert abs(air["data_per_k"]) < 0.3 * abs(air["prior_per_k"])  # what the data had made of it
    names = {e["name"] for e in report.effects_added} | {e["name"] for e in report.effects_assumed}
    assert "tracker_scale" not in names and report.thermal["fitted_per_k"] == pytest.approx(23e-6, rel=0.05)
    assert "the data find no such scale" in conclusion(report)


def test_a_weather_station_that_reads_the_hall_leaves_no_tracker_scale():
    _, train = _campaign(tracker_air_c=None)
    report = run_diagnosis(train, "ur10")
    assert "tracker_scale" not in {e["name"] for e in report.effects_added}
    assert report.thermal["fitted_per_k"] == pytest.approx(23e-6, rel=0.05)


def test_the_scale_held_at_the_cells_refraction_leaves_the_cell_of_a_station_that_reads_the_hall():
    # The yardstick benchmarks/diagnosis_goals.py holds at the cell's true values: the simulator's refraction
    # error (a station fixed at 20 degC while the hall warms) is the model's tracker scale at REFRACTION_PER_K
    # per K of the recorded temperature, so the cell fitted with it held there predicts points 7 K warmer than
    # its training as well as the same cell with a station that reads the hall; without it, clearly worse.
    from calib_data import true_effect_fit
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import REFRACTION_PER_K, SimCellConfig, SimulatedCell
    from hil.analysis.calibration.solve import calibrate

    def validation_rms_mm(tracker_air_c, true_values):
        cfg = SimCellConfig(
            robot="ur10",
            seed=0,
            thermal=True,
            expansion_per_k=0.0,
            compliance=False,
            tracker_air_c=tracker_air_c,
        )
        cell = SimulatedCell(cfg)
        train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=0))
        cell.advance_time(3600.0)
        val = simulate_campaign(cell, held_out_joints(cell, 100, seed=1))
        assert val["temperature_c"].min() > train["temperature_c"].max() + 6.0
        if true_values is None:
            model = calibrate(train, RIGID_UR10, "ridge").model
        else:
            model = true_effect_fit(train, RIGID_UR10, ("tracker_scale",), true_values).model
            assert [e.family for e in model.effects] == ["tracker_scale"] and model.effects[0].held
        err = model.predict(val) - val[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
        return float(np.sqrt(np.mean(np.sum(err**2, axis=1))) * 1000)

    reads_the_hall = validation_rms_mm(None, None)
    known = validation_rms_mm(20.0, {"tracker_scale": REFRACTION_PER_K})
    assert known == pytest.approx(reads_the_hall, rel=0.02)
    assert validation_rms_mm(20.0, None) > 1.1 * reads_the_hall
