"""The plans of the iso9283 and joint_axes procedures on a simulated cell's configuration (no instruments)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.analysis.standards.iso9283 import cube_poses
from hil.geometry.kinematics import tool_points
from hil.runner.cell_config import load_cell_config
from procedures import iso9283, joint_axes
from tests.cell_fixtures import sim_cell_toml


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = tmp_path_factory.mktemp("plans") / "cell.toml"
    path.write_text(sim_cell_toml(seed=4))
    return load_cell_config(path)


def test_sweeps_turn_one_joint_at_a_time_from_one_reference_pose(config):
    plan = joint_axes.PROCEDURE.make_plan(config, points=7, smrs=2)
    q = plan.joints()
    sweep = np.array([p.point_id.split("/")[0] for p in plan.poses])
    counts = [int(np.sum(sweep == f"j{j + 1}")) // 2 for j in range(6)]
    assert all(7 <= c <= 7 * joint_axes.MAX_POINTS_FACTOR for c in counts) and plan.operator_steps == 2
    assert list(sweep) == [
        f"j{j + 1}" for j in range(6) for _ in range(2 * counts[j])
    ]  # one sweep after another
    q_ref = q[0].copy()
    q_ref[0] = np.median(q[sweep == "j1", 0])
    assert joint_axes.free_joints(config.nominal, q_ref) == [
        1
    ]  # joint 2: only the vertical joint 1 before it
    for j in range(6):
        rows = q[sweep == f"j{j + 1}"]
        held = q_ref if j != 1 else rows[0]  # joint 2 sweeps from its own pose, joint 1 as at the reference
        others = np.delete(rows - held, j, axis=1)
        assert np.allclose(others, 0.0) and np.ptp(rows[:, j]) >= math.radians(30) - 1e-9
        assert np.all(np.diff(rows[::2, j]) > 0)  # always turned the same way
    assert q[sweep == "j2"][0, 0] == pytest.approx(q_ref[0], abs=1e-12)  # the median of an even count: 1 ulp
    assert not config.envelope.outside(config.nominal, q, config.nests_flange_m).any()
    approaches = np.array([p.approach_q_rad for p in plan.poses if p.approach_q_rad is not None])
    assert (
        len(approaches) == 6
        and not config.envelope.outside(config.nominal, approaches, config.nests_flange_m).any()
    )
    assert np.all(joint_axes.facing_angles(config, q, config.nests_flange_m[:2]) < math.radians(30))


def test_short_arcs_get_the_points_that_fix_their_axis(config):
    """Every arc is planned with enough points for its axis to come out within the goal sigma (the nominal
    arcs, the tracker's noise), up to MAX_POINTS_FACTOR times `points`; a long arc keeps `points`."""
    p_nest = config.nests_flange_m[:2]
    q_ref = np.deg2rad([-37.0, -97.0, 111.0, 54.0, 13.0, 28.0])
    spans = np.deg2rad([40.0, 120.0, 120.0, 120.0, 120.0, 120.0])
    centres = np.repeat(q_ref[None], 6, axis=0)
    counts = joint_axes.points_per_arc(config, centres, spans, 25, p_nest, 3)
    assert counts[0] > 25 and counts[3] == 25 and max(counts) <= 25 * joint_axes.MAX_POINTS_FACTOR
    assert joint_axes.points_per_arc(config, centres, spans, 25, p_nest, 3, 0.0) == [25] * 6  # 0: as given
    sigma = float(joint_axes.tracker_sigma_m(2.5)) / math.sqrt(3)
    for j, n in enumerate(counts):
        if n == 25 * joint_axes.MAX_POINTS_FACTOR:
            continue
        q = np.repeat(q_ref[None], n, axis=0)
        q[:, j] += np.linspace(-spans[j] / 2, spans[j] / 2, n)
        arcs = [tool_points(config.nominal, q, nest) for nest in p_nest]
        direction, position = joint_axes.expected_line_sigmas(arcs, sigma)
        goal_rad = math.radians(joint_axes.AXIS_SIGMA_DEG)
        assert direction <= goal_rad * 1.15
        assert position <= goal_rad * joint_axes.POSITION_PER_DIRECTION_M_PER_RAD * 1.15


def test_the_shoulder_sweeps_where_the_other_joints_sag_along_its_arc(config):
    """The elbow and wrist yield under a load that changes as the shoulder turns: joint 2's sweep pose puts the
    SMRs where that yield moves them along the arc (the arm stretched along the upper arm), and the generic
    sag model predicts a far smaller axis error there than at the reference."""
    p_nest = config.nests_flange_m[:2]
    q_ref = np.deg2rad([-37.0, -97.0, 111.0, 54.0, 13.0, 28.0])
    spans = joint_axes.arc_spans(config, q_ref, math.radians(120), p_nest)[0]
    centres, arcs = joint_axes.sweep_poses(config, q_ref, spans, math.radians(120), p_nest)
    assert np.allclose(np.delete(centres, 1, axis=0), q_ref) and centres[1, 0] == q_ref[0]
    assert arcs[1] >= min(spans[1], joint_axes.LONG_ARC_RAD) and abs(centres[1, 2]) < math.radians(20)
    both = np.array([centres[1], q_ref])
    sensitivity = joint_axes.yield_sensitivity(config.nominal, both, p_nest, 1)
    bias = joint_axes.sag_bias(config.nominal, both, 1, np.array([arcs[1], arcs[1]]), p_nest)
    assert sensitivity[0] < 0.5 * sensitivity[1] and bias[0] < 0.2 * bias[1]
    sag = joint_axes.gravity_sag(config.nominal, np.array([q_ref, q_ref + [1.0, 0, 0, 0, 0, 0]]))
    assert np.allclose(sag[:, 0], 0.0) and np.allclose(sag[0, 1:], sag[1, 1:])  # joint 1 turns no load


def test_a_reference_pose_without_room_to_turn_is_refused(config):
    with pytest.raises(ValueError, match="--q-ref-deg joint"):
        joint_axes.PROCEDURE.make_plan(config, q_ref_rad=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="--smrs 5"):
        joint_axes.PROCEDURE.make_plan(config, smrs=5, q_ref_rad=(0.0,) * 6)


def test_an_existing_robot_file_is_refused_before_anything_moves(config, tmp_path):
    written = tmp_path / "measured.toml"
    written.write_text("# the axes of last week\n")
    with pytest.raises(ValueError, match="measured.toml exists"):
        joint_axes.PROCEDURE.make_plan(config, points=7, output=str(written))
    assert written.read_text() == "# the axes of last week\n"
    joint_axes.PROCEDURE.make_plan(config, points=7, output=str(tmp_path / "new.toml"))  # a new file is fine


def test_the_cycles_visit_the_five_poses_on_one_branch_from_below(config):
    plan = iso9283.PROCEDURE.make_plan(config, cycles=3, side_m=0.3)
    assert [p.point_id for p in plan.poses[:6]] == [
        "c01/P1",
        "c01/P2",
        "c01/P3",
        "c01/P4",
        "c01/P5",
        "c02/P1",
    ]
    assert {p.step for p in plan.poses} == {"before"} and len(plan.poses) == 15
    q = plan.joints()[:5]
    assert np.all(np.abs(q - q[0]) < math.radians(60))  # one arm and wrist configuration
    assert all(np.allclose(p.q_rad - p.approach_q_rad, iso9283.APPROACH_RAD) for p in plan.poses)
    cube = iso9283.choose_cube(config, None, 0.3, 1)
    assert np.allclose(tool_points(config.nominal, q, config.nests_flange_m[0]), cube.p_base_m, atol=1e-6)
    assert np.allclose(cube.p_base_m, cube_poses(cube.centre_m, 0.3))
    with pytest.raises(ValueError, match="--model nowhere.json: no such file"):
        iso9283.PROCEDURE.make_plan(config, cycles=2, model="nowhere.json")


def test_each_sweeps_approach_pose_stays_inside_the_envelope(tmp_path):
    """Each sweep starts from APPROACH_RAD below its first pose: the arc search keeps that pose inside too (on
    this cell joint 2's full 120 deg arc would put tool point 3 13 mm below the box on the approach)."""
    path = tmp_path / "cell.toml"
    path.write_text(sim_cell_toml(seed=1))
    config = load_cell_config(path)
    q_ref = np.deg2rad([-16.6, -180.9, 92.1, 41.6, -11.4, -17.3])
    arcs = joint_axes.arc_spans(config, q_ref, math.radians(120), config.nests_flange_m)[0]
    starts = np.repeat(q_ref[None], 6, axis=0)
    starts[np.arange(6), np.arange(6)] -= arcs / 2 + joint_axes.APPROACH_RAD
    assert not config.envelope.outside(config.nominal, starts, config.nests_flange_m).any()
    assert math.radians(100) < arcs[1] < math.radians(120)  # shortened by a step, not given up
