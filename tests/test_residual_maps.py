"""Residual maps on synthetic fields: the IDW grid in the grid's own frame, the SVR's two modes."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from hil.model.grid_frame import estimate_grid_frame
from hil.model.residual_maps import IDWGridMap, SVRMap, map_from_dict
from hil.runner.planners import Box, grid_points, random_points


def smooth_field(p: np.ndarray) -> np.ndarray:
    """A smooth residual of ~0.1 mm over a metre (what a calibration leaves), metres."""
    return 1e-4 * np.column_stack(
        [np.sin(3 * p[:, 0] + 1), np.cos(2 * p[:, 1]), np.sin(2.5 * p[:, 2] + p[:, 0])]
    )


def turned_box(yaw_deg: float, half_m=(0.4, 0.25, 0.25)) -> Box:
    """A box turned about z, as the grid planner turns it to face the tracker."""
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return Box(np.array([0.6, 0.2, 0.4]), R * np.array(half_m))


def measured_grid(box: Box, step_m: float, orientations: int, seed: int = 0) -> np.ndarray:
    """Every vertex once per orientation, each position off by ~0.3 mm (the calibrated model's position of
    a joint set planned with the nominal model differs from the vertex by the model's correction)."""
    g = grid_points(box, step_m)
    rng = np.random.default_rng(seed)
    return np.vstack([g + rng.normal(0, 0.3e-3, g.shape) for _ in range(orientations)])


def test_idw_finds_every_vertex_of_a_turned_grid_and_interpolates_a_smooth_field():
    box = turned_box(35.0)
    p = measured_grid(box, 0.1, orientations=3)
    n_vertices = len(grid_points(box, 0.1))
    assert n_vertices == 324
    m = IDWGridMap().fit(np.zeros((len(p), 6)), p, smooth_field(p), 1e-5)
    assert len(m.state["vertex_index"]) == n_vertices
    test = random_points(Box(box.centre_m, box.axes_m * 0.85), 300, np.random.default_rng(1))
    left = smooth_field(test) - m.predict_raw(np.zeros((len(test), 6)), test)
    rms = float(np.sqrt(np.mean(np.sum(left**2, axis=1))))
    assert rms < 6e-6, rms  # the old axis-aligned grid found 90 of the 324 vertices and left 16 um
    again = map_from_dict(m.to_dict())  # what a model file carries predicts the same
    np.testing.assert_allclose(again.predict_raw(np.zeros((5, 6)), test[:5]), m.predict_raw(None, test[:5]))


def test_grid_frame_recovers_any_rotation_and_a_step_per_axis_with_off_grid_points_mixed_in():
    R = Rotation.from_euler("zyx", [-50.0, 12.0, 7.0], degrees=True).as_matrix()
    steps = np.array([0.1, 0.15, 0.2])
    k = np.stack(np.meshgrid(np.arange(6), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    origin = np.array([0.3, -0.2, 0.5])
    p = origin + (k * steps) @ R.T
    rng = np.random.default_rng(3)
    extra = origin + rng.uniform(0, 0.5, (20, 3))  # validation poses among the grid
    frame = estimate_grid_frame(np.vstack([p, extra]))
    assert np.allclose(np.sort(frame.steps_m), np.sort(steps), atol=1e-6)
    # Every grid axis is one of the recovered axes (in any order and sign), every vertex recognised.
    assert np.allclose(np.sort(np.abs(R.T @ frame.R_base_grid).max(axis=0)), 1.0, atol=1e-6)
    _, on = frame.vertices(p)
    assert on.all()


def test_grid_frame_finds_a_grid_far_from_the_base_origin():
    """A calibrated model's base frame may lie metres from the grid (a poorly identified base, seen on a
    fixed-orientation grid) and the model sees the grid slightly sheared: the grid axes' small departure
    from square must not add up over 70 m to a wrong lattice offset."""
    box = turned_box(20.0)
    g = grid_points(box, 0.2)
    shear = np.eye(3) + np.array([[0, 2e-3, 0], [0, 0, -1.5e-3], [1e-3, 0, 0]])
    p = (g - box.centre_m) @ shear.T + box.centre_m + np.array([-20.0, 64.0, -33.0])
    _, on = estimate_grid_frame(p).vertices(p)
    assert on.all()


def test_per_cube_svr_picks_the_model_of_the_cube_holding_the_target():
    """Two cubes with opposite errors over the same joint angles: only the cube can tell them apart."""
    rng = np.random.default_rng(4)
    q = rng.uniform(-1, 1, (80, 6))
    p = np.vstack([rng.uniform(0.0, 0.1, (40, 3)), rng.uniform(0.0, 0.1, (40, 3)) + [0.3, 0.0, 0.0]])
    error = np.zeros((80, 3))
    error[:40, 0], error[40:, 0] = 1e-3, -1e-3
    m = SVRMap(mode="per_cube", cube_m=0.1).fit(q, p, error, 0.0)
    assert len(m.state["cubes"]) == 2
    q_new = rng.uniform(-1, 1, (10, 6))
    in_a, in_b = np.full((10, 3), 0.05), np.full((10, 3), 0.05) + [0.3, 0.0, 0.0]
    np.testing.assert_allclose(m.predict_raw(q_new, in_a)[:, 0], 1e-3, atol=0.25e-3)
    np.testing.assert_allclose(m.predict_raw(q_new, in_b)[:, 0], -1e-3, atol=0.25e-3)
    beside_b = in_b + [0.15, 0.0, 0.0]  # an untrained cube: the nearest trained one
    np.testing.assert_allclose(
        map_from_dict(m.to_dict()).predict_raw(q_new, beside_b)[:, 0], -1e-3, atol=0.25e-3
    )
    assert "per cube of 100 mm" in m.describe() and "raw error" in m.describe()


def test_cube_svr_learns_the_raw_error_against_the_nominal_model():
    """A robot ~1 mm off its nominal geometry: the paper's model (nominal + per-cube SVR) must predict held-out
    points to a fraction of that; one trained on the residual after calibration would leave the millimetre."""
    from hil.analysis.calibration.cube_svr import fit_cube_svr, registered_nominal
    from hil.data.dataset import make_dataset
    from hil.geometry.kinematics import measured_point
    from hil.geometry.robots import get_robot

    rng = np.random.default_rng(5)
    nominal = get_robot("ur5")
    true = nominal.with_errors(
        {n: rng.normal(0, 2e-3 if n[0] in "ad" else 4e-3) for n in nominal.param_names}
    )
    T = np.eye(4)
    T[:3, 3] = [2.0, 0.3, -0.2]
    tool = np.array([0.0, 0.0, 0.1])
    centre = np.array([0.3, -1.6, 1.6, -1.5, -1.5, 0.0])

    def campaign(n: int):
        q = centre + rng.uniform(-0.4, 0.4, (n, 6))
        return make_dataset(q, measured_point(true, q, T, tool) + rng.normal(0, 10e-6, (n, 3)), smr=1)

    train, test = campaign(150), campaign(60)
    model = fit_cube_svr(nominal, train, cube_m=0.5, tool_guess_m=tool)
    measured = test[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3
    raw = np.linalg.norm(measured - registered_nominal(nominal, train, tool).predict(test), axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a few test points lie just beyond the training points
        left = np.linalg.norm(measured - model.predict(test), axis=1)
    assert raw.mean() > 0.3e-3, raw.mean()
    assert left.mean() < 0.3 * raw.mean(), (left.mean(), raw.mean())
    assert "raw error against the nominal model" in model.info["residual_map"]


def test_the_report_says_which_svr_mode_was_used():
    from hil.report.text import conclusion_text

    text = conclusion_text({"residual": "structured", "ratio": 2.0, "map": "svr", "cautions": []}, [])
    assert "one model over the whole volume, on the residual after the kinematic calibration" in text
