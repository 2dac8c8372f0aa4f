"""`hil run pseudo_target --targets FILE.csv`: orientation columns mean what they mean in every dataset."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from hil.data.dataset import orientation_columns
from procedures.pseudo_target import read_targets_csv


def test_target_orientations_are_read_in_the_dataset_convention(tmp_path):
    R = Rotation.from_euler("xyz", [[10, -20, 30], [0, 45, -90]], degrees=True).as_matrix()
    frame = pd.DataFrame(
        {"x_mm": [500.0, 600.0], "y_mm": [0.0, 100.0], "z_mm": [300.0, 400.0], **orientation_columns(R)}
    )
    frame.to_csv(tmp_path / "targets.csv", index=False)
    T = read_targets_csv(tmp_path / "targets.csv")
    assert np.allclose(T[:, :3, :3], R, atol=1e-12)
    assert np.allclose(T[:, :3, 3], [[0.5, 0.0, 0.3], [0.6, 0.1, 0.4]])


def test_targets_with_part_of_an_orientation_are_refused(tmp_path):
    pd.DataFrame({"x_mm": [1.0], "y_mm": [2.0], "z_mm": [3.0], "rx_deg": [4.0]}).to_csv(
        tmp_path / "t.csv", index=False
    )
    with pytest.raises(ValueError, match="rx_deg, ry_deg, rz_deg"):
        read_targets_csv(tmp_path / "t.csv")


def test_a_circle_of_targets_lies_on_one_circle_facing_the_tracker():
    import tomllib

    from hil.runner.cell_config import parse_cell_config
    from procedures.pseudo_target import CIRCLE_RADIUS_M, circle_targets, nominal_model, resolve_targets
    from tests.cell_fixtures import sim_cell_toml

    config = parse_cell_config(tomllib.loads(sim_cell_toml(0)))
    model = nominal_model(config, np.eye(4), config.nests_flange_m[0])
    T = circle_targets(config, model, 12, full_pose=True)
    centre = T[:, :3, 3].mean(axis=0)
    np.testing.assert_allclose(np.linalg.norm(T[:, :3, 3] - centre, axis=1), CIRCLE_RADIUS_M, atol=1e-12)
    np.testing.assert_allclose(T[:, :3, :3], np.broadcast_to(T[0, :3, :3], (12, 3, 3)))  # one orientation
    assert resolve_targets("circle:7", config, model, 0, 1).shape == (7, 3)
    assert resolve_targets("circle", config, model, 0, 1).shape == (2000, 3)  # the paper's trajectory
    with pytest.raises(ValueError, match="circle:N with N >= 3"):
        resolve_targets("circle:2", config, model, 0, 1)


def test_the_pt_paper_option_and_the_ensemble_subset_are_checked():
    from hil.runner.procedure import ParameterError
    from procedures.pseudo_target import PT_PAPER, ensemble_subset, paper_options

    assert paper_options(True, None, 1, "yin", 3, 2, 1e-5) == PT_PAPER == (3, "zyz", 2, 0, 0.0005e-3)
    assert paper_options(False, "m.json", 1, "yin", 3, 2, 1e-5) == (1, "yin", 3, 2, 1e-5)
    with pytest.raises(ParameterError, match="drop --model"):
        paper_options(True, "m.json", 1, "yin", 3, 2, 1e-5)
    assert ensemble_subset(" zyz, quaternion ") == ["zyz", "quaternion"]
    with pytest.raises(ParameterError, match="--ensemble zyz,nope"):
        ensemble_subset("zyz,nope")
    with pytest.raises(ParameterError, match="at least one"):
        ensemble_subset(",")


def test_the_one_sided_approach_is_asked_of_the_engine_below_every_joint_and_only_for_the_first_nest():
    """The loop's request carries the approach pose (q - approach on every joint), optional: the engine passes
    it before a point it measures, skips it (an event) where the envelope refuses it, and replays a recorded
    point without moving (tests/test_engine.py)."""
    from procedures.pseudo_target import _Loop

    loop = _Loop.__new__(_Loop)  # only the request: no model, no targets
    loop.nests, loop.shots = np.zeros((3, 3)), None
    q = np.array([0.1, -1.2, 1.3, -1.5, -1.6, 0.2])
    for approach, first_nest, expected in ((0.01, True, q - 0.01), (0.01, False, None), (0.0, True, None)):
        loop.approach_rad = approach
        request = next(loop._point("t001/i1/n1", q, 1, approach=first_nest))
        assert request.approach_optional and request.pose.point_id == "t001/i1/n1"
        if expected is None:
            assert request.pose.approach_q_rad is None
        else:
            np.testing.assert_allclose(request.pose.approach_q_rad, expected)
