"""Cells that break the program's own assumptions (issue 30): the diagnosis names nothing the cell does not have
and predicts a later, warmer validation about as well as the model a user who knew the cell would fit."""

from dataclasses import replace

import numpy as np
import pytest
from calib_data import true_effect_model

from hil.analysis.calibration.solve import calibrate
from hil.analysis.diagnosis.cautions import TrackerAirStuck
from hil.analysis.diagnosis.physics_terms import (
    STUCK_AIR_MIN_SPAN_K,
    STUCK_AIR_TOLERANCE_K,
    Coefficient,
    stuck_air,
)
from hil.analysis.diagnosis.pipeline import run_diagnosis
from hil.geometry.robots import get_robot
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import REFRACTION_PER_K, physical, stuck_air_scale
from hil.report.json_report import report_dict
from hil.report.text import caution_text

pytestmark = pytest.mark.timeout(180)


def _cell_campaigns(seed: int, pause_s: float, **config):
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, **config))
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=seed))
    cell.advance_time(pause_s)
    return train, simulate_campaign(cell, held_out_joints(cell, 100, seed=seed + 1))


def _rms_mm(model, df) -> float:
    err = model.predict(df) - df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))) * 1000)


def _diagnose(train, val, robot):
    report = run_diagnosis(train, robot, df_validate=val)
    validate = [s for s in report.stages if s["on"] == "validate"][-1]["rms_mm"]
    return report, {e["name"] for e in report.effects_added}, validate


def test_an_arm_that_does_not_grow_in_a_warming_hall_is_not_given_the_materials_growth():
    train, val = _cell_campaigns(1, 3600.0, thermal=True, expansion_per_k=0.0, compliance=False)
    assert np.ptp(train["temperature_c"]) > 2.0  # the hall warms over the campaign
    report, named, validate = _diagnose(train, val, "ur10")
    assert named == set() and report.thermal["standing"] == "rejected"
    assert report.thermal["fitted_per_k"] == 0.0 and "held at the material" not in str(report.verdict)
    # the weather station reads the hall's air as it warms: no scale from it
    assert np.ptp(train["air_temperature_c"]) > 2.0
    assert report.tracker_air is None and "tracker_scale" not in {e.family for e in report.model.effects}
    assert validate <= 1.1 * _rms_mm(calibrate(train, "ur10", "ridge").model, val)


def test_joints_that_do_not_yield_keep_no_gravity_yield_as_a_finding():
    train, val = _cell_campaigns(1, 0.0, compliance=False)
    report, named, validate = _diagnose(train, val, "ur10")
    assert named == set()
    assert all(g["standing"] != "found" for g in report.gravity)
    assert validate <= 1.1 * _rms_mm(calibrate(train, "ur10", "ridge").model, val)


def test_a_robot_file_with_wrong_masses_names_nothing_but_the_yield():
    robot = get_robot("ur10")
    wrong = np.asarray(robot.link_masses_kg) * np.array([0.5, 2.0, 0.5, 2.0, 0.5, 2.0])
    robot = replace(robot, link_masses_kg=tuple(wrong.tolist()))
    train, val = _cell_campaigns(1, 0.0)
    report, named, validate = _diagnose(train, val, robot)
    assert named <= {"gravity_compliance"}
    assert validate <= 1.1 * _rms_mm(true_effect_model(train, robot, ("gravity_compliance",)), val)


def test_a_tracker_whose_air_reading_is_wrong_is_never_the_arms_growth():
    # The station reads 20 degC while the hall warms: the tracker's distances scale, the arm does not grow.
    train, val = _cell_campaigns(
        1, 3600.0, thermal=True, expansion_per_k=0.0, compliance=False, tracker_air_c=20.0
    )
    report, named, validate = _diagnose(train, val, "ur10")
    assert "thermal_expansion" not in named and named <= {"tracker_scale"}
    assert report.thermal["standing"] != "found"
    assert validate <= 1.1 * _rms_mm(true_effect_model(train, "ur10", ("tracker_scale",)), val)
    # The station's fixed 20 degC beside a recorded temperature that rises: the tracker's scale is in the
    # model as physics, carried by its prior (2.7 K do not resolve it), so assumed and not found.
    assert (train["air_temperature_c"] == 20.0).all() and np.ptp(train["temperature_c"]) > 2.0
    air = report.tracker_air
    assert air is not None and air["standing"] == "assumed" and not air["data_led"]
    assert air["prior_per_k"] == pytest.approx(0.5 * REFRACTION_PER_K)
    assert named == set()  # the scale is assumed: not in effects_added
    (assumed,) = [e for e in report.effects_assumed if e["name"] == "tracker_scale"]
    assert assumed["shift_mm"] == air["shift_mm"] > 0
    (scale,) = [e for e in report.model.effects if e.family == "tracker_scale"]  # one, never a second
    assert scale.params[0] == air["fitted_per_k"] < 0 and not scale.held
    # the prior narrows what the data alone say (between the prior's and the data's own values)
    assert air["std_per_k"] < min(air["prior_std_per_k"], air["data_std_per_k"])
    (caution,) = [c for c in report.verdict["cautions"] if isinstance(c, TrackerAirStuck)]
    text = caution_text(caution)
    assert (
        "read 20.00 degC at every point" in text
        and "weather station" in text
        and "not the arm's growth" in text
    )
    assert report_dict(report)["tracker_air"]["text"].startswith("Tracker scale from a stuck air reading")
    # the model file keeps the term as physics, with its prior: a model read back predicts and refits alike
    (read_back,) = [
        e for e in CalibratedModel.from_dict(report.model.to_dict()).effects if e.family == "tracker_scale"
    ]
    assert stuck_air_scale(read_back) and physical(read_back)
    assert [a.tolist() for a in read_back.prior()] == [a.tolist() for a in scale.prior()]
    assert read_back.params.tolist() == scale.params.tolist()
    # a station that read the hall's air would have recorded its rise: without the column, no such term
    unrecorded = run_diagnosis(train.drop(columns="air_temperature_c"), "ur10")
    assert unrecorded.tracker_air is None


