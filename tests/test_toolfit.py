"""Tool-paper flange fit and distance-constraint tool point, on SMR readings from the simulated cell."""

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell, SmrLocation
from hil.analysis.flange_geometry import fit_flange_frame, tool_point_by_distances, tool_point_in_flange
from hil.geometry.kinematics import forward_kinematics

Q_FACING = np.array([0.0, -1.3, 1.6, -1.9, -1.57, 0.0])


def _cell_facing_tracker(**overrides) -> SimulatedCell:
    """A cell whose flange looks roughly at the tracker at Q_FACING (rotate joint 1 towards it)."""
    cell = SimulatedCell(SimCellConfig(seed=5, **overrides))
    p_base_tracker = np.linalg.inv(cell.T_tracker_base)[:3, 3]
    q = Q_FACING.copy()
    best = min(
        np.linspace(-np.pi, np.pi, 73),
        key=lambda a: _facing(cell, np.r_[a, q[1:]], p_base_tracker),
    )
    cell.set_commanded_joints(np.r_[best, q[1:]])
    return cell


def _facing(cell: SimulatedCell, q: np.ndarray, p_base_tracker: np.ndarray) -> float:
    T = forward_kinematics(cell.nominal, q)[0]
    to_tracker = p_base_tracker - T[:3, 3]
    return -T[:3, 2] @ to_tracker / np.linalg.norm(to_tracker)


def _read(cell: SimulatedCell, location: SmrLocation, shots: int) -> np.ndarray:
    cell.place_smr(1, location)
    return np.mean([cell.measure_smr(1) for _ in range(shots)], axis=0)


def test_flange_hole_fit_recovers_the_flange_and_the_tool_point():
    cell = _cell_facing_tracker()
    holes = {k: _read(cell, SmrLocation("hole", index=k), 3) for k in (1, 3, 5, 7)}
    face = _read(cell, SmrLocation("face", point_m=(0.0, -0.02)), 3)
    fit = fit_flange_frame(holes, face)
    T_true = cell.T_tracker_base @ cell.T_base_flange_true()
    assert np.linalg.norm(fit.T_tracker_flange[:3, 3] - T_true[:3, 3]) < 0.1e-3
    angle = np.arccos(np.clip((np.trace(fit.T_tracker_flange[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1))
    assert np.degrees(angle) < 0.3
    tool = tool_point_in_flange(fit.T_tracker_flange, _read(cell, SmrLocation("nest", index=1), 3))
    true_nest = np.array(cell.ground_truth()["tool_nests_flange_m"][0])
    assert np.linalg.norm(tool - true_nest) < 0.25e-3


def test_all_six_holes_fit_better_than_three_and_report_residuals():
    cell = _cell_facing_tracker()
    readings = {k: _read(cell, SmrLocation("hole", index=k), 3) for k in range(1, 8)}
    face = _read(cell, SmrLocation("face", point_m=(0.0, -0.02)), 3)
    fit6 = fit_flange_frame(readings, face)
    assert fit6.circle_residual_rms_m < 50e-6
    assert abs(fit6.circle_radius_m - cell.config.hole_circle_radius_m) < 50e-6


def test_flange_fit_refuses_bad_input():
    p = np.zeros(3)
    with pytest.raises(ValueError, match="at least 3 of holes"):
        fit_flange_frame({1: p, 3: p, 7: p}, p)
    with pytest.raises(ValueError, match="hole 7"):
        fit_flange_frame({1: np.array([1.0, 0, 0]), 3: np.array([0, 1.0, 0]), 5: np.array([0, 0, 1.0])}, p)
    circle = {k: np.array([np.cos(k), np.sin(k), 2.0]) * 0.03 + [0, 0, 2.0] for k in (1, 3, 5)}
    circle[7] = np.array([0.05, 0.0, 2.06])
    with pytest.raises(ValueError, match="resting on the flange face"):
        fit_flange_frame(circle, np.array([0.0, 0.0, 2.5]))


def test_distance_constraint_finds_the_tool_point():
    cell = SimulatedCell(SimCellConfig(seed=6, geometric_errors=False, compliance=False))
    rng = np.random.default_rng(0)
    q = np.array(cell.config.q_home_rad) + rng.uniform(-0.6, 0.6, (25, 6))
    r = cell.run_sequence(q)
    T_base_flange = forward_kinematics(cell.nominal, r["q_encoder"])
    p_tool, rms = tool_point_by_distances(T_base_flange, r["p_tracker_measured"])
    true_nest = np.array(cell.ground_truth()["tool_nests_flange_m"][0])
    assert np.linalg.norm(p_tool - true_nest) < 0.2e-3
    assert rms < 0.1e-3


def test_the_summary_prints_each_judged_figure_with_its_limit():
    from procedures.tool_fit import ToolFitResult, _Limits, summary

    result = ToolFitResult(
        {1: np.array([0.03, -0.02, 0.11])},
        {1: 8e-6},
        6.6e-6,
        0.0315,
        0.717e-3,
        {},
        _Limits(30e-6, 0.2e-3, 0.1e-3, 3e-3),
    )
    assert (
        "worst circle residual 0.0066 mm (limit 0.03 mm); distance-method check 0.717 mm (limit 3 mm)"
        in summary(result)
    )
