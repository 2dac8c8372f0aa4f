"""The ISO 9283 procedure on `hil sim` through ur-rtde and emScon: a few cycles and path runs before and after
compensation; the figures agree with the cell's true errors, `hil iso9283` on the rows it wrote gives the same,
a resumed run repeats nothing, and every refusal comes before the robot moves."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.standards.iso9283 import commanded_tangents, crossings
from hil.data.dataset import orientation_columns
from hil.geometry.se3 import fit_rigid
from hil.runner.engine import CampaignStopped, MeasurePath, PathOptions
from hil.runner.envelope import EnvelopeError
from hil.runner.procedure import ParameterError
from procedures import iso9283, registration
from tests.cli_in_process import run_hil
from tests.iso_truth import true_path as iso_truth_path
from tests.iso_truth import true_smr_points
from tests.sim_session import running_cell, session_on

sys.path.insert(0, str(Path(__file__).parent))
from calib_data import cell_datasets, true_effect_model  # noqa: E402

pytestmark = [pytest.mark.sim, pytest.mark.timeout(300)]
SEED = 3
# Short and slow enough that the cell's clock (8 ms controller ticks x the time scale) moves the SMR by a few
# mm between the tracker's samples: 0.025 m/s x 0.16 s = 4 mm.
TIME_SCALE = 20.0
OPTIONS = {"cycles": 2, "side_m": 0.2, "path_runs": 2, "path_speed_m_s": 0.025, "smrs": 3}


def true_points(q: np.ndarray) -> np.ndarray:
    """Where the cell really puts SMR 1 in nest 1 at joints q (approached from below), tracker frame."""
    return true_smr_points(SimulatedCell(SimCellConfig(seed=SEED)), q)


def true_angles_deg(config, q: np.ndarray) -> np.ndarray:
    """rx, ry, rz (N, 3) of the tool as its drawing's nests define it, fitted to the nests' true centres."""
    sim = SimulatedCell(SimCellConfig(seed=SEED))
    truth = sim.ground_truth()
    nests = np.asarray(truth["tool_nests_flange_m"])
    _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
    T = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
    p = (
        np.einsum("nij,kj->nki", T[:, :3, :3], nests)
        + T[:, None, :3, 3]
        + np.asarray(truth["smr_centering_m"])
    )
    R = np.array([fit_rigid(config.nests_flange_m, pk)[0][:3, :3] for pk in p])
    return np.column_stack(list(orientation_columns(R).values()))


def true_path(config, run: iso9283.PathRun) -> np.ndarray:
    """The true SMR path of a moveL through the run's flange waypoints (tests/iso_truth.py)."""
    return iso_truth_path(SimulatedCell(SimCellConfig(seed=SEED)), config, run)


def true_at_mm(samples: pd.DataFrame, path: str, p_true: np.ndarray) -> float:
    """AT of the true path against the commanded points the measurement used (its first run's)."""
    first = samples[(samples["path"] == path) & (samples["run"] == samples["run"].min())]
    c = first[["x_cmd_mm", "y_cmd_mm", "z_cmd_mm"]].to_numpy() / 1e3
    c = c[np.concatenate([[True], np.linalg.norm(np.diff(c, axis=0), axis=1) > 1e-9])]
    x = crossings(p_true, c, commanded_tangents(c))
    ok = np.isfinite(x[:, 0])
    return float(np.linalg.norm(x[ok] - c[ok], axis=1).max() * 1e3)


class PlainTracker:
    """A tracker that measures stationary points only (no stream): the path test must refuse it."""

    def __init__(self, tracker):
        self._tracker = tracker

    def measure(self, shots=1):
        return self._tracker.measure(shots)

    def point_at(self, p):
        self._tracker.point_at(p)

    def find_target(self, approx_distance_m=None):
        self._tracker.find_target(approx_distance_m)

    def state(self):
        return self._tracker.state()

    def close(self):
        self._tracker.close()


def refusals_before_motion(session) -> None:
    """Each refusal names what to change, and nothing has moved or been recorded."""
    q0 = session.robot.joints()
    with pytest.raises(ParameterError, match="path-speed-m-s"):
        iso9283.PROCEDURE(session, **{**OPTIONS, "path_speed_m_s": 2.0})
    with pytest.raises(ValueError, match="the tool has 3 nest"):
        iso9283.PROCEDURE(session, **{**OPTIONS, "smrs": 4})
    with pytest.raises(ValueError, match="give at most"):  # the 200 mm cube's line cannot hold 0.5 m/s
        iso9283.PROCEDURE(session, **{**OPTIONS, "path_speed_m_s": 0.5})
    streaming = session.tracker
    session.tracker = PlainTracker(streaming)
    try:
        with pytest.raises(CampaignStopped, match="cannot sample a moving SMR"):
            iso9283.PROCEDURE(session, **OPTIONS)
    finally:
        session.tracker = streaming
    config = session.config
    cube = iso9283.choose_cube(config, None, OPTIONS["side_m"], 1)
    circle = iso9283.plan_paths(config, cube, 1, None, 0.05)["before"][1]
    box_max = config.envelope.box_max_m.copy()
    box_max[0] = iso9283.path_shapes(cube)["circle"][:, 0].max() - 0.01  # the circle's far side is out
    tight = dataclasses.replace(config, envelope=dataclasses.replace(config.envelope, box_max_m=box_max))
    with pytest.raises(ValueError, match="circle path leaves the envelope"):
        iso9283.check_path(tight, circle.T_base_flange, 1, circle.q_start, "circle")
    envelope, session.envelope = session.envelope, tight.envelope  # the session checks every path run too
    try:
        with pytest.raises(EnvelopeError, match="leaves the reach or the envelope"):
            options = PathOptions(
                speed_m_s=0.05, accel_m_s2=1.2, interval_s=0.01, p_flange_m=config.nests_flange_m[0]
            )
            session.engine.serve_path(
                MeasurePath("iso9283", "path/test/circle/r01", circle.q_start, circle.T_base_flange, options)
            )
    finally:
        session.envelope = envelope
    np.testing.assert_allclose(session.robot.joints(), q0, atol=1e-9)
    assert session.store.measurements("iso9283").empty


