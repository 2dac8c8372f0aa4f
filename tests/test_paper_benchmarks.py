"""The paper benchmarks' analysis on small in-process campaigns of the simulated cell: the shape of each
paper's result (which stage beats which), not its figures. benchmarks/paper_grid.py and paper_svr.py run the
same analysis on campaigns measured through the drivers and procedures."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from fakes.campaign import simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.runner.planners import Box, facing_rotations, fixed_poses, grid_points, plan_joints, random_points
from tests.sim_campaigns import facing_joints, sampling_box, tracker_position_base_m

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import paper_grid  # noqa: E402
import paper_svr  # noqa: E402

# Beyond either paper's model family. Without thermal growth: the arm warming between the grid and the test
# points (measured after it) leaves a drift neither the calibration nor the map knows, and the IDW's small
# gain then depends on the seed (the benchmarks run with it).
EFFECTS = dict(compliance=True, cyclic=True)


def _fixed_joints(cell: SimulatedCell, points: np.ndarray, R_base_tool: np.ndarray) -> np.ndarray:
    p_nest = np.asarray(cell.config.tool_nests_flange_m[0])
    plan = plan_joints(
        cell.nominal, fixed_poses(points, R_base_tool), p_nest, np.asarray(cell.config.q_home_rad)
    )
    return plan.q[plan.usable]


def test_grid_paper_shape_calibration_then_idw_each_reduce_the_error_on_a_turned_fixed_orientation_grid():
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=0, **EFFECTS))
    box = sampling_box(cell)  # turned to face the tracker
    R_fixed = facing_rotations(box.centre_m[None], tracker_position_base_m(cell))[0]
    train = simulate_campaign(cell, _fixed_joints(cell, grid_points(box, 0.15), R_fixed))
    inner = Box(box.centre_m, box.axes_m * 0.6)  # the grid's inner cubes: IDW interpolates there
    test = simulate_campaign(
        cell, _fixed_joints(cell, random_points(inner, 40, np.random.default_rng(3)), R_fixed)
    )
    errors, facts = paper_grid.evaluate(
        cell.nominal, np.asarray(cell.config.tool_nests_flange_m[0]), train, test
    )
    unc, kin, idw = (errors[s].mean() for s in paper_grid.PAPER_TABLE)
    assert facts["vertices"] == facts["locations"] == len(train)  # every vertex of the turned grid
    assert kin < 0.5 * unc, (unc, kin)
    assert idw < kin, (kin, idw)


def test_svr_paper_shape_per_cube_svr_on_the_raw_error_reduces_it_in_both_cubes():
    cell = SimulatedCell(SimCellConfig(robot="ur5", seed=1, **EFFECTS))
    rng = np.random.default_rng(4)
    train, test = [], {}
    for name, lo in paper_svr.cubes(sampling_box(cell)).items():
        cube = Box.from_limits(lo, lo + paper_svr.CUBE_M)
        q = facing_joints(cell, random_points(cube, 80, rng), rng)[:40]
        rows = simulate_campaign(cell, q)
        train.append(rows.iloc[:20])
        test[name] = rows.iloc[20:]
    errors = paper_svr.evaluate(
        cell.nominal,
        np.asarray(cell.config.tool_nests_flange_m[0]),
        pd.concat(train, ignore_index=True),
        test,
    )
    for name, e in errors.items():
        # mm: the raw error is what the paper's mode learns; its epsilon of 0.2 mm ignores errors below it,
        # so on a robot ~0.3 mm off the gain is modest (the paper's UR5 was ~2 mm off)
        assert e["raw"].mean() > 0.2, (name, e["raw"].mean())
        assert e["per-cube SVR"].mean() < 0.9 * e["raw"].mean(), (
            name,
            e["per-cube SVR"].mean(),
            e["raw"].mean(),
        )
