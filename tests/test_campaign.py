"""Campaigns on the simulated cell: joints planned by hil.runner.planners, visited by fakes.campaign, in the CSV
dataset contract."""

import numpy as np
import pytest
from sim_campaigns import grid_joints, held_out_joints, sampling_box

from fakes.campaign import simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.geometry.kinematics import forward_kinematics

CONTRACT_COLUMNS = [f"q{i}_rad" for i in range(1, 7)] + [
    "x_mm",
    "y_mm",
    "z_mm",
    "t_s",
    "temperature_c",
    "smr",
    "air_temperature_c",
]


@pytest.fixture(scope="module")
def cell() -> SimulatedCell:
    return SimulatedCell(SimCellConfig(seed=11))


def test_grid_vertices_are_reached_with_the_smr_facing_the_tracker(cell):
    q = grid_joints(cell, step_m=0.2)
    assert len(q) >= 30
    assert np.all(cell.nominal.within_limits(q))
    p_nest = np.array(cell.config.tool_nests_flange_m[0])
    T = forward_kinematics(cell.nominal, q)
    p_base = T[:, :3, :3] @ p_nest + T[:, :3, 3]
    box = sampling_box(cell)
    local = (p_base - box.centre_m) @ (box.axes_m / box.half_extents_m**2)
    assert np.all(np.abs(local) <= 1 + 1e-9)  # inside the box
    spacing = np.sort(np.linalg.norm(p_base[:, None] - p_base[None], axis=2), axis=1)[:, 1]
    np.testing.assert_allclose(np.median(spacing), 0.2, atol=1e-6)  # grid step honoured
    for qq in q:
        cell.set_commanded_joints(qq)
        assert cell.smr_facing_angle_rad(1) < np.deg2rad(30)


def test_held_out_poses_are_distinct_from_the_grid(cell):
    q_grid = grid_joints(cell, step_m=0.2)
    q_held = held_out_joints(cell, 40, seed=3)
    assert q_held.shape == (40, 6)
    for qq in q_held:
        cell.set_commanded_joints(qq)
        assert cell.smr_facing_angle_rad(1) < np.deg2rad(30)
    nearest = np.min(np.linalg.norm(q_held[:, None] - q_grid[None], axis=2), axis=1)
    assert np.all(nearest > 1e-6)


def test_campaign_rows_follow_the_dataset_contract(cell):
    q = held_out_joints(cell, 25, seed=4)
    df = simulate_campaign(cell, q, seconds_per_point=5.0)
    assert list(df.columns) == CONTRACT_COLUMNS
    assert len(df) == 25
    np.testing.assert_allclose(np.diff(df["t_s"]), 5.0)
    np.testing.assert_allclose(df[[f"q{i}_rad" for i in range(1, 7)]].to_numpy(), q, atol=1e-5)
    distances_m = np.linalg.norm(df[["x_mm", "y_mm", "z_mm"]].to_numpy(), axis=1) / 1e3
    assert np.all((distances_m > 1.0) & (distances_m < 4.5))  # tracker 2.5 m from the base
    assert set(df["smr"]) == {1}
    # the air the tracker's station read: the hall's, at each point's time (a campaign export's column)
    np.testing.assert_allclose(df["air_temperature_c"], cell.hall_air_c(df["t_s"].to_numpy()), atol=1e-12)


def test_bad_grid_step_is_refused(cell):
    with pytest.raises(ValueError, match="grid step"):
        grid_joints(cell, step_m=2.0)