def test_poses_and_paths_before_and_after_compensation_in_the_standards_terms(tmp_path, capsys):
    _, train, _ = cell_datasets(step_m=0.2, n_val=1, seed=SEED)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    model.save(tmp_path / "model.json")
    options = {**OPTIONS, "model": str(tmp_path / "model.json"), "csv": str(tmp_path / "iso.csv")}
    with (
        running_cell(tmp_path, seed=SEED, time_scale=TIME_SCALE) as (_, config),
        session_on(config, tmp_path / "c.sqlite") as session,
    ):
        registration.PROCEDURE(session)
        refusals_before_motion(session)
        result = iso9283.PROCEDURE(session, **options)
        runs_recorded = session.store.steps()["step"].str.startswith("path/").sum()
        again = iso9283.PROCEDURE(session, **{**options, "csv": None})  # resumed: nothing is measured again
        assert session.store.steps()["step"].str.startswith("path/").sum() == runs_recorded == 2 * 2 * 2
        reg = session.registration
    table = result.table()
    assert "before compensation" in table and "after compensation" in table and "AT_P" in table
    before, after = (result.reports[s].to_dict()["poses"] for s in ("before", "after"))
    assert list(before) == ["P1", "P2", "P3", "P4", "P5"]
    # consistent with the truth: the true SMR at the commanded joints against the commanded position
    cube = result.cube
    cmd = cube.p_base_m @ reg.T_tracker_base[:3, :3].T + reg.T_tracker_base[:3, 3]
    ap_true = np.linalg.norm(true_points(cube.q_rad) - cmd, axis=1) * 1e3
    ap = np.array([before[p]["AP_mm"] for p in before])
    assert np.all(np.abs(ap - ap_true) < 0.03), (ap, ap_true)
    assert np.all([before[p]["RP_mm"] < 0.1 for p in before])
    assert np.mean([after[p]["AP_mm"] for p in after]) < 0.5 * np.mean(ap)
    # orientation from the three nests: AP_a/b/c against the tool's true angles less the commanded ones
    R_cmd = reg.T_tracker_base[:3, :3] @ cube.R_base_flange
    cmd_deg = np.array([float(v[0]) for v in orientation_columns(R_cmd[None]).values()])
    ap_abc_true = (true_angles_deg(config, cube.q_rad) - cmd_deg + 180.0) % 360.0 - 180.0
    ap_abc = np.array([[before[p][f"AP_{a}_deg"] for a in "abc"] for p in before])
    assert np.all(np.abs(ap_abc - ap_abc_true) < 0.02), (ap_abc, ap_abc_true)
    assert all(before[p][f"RP_{a}_deg"] < 0.1 for p in before for a in "abc")
    # path accuracy: AT against the true path's (normal-plane) deviation, RT small, compensation helps
    assert result.paths is not None and set(result.paths) == {"before", "after"}
    paths = iso9283.plan_paths(config, cube, 1, model, OPTIONS["path_speed_m_s"])
    for step, csv in (("before", "iso-paths.csv"), ("after", "iso-paths-after.csv")):
        samples = pd.read_csv(tmp_path / csv)
        for run in paths[step]:
            fig = result.paths[step][run.name]
            at_true = true_at_mm(samples, run.name, true_path(config, run))
            assert abs(fig.AT_m * 1e3 - at_true) < 0.04, (step, run.name, fig.AT_m * 1e3, at_true)
            assert fig.RT_m < 1e-4 and fig.runs == 2
            assert again.paths is not None and again.paths[step][run.name].AT_m == fig.AT_m
    for name in iso9283.PATH_NAMES:
        assert result.paths["after"][name].AT_m < 0.5 * result.paths["before"][name].AT_m
    # the rows it wrote are a campaign `hil iso9283` reads, with the same figures, paths included
    r = run_hil(
        "iso9283", "iso.csv", "--paths", "iso-paths.csv", "--json", "r.json", cwd=tmp_path, capsys=capsys
    )
    assert r.returncode == 0, r.stderr
    recomputed = json.loads((tmp_path / "r.json").read_text())
    assert all(abs(recomputed["poses"][p]["AP_mm"] - before[p]["AP_mm"]) < 1e-6 for p in before)
    assert all(abs(recomputed["poses"][p]["AP_a_deg"] - before[p]["AP_a_deg"]) < 1e-6 for p in before)
    for name, fig in result.paths["before"].items():
        assert abs(recomputed["paths"][name]["AT_mm"] - fig.AT_m * 1e3) < 1e-6
        assert abs(recomputed["paths"][name]["RT_mm"] - fig.RT_m * 1e3) < 1e-6
    assert (tmp_path / "iso-after.csv").exists()
