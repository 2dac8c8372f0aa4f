"""Geometric calibration on synthetic data made from hil.geometry.kinematics: recovery, identifiability, outliers, JSON."""

import numpy as np
import pandas as pd
import pytest
from calib_data import synthetic

from hil.analysis.calibration.noise_floor import estimate_noise_floor
from hil.analysis.calibration.solve import calibrate
from hil.data.dataset import make_dataset
from hil.geometry.kinematics import measured_point
from hil.model.calibrated_model import CalibratedModel
from hil.model.residual_maps import IDWGridMap


@pytest.fixture(scope="module")
def data():
    return synthetic(n=200, seed=3)


@pytest.mark.parametrize("solver", ["ridge", "lm"])
def test_recovers_base_tool_and_geometry(data, solver):
    truth, df, make = data
    result = calibrate(df, "ur10", solver=solver)
    # Held-out poses, noise-free: the model predicts the truth far below the 15 um noise.
    q, _ = make(100, noise=0.0)
    p_true = measured_point(truth["model"], q, truth["T_tracker_base"], truth["tool"])
    err = np.linalg.norm(result.model.predict(make_dataset(q, p_true)) - p_true, axis=1)
    assert np.sqrt(np.mean(err**2)) < 12e-6
    assert 10e-6 < result.sigma0_m < 20e-6  # the 15 um noise, seen back
    # Identified kinematic parameters lie within 5 standard errors of the truth (merged ones excluded).
    table = {row["name"]: row for row in result.parameter_table()}
    true_params = dict(zip(truth["model"].param_names, truth["model"].params, strict=True))
    z = [abs(table[n]["value"] - true_params[n]) / table[n]["std"] for n in table if n in true_params]
    assert len(z) == 18 and max(z) < 5.0
    assert not result.outliers.any()


def test_identifiability_merges_what_position_data_cannot_separate(data):
    _, df, _ = data
    report = calibrate(df, "ur10").identifiability
    dropped = {d["name"]: d for d in report.dropped}
    # theta1 is a base rotation about z, d1 a base shift along z; the last joint's four parameters
    # only move the tool point, which is identified anyway.
    assert set(dropped) == {"theta1", "d1", "theta6", "d6", "a6", "alpha6"}
    assert dropped["theta1"]["merged_into"][0][0] == "base_rz"
    assert dropped["d6"]["merged_into"][0][0] == "tool1_z"
    assert report.condition_before > 1e12 and report.condition_after < 1e3


@pytest.mark.parametrize("solver", ["ridge", "lm"])
def test_gross_outlier_is_flagged_and_does_not_move_the_parameters(data, solver):
    _, df, make = data
    clean = calibrate(df, "ur10", solver=solver)
    bad = df.copy()
    bad.loc[17, "y_mm"] += 2.0  # a 2 mm blunder (SMR knocked in its nest)
    result = calibrate(bad, "ur10", solver=solver)
    assert result.outliers[17]
    assert result.outliers.sum() <= 2
    q, _ = make(50, noise=0.0)
    probe = make_dataset(q, np.zeros((50, 3)))
    shift = np.linalg.norm(result.model.predict(probe) - clean.model.predict(probe), axis=1)
    assert shift.max() < 3e-6


def test_two_nests_get_their_own_tool_points():
    truth, df, make = synthetic(n=160, seed=5)
    q, _ = make(80, noise=0.0)
    tool2 = np.array([-0.06, 0.04, 0.09])
    p2 = measured_point(truth["model"], q, truth["T_tracker_base"], tool2)
    p2 += np.random.default_rng(9).normal(0, 15e-6, p2.shape)
    both = make_dataset(
        np.vstack([df[[f"q{i}_rad" for i in range(1, 7)]].to_numpy(), q]),
        np.vstack([df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000, p2]),
        smr=np.r_[np.ones(len(df), int), np.full(80, 2)],
    )
    model = calibrate(both, "ur10").model
    # theta6/d6/a6/alpha6 are merged into the tool points, so compare predictions, not raw tool values.
    err = np.linalg.norm(model.predict(both) - both[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000, axis=1)
    assert np.sqrt(np.mean(err**2)) < 25e-6
    assert np.linalg.norm((model.tools[2] - model.tools[1]) - (tool2 - truth["tool"])) < 1e-4


def test_model_file_round_trip_and_corrected_joints(data, tmp_path):
    _, df, make = data
    model = calibrate(df, "ur10").model
    path = tmp_path / "model.json"
    model.save(path)
    back = CalibratedModel.load(path)
    np.testing.assert_allclose(back.predict(df), model.predict(df), atol=1e-12)
    # Corrected joints: the model puts the SMR on the targets.
    q, p = make(10, noise=0.0)
    seed = q + 0.002
    q_corr, err = back.corrected_joints(p, seed)
    assert err.max() < 1e-9
    np.testing.assert_allclose(back.predict(make_dataset(q_corr, p)), p, atol=1e-9)
    q_ik, err_ik = back.corrected_joints(p)  # seeded by the position IK of the calibrated geometry
    assert err_ik.max() < 1e-9


def test_noise_floor_from_repeated_poses():
    truth, df, make = synthetic(n=60, seed=8, noise_m=40e-6)
    repeated = pd.concat([df, df.iloc[:20]] * 1, ignore_index=True)
    rng = np.random.default_rng(2)
    repeated.loc[60:, ["x_mm", "y_mm", "z_mm"]] = df.iloc[:20][
        ["x_mm", "y_mm", "z_mm"]
    ].to_numpy() + rng.normal(0, 0.04, (20, 3))
    floor = estimate_noise_floor(repeated)
    assert "repeated poses" in floor.method
    # Pairs of 40 um-per-axis readings: the floor (3-D RMS of one reading's noise) is ~ sqrt(3) * 40 um.
    assert floor.floor_mm == pytest.approx(np.sqrt(3) * 0.04, rel=0.3)
    assert "tracker noise model" in estimate_noise_floor(df).method


def test_residual_map_warns_outside_the_measured_volume():
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(*[np.arange(4) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3)
    field = lambda p: 1e-4 * np.sin(p * 7.0)  # noqa: E731
    m = IDWGridMap().fit(np.zeros((len(g), 6)), g, field(g), 1e-5)
    inside = rng.uniform(0.02, 0.28, (20, 3))
    pred = m.predict(np.zeros((20, 6)), inside)
    assert np.max(np.abs(pred - field(inside))) < 3e-5
    np.testing.assert_allclose(m.predict(np.zeros((1, 6)), g[5:6]), field(g[5:6]))  # on a vertex
    with pytest.warns(UserWarning, match="outside the measured volume"):
        m.predict(np.zeros((1, 6)), np.array([[0.9, 0.1, 0.1]]))


def test_approach_signs_follow_the_row_order():
    from hil.model.effects import approach_signs

    q = np.array([[0, 0], [1, 0], [1, 0], [0.5, 1e-9], [0.5, 2], [0.7, 2]], float)
    expected = [[0, 0], [1, 0], [1, 0], [-1, 0], [-1, 1], [1, 1]]  # a joint at rest keeps its side
    np.testing.assert_array_equal(approach_signs(q), expected)
