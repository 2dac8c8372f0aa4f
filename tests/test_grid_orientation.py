"""Grid sampling's tool orientation: varied (calibration, the default) or fixed (the grid paper)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hil.geometry.kinematics import forward_kinematics
from hil.runner.cell_config import CellConfigError, parse_cell_config
from procedures import grid_sampling
from tests.cell_fixtures import sim_cell_toml

OPTIONS = dict(
    step_m=0.25, box_min_m=None, box_max_m=None, orientations=1, order="travel", both_directions=False,
    validation=4, nest=1, tilt_rad=np.deg2rad(20.0), seed=0,
)  # fmt: skip


def _config(**grid):
    data = tomllib.loads(sim_cell_toml())
    if grid:
        data["grid"] = grid
    return parse_cell_config(data)


def _tool_rotations(config, plan) -> np.ndarray:
    q = np.array([p.q_rad for p in plan.poses if p.step in ("grid", "validation")])
    return forward_kinematics(config.nominal, q)[:, :3, :3]


def _spread_deg(R: np.ndarray) -> float:
    """Largest angle between any planned tool orientation and the first."""
    cos = (np.einsum("ij,nij->n", R[0], R) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(cos, -1, 1))).max())


def test_fixed_orientation_in_cell_toml_gives_one_orientation_at_every_vertex():
    config = _config(orientation="fixed")
    plan = grid_sampling.PROCEDURE.make_plan(config, **OPTIONS)
    assert sum(p.step == "grid" for p in plan.poses) >= 8
    assert _spread_deg(_tool_rotations(config, plan)) < 1e-3  # degrees: the IK tolerance
    varied = _config()  # the default stays varied: what a calibration wants
    assert varied.grid_orientation == "varied"
    assert _spread_deg(_tool_rotations(varied, grid_sampling.PROCEDURE.make_plan(varied, **OPTIONS))) > 10.0


def test_fixed_orientation_from_the_parameter_and_given_angles():
    config = _config()
    rpy = np.deg2rad([180.0, 0.0, 90.0])  # tool z pointing down
    plan = grid_sampling.PROCEDURE.make_plan(config, **OPTIONS, orientation="fixed", fixed_rpy_rad=rpy)
    R = _tool_rotations(config, plan)
    assert _spread_deg(R) < 1e-3  # degrees: the IK tolerance
    np.testing.assert_allclose(R[0][:, 2], [0.0, 0.0, -1.0], atol=1e-9)


def test_bad_grid_settings_are_refused_with_what_to_do():
    with pytest.raises(CellConfigError, match="grid.orientation"):
        _config(orientation="random")
    with pytest.raises(CellConfigError, match="only used with orientation"):
        _config(fixed_rpy_deg=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="--orientations 1"):
        grid_sampling.PROCEDURE.make_plan(_config(orientation="fixed"), **{**OPTIONS, "orientations": 2})
