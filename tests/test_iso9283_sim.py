"""The ISO 9283 procedure on `hil sim` through ur-rtde and emScon: a few cycles before and after compensation;
the figures agree with the cell's true errors, and `hil iso9283` on the rows it wrote gives the same."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from procedures import iso9283, registration
from tests.cli_in_process import run_hil
from tests.sim_session import running_cell, session_on

sys.path.insert(0, str(Path(__file__).parent))
from calib_data import cell_datasets, true_effect_model  # noqa: E402

pytestmark = [pytest.mark.sim, pytest.mark.timeout(300)]
SEED = 3


def true_points(q: np.ndarray) -> np.ndarray:
    """Where the cell really puts SMR 1 in nest 1 at joints q (approached from below), tracker frame."""
    sim = SimulatedCell(SimCellConfig(seed=SEED))
    truth = sim.ground_truth()
    _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
    T = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
    nest = np.asarray(truth["tool_nests_flange_m"][0])
    return T[:, :3, :3] @ nest + T[:, :3, 3] + np.asarray(truth["smr_centering_m"][0])


def test_before_and_after_compensation_in_the_standards_terms(tmp_path, capsys):
    _, train, _ = cell_datasets(step_m=0.2, n_val=1, seed=SEED)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    model.save(tmp_path / "model.json")
    options = {
        "cycles": 3,
        "side_m": 0.3,
        "model": str(tmp_path / "model.json"),
        "csv": str(tmp_path / "iso.csv"),
    }
    with (
        running_cell(tmp_path, seed=SEED, time_scale=200.0) as (_, config),
        session_on(config, tmp_path / "c.sqlite") as session,
    ):
        registration.PROCEDURE(session)
        result = iso9283.PROCEDURE(session, **options)
        reg = session.registration
    table = result.table()
    assert "before compensation" in table and "after compensation" in table and "RP" in table
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
    # the rows it wrote are a campaign `hil iso9283` reads, with the same figures
    r = run_hil("iso9283", "iso.csv", "--json", "r.json", cwd=tmp_path, capsys=capsys)
    assert r.returncode == 0, r.stderr
    again = json.loads((tmp_path / "r.json").read_text())["poses"]
    assert all(abs(again[p]["AP_mm"] - before[p]["AP_mm"]) < 1e-6 for p in before)
    assert (tmp_path / "iso-after.csv").exists()