def test_a_growth_the_data_alone_do_not_show_is_not_found_on_the_strength_of_its_prior():
    # A fit's posterior 15.1 +- 3.6 ppm/K beside the material's prior 23 +- 6.9 ppm/K: 4 sigma from zero, but
    # the data alone say 12 +- 4.2 ppm/K, 2.9 sigma: the rest of that distance is the prior's.
    c = Coefficient(15.1e-6, 3.6e-6, 23e-6, 6.9e-6, 0.73, 12.2e-6, 4.2e-6)
    z = 3.29  # two-sided alpha 1e-3
    assert c.away_from_zero(z) and not c.data_show_it(z)
    assert Coefficient(23e-6, 3.6e-6, 23e-6, 6.9e-6, 0.73, 23e-6, 4.2e-6).data_show_it(z)
    assert not Coefficient(23e-6, 6.9e-6, 23e-6, 6.9e-6, 0.0, None, None).data_show_it(z)


def test_a_joint_error_that_follows_the_warming_raster_is_not_named_as_the_links_growth():
    # Joint 1's once-per-turn error over a grid visited in raster order while the hall warms (the links do
    # not grow): the growth's data value lies near 3 sigma from zero, and the material's prior had carried
    # it to 'found'; extrapolated to a 2 K warmer validation it doubled the error there.
    train, val = _cell_campaigns(
        2, 3600.0, thermal=True, expansion_per_k=0.0, cyclic=True, cyclic_joints=(1,), compliance=False
    )
    report, named, validate = _diagnose(train, val, "ur10")
    assert "thermal_expansion" not in named and report.thermal["standing"] != "found"
    assert validate <= 1.1 * _rms_mm(true_effect_model(train, "ur10", ("cyclic",)), val)


def test_an_air_reading_counts_as_stuck_only_when_it_stays_put_while_the_recorded_temperature_moves():
    import pandas as pd

    rises = np.linspace(20.0, 20.0 + 2 * STUCK_AIR_MIN_SPAN_K, 30)
    stuck = stuck_air(pd.DataFrame({"temperature_c": rises, "air_temperature_c": 21.5}))
    assert (
        stuck is not None and stuck.air_c == 21.5 and stuck.span_k == pytest.approx(2 * STUCK_AIR_MIN_SPAN_K)
    )
    assert (stuck.start_c, stuck.end_c) == (rises[0], rises[-1])
    # a file's rounding within the tolerance still reads as stuck; a live station's 0.01 K step does not
    rounding = 21.5 + np.resize([0.0, 0.8 * STUCK_AIR_TOLERANCE_K], 30)
    assert stuck_air(pd.DataFrame({"temperature_c": rises, "air_temperature_c": rounding})) is not None
    moving = 21.5 + np.resize([0.0, 0.01], 30)
    assert stuck_air(pd.DataFrame({"temperature_c": rises, "air_temperature_c": moving})) is None
    # the recorded temperature spanning too little, being the air itself, or a row without either: nothing said
    flat = np.linspace(20.0, 20.0 + 0.5 * STUCK_AIR_MIN_SPAN_K, 30)
    assert stuck_air(pd.DataFrame({"temperature_c": flat, "air_temperature_c": 21.5})) is None
    assert stuck_air(pd.DataFrame({"temperature_c": rises, "air_temperature_c": rises})) is None
    assert stuck_air(pd.DataFrame({"temperature_c": rises})) is None
    gap = np.where(np.arange(30) == 4, np.nan, 21.5)
    assert stuck_air(pd.DataFrame({"temperature_c": rises, "air_temperature_c": gap})) is None
