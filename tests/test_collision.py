"""The body model and the collision checks: exact distances, and poses and paths refused with their reason."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hil.geometry.body import segment_box_distance, segment_distance
from hil.geometry.kinematics import forward_kinematics
from hil.runner.cell_config import CellConfigError, parse_cell_config
from hil.runner.envelope import EnvelopeError
from tests.cell_fixtures import sim_cell_toml

HOME = np.deg2rad([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


def _cell(**envelope) -> dict:
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["collisions"] = True
    data["envelope"].update(envelope)
    return data


def _brute_segments(p0, p1, q0, q1, n=401):
    s = np.linspace(0, 1, n)
    a = p0 + s[:, None] * (p1 - p0)
    b = q0 + s[:, None] * (q1 - q0)
    return np.min(np.linalg.norm(a[:, None] - b[None], axis=2))


def test_segment_distance_matches_dense_sampling_including_parallel_and_points():
    rng = np.random.default_rng(1)
    ends = rng.normal(size=(200, 4, 3))
    ends[:20, 3] = ends[:20, 2] + 0.7 * (ends[:20, 1] - ends[:20, 0])  # parallel
    ends[20:30, 1] = ends[20:30, 0]  # a point
    exact = segment_distance(ends[:, 0], ends[:, 1], ends[:, 2], ends[:, 3])
    brute = np.array([_brute_segments(*e) for e in ends])
    assert np.all(exact <= brute + 1e-12)  # never more than a distance actually found
    assert np.allclose(
        exact, brute, atol=2e-2 * np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).max() / 400 + 1e-2
    )


def test_segment_box_distance_matches_dense_sampling_and_sees_a_segment_through_the_box():
    rng = np.random.default_rng(2)
    lo, hi = np.array([-0.2, -0.1, 0.0]), np.array([0.3, 0.2, 0.4])
    a, b = rng.uniform(-1, 1, (300, 3)), rng.uniform(-1, 1, (300, 3))
    exact = segment_box_distance(a, b, lo, hi)
    s = np.linspace(0, 1, 2001)
    points = a[:, None] + s[None, :, None] * (b - a)[:, None]
    brute = np.linalg.norm(np.maximum(lo - points, 0) + np.maximum(points - hi, 0), axis=2).min(axis=1)
    assert np.all(exact <= brute + 1e-12)
    assert np.allclose(exact, brute, atol=2e-3)
    through = segment_box_distance(np.array([-1.0, 0.0, 0.2]), np.array([1.0, 0.05, 0.2]), lo, hi)
    assert through == 0.0  # both ends outside, the middle inside


def test_a_folded_elbow_is_refused_naming_the_bodies():
    config = parse_cell_config(_cell())
    folded = HOME.copy()
    folded[2] = np.pi  # the forearm laid back onto the upper arm
    problem = config.envelope.pose_problems(config.nominal, folded[None], config.nests_flange_m)[0]
    assert problem is not None and "collide" in problem and "shoulder" in problem
    assert not config.envelope.outside(config.nominal, HOME[None], config.nests_flange_m)[0]
    with pytest.raises(EnvelopeError, match="shoulder"):
        config.envelope.check_poses(config.nominal, folded[None], config.nests_flange_m)


def test_a_pose_through_the_tracker_is_refused():
    reach = HOME.copy()
    reach[1] = np.deg2rad(-30.0)  # the arm stretched out over the base's x axis
    data = tomllib.loads(sim_cell_toml())
    config0 = parse_cell_config(data)
    p_flange = forward_kinematics(config0.nominal, reach[None])[0, :3, 3]
    data = _cell()
    data["tracker"]["position_base_mm"] = [float(v) for v in p_flange * 1e3]
    data["motion"] = {**data.get("motion", {}), "home_deg": [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]}
    config = parse_cell_config(data)
    problem = config.envelope.pose_problems(config.nominal, reach[None], config.nests_flange_m)[0]
    assert problem is not None and "the tracker" in problem


def test_a_path_between_two_clear_poses_through_a_keep_out_box_is_refused():
    start, end = HOME.copy(), HOME.copy()
    start[0], end[0] = np.deg2rad(-80.0), np.deg2rad(80.0)  # swing the arm over the box at joint 1 = 0
    config0 = parse_cell_config(tomllib.loads(sim_cell_toml()))
    p_mid = forward_kinematics(config0.nominal, HOME[None])[0, :3, 3]
    box = {
        "name": "fixture",
        "min_mm": list((p_mid * 1e3 - 60).round()),
        "max_mm": list((p_mid * 1e3 + 60).round()),
    }
    data = _cell(keep_out=[box])
    data["motion"] = {**data.get("motion", {}), "home_deg": list(np.rad2deg(start))}
    config = parse_cell_config(data)
    env, tools = config.envelope, config.nests_flange_m
    assert not env.outside(config.nominal, np.stack([start, end]), tools).any()  # both ends are clear
    with pytest.raises(EnvelopeError, match="keep-out box 'fixture'"):
        env.check_joint_move(config.nominal, start, end, tools)
    assert env.path_problems(config.nominal, start[None], start[None])[0] is None  # standing still is clear


def test_keep_out_boxes_are_read_and_checked():
    with pytest.raises(CellConfigError, match="envelope.keep_out 1"):
        parse_cell_config(_cell(keep_out=[{"name": "x", "min_mm": [0, 0, 0], "max_mm": [0, 10, 10]}]))


def test_first_motions_run_at_reduced_speed_until_the_cell_says_otherwise():
    data = tomllib.loads(sim_cell_toml())
    assert "joint_speed" not in parse_cell_config(data).robot_mapping()  # the simulated cell: full speed
    del data["motion"]["reduced_speed"]  # a cell file that does not say: a new real cell, reduced
    mapping = parse_cell_config(data).robot_mapping()
    assert mapping["joint_speed"] == pytest.approx(1.05 * 0.25)
    assert mapping["linear_speed"] == pytest.approx(0.25 * 0.25)
