"""The joint_axes procedure on `hil sim` through ur-rtde and emScon: short sweeps, judged against the cell's
truth (gravity sag on, as by default: the shoulder's axis within the 0.1 mm goal); the robot file it writes
loads; a second run resumes with nothing left to measure."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from hil.geometry.robots import load_robot_file
from procedures import joint_axes, registration
from tests.cli_in_process import run_hil
from tests.sim_session import running_cell, session_on

pytestmark = [pytest.mark.sim, pytest.mark.timeout(300)]
SEED = 3
Q_REF_DEG = (-76.5, -101.0, 121.3, 21.2, 21.9, -55.0)  # the reference the procedure finds on this cell


def test_sweeps_give_axes_near_the_truth_and_a_loadable_robot_file(tmp_path, capsys):
    options = {
        "points": 5,
        "axis_sigma_rad": 0.0,  # 5 points on every arc: the test's speed, not the plan's precision
        "smrs": 2,
        "q_ref_rad": tuple(np.deg2rad(Q_REF_DEG)),
        "output": str(tmp_path / "arm.toml"),
    }
    with running_cell(tmp_path, seed=SEED, time_scale=200.0) as (_, config):
        with session_on(config, tmp_path / "c.sqlite") as session:
            registration.PROCEDURE(session)
            result = joint_axes.PROCEDURE(session, **options)
            measured = len(session.store.measurements(joint_axes.NAME))
        with session_on(config, tmp_path / "c.sqlite") as session:
            # run again into a new file (an existing robot file is refused): nothing is measured twice
            again = joint_axes.PROCEDURE(session, **{**options, "output": str(tmp_path / "again.toml")})
            assert len(session.store.measurements(joint_axes.NAME)) == measured == 60
    cell = SimulatedCell(SimCellConfig(seed=SEED))
    _, frames = cell.true_joint_offsets(result.axes.q_ref_rad, np.ones(6), 0.0)
    F = cell.T_tracker_base @ frames[0]
    assert cell.config.compliance  # the elbow and wrists sag by amounts that change as the shoulder turns
    for a in result.axes.axes:
        z, o = F[a.joint, :3, 2], F[a.joint, :3, 3]
        d = a.point_m - o
        angle_deg, offset_m = (
            math.degrees(math.acos(min(1.0, float(a.direction @ z)))),
            np.linalg.norm(d - (d @ z) * z),
        )
        assert angle_deg < 0.1 and offset_m < 0.6e-3
        assert a.swept_rad > math.radians(35)
        if a.joint == 1:  # swept from its own pose (the arm stretched): 0.18-0.20 mm off from the reference
            assert angle_deg < 0.02 and offset_m < 0.1e-3
    assert np.all(result.nominal_angle_deg < 0.3) and "vs nominal" in result.table()
    assert load_robot_file(tmp_path / "arm.toml").n_joints == 6
    assert np.allclose([a.direction for a in again.axes.axes], [a.direction for a in result.axes.axes])
    # the recorded sweeps, exported, are a campaign `hil axes` reads (rows in order, no labels needed)
    r = run_hil("campaign", "export", "c.sqlite", "--procedure", "joint_axes", "--csv", "s.csv", cwd=tmp_path,
                capsys=capsys)  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = run_hil("axes", "s.csv", "-o", "b.toml", "--json", "b.json", cwd=tmp_path, capsys=capsys)
    assert r.returncode == 0, r.stderr
    joints = json.loads((tmp_path / "b.json").read_text())["joints"]
    for a, j in zip(result.axes.axes, joints, strict=True):
        assert np.allclose(a.direction, j["direction"], atol=1e-9) and np.allclose(
            a.point_m * 1e3, j["point_mm"]
        )
