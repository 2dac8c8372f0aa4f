"""The drift monitor: grid sampling re-measures reference poses at intervals declared in cell.toml, and the
export carries them with their time and temperature."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest

from hil.commands.inputs import read_training_and_validation
from hil.data.store import campaign_dataset
from hil.runner.cell_config import CellConfigError, parse_cell_config
from procedures import grid_sampling, registration
from tests.cell_fixtures import sim_cell_toml
from tests.sim_session import running_cell, session_on

pytestmark = pytest.mark.sim


def _toml(extra: str) -> dict:
    return tomllib.loads(sim_cell_toml() + extra)


def test_drift_monitor_is_read_from_cell_toml_and_checked():
    config = parse_cell_config(_toml("\n[drift_monitor]\nposes = 3\nevery_points = 25\n"))
    assert (config.drift_poses, config.drift_every_points) == (3, 25)
    assert parse_cell_config(_toml("")).drift_poses == 0
    with pytest.raises(CellConfigError, match="give both poses and every_points"):
        parse_cell_config(_toml("\n[drift_monitor]\nposes = 3\n"))
    with pytest.raises(CellConfigError, match="every_points: must be a whole number"):
        parse_cell_config(_toml("\n[drift_monitor]\nposes = 3\nevery_points = 0\n"))


def test_reference_rounds_before_between_and_after_the_grid():
    config = dataclasses.replace(parse_cell_config(_toml("")), drift_poses=2, drift_every_points=5)
    plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=3)
    steps = [p.step for p in plan.poses]
    grid = [p for p in plan.poses if p.step == "grid"]
    n_rounds = -(-len(grid) // 5) + 1
    assert steps.count("reference") == 2 * n_rounds and steps[:2] == ["reference"] * 2
    assert steps[-3:] == ["validation"] * 3 and steps[-5:-3] == ["reference"] * 2
    assert steps[2:7] == ["grid"] * 5 and steps[7:9] == ["reference"] * 2
    refs = [p for p in plan.poses if p.step == "reference"]
    assert len({p.point_id for p in refs}) == len(refs)
    np.testing.assert_array_equal(refs[0].q_rad, refs[-2].q_rad)  # the same pose, measured again
    off = grid_sampling.PROCEDURE.make_plan(parse_cell_config(_toml("")), step_m=0.2, validation=3)
    assert "reference" not in [p.step for p in off.poses]


@pytest.mark.sim
@pytest.mark.timeout(400)
def test_reference_poses_are_measured_and_exported_with_time_and_temperature(tmp_path):
    effects = ("--effects", "thermal_expansion")
    with running_cell(tmp_path, time_scale=200.0, seed=5, extra_args=effects) as (_cell, config):
        config = dataclasses.replace(config, drift_poses=2, drift_every_points=6)
        path = tmp_path / "campaign.sqlite"
        with session_on(config, path) as session:
            registration.PROCEDURE(session)
            grid_sampling.PROCEDURE(session, step_m=0.25, validation=2)
    df = campaign_dataset(path, "grid_sampling", step="reference")
    assert len(df) >= 4 and set(df["step_id"]) == {"reference"}
    assert np.all(np.diff(df["t_s"].to_numpy()) > 0)
    assert {"temperature_c", "air_temperature_c", "robot_temperature_c"} <= set(df.columns)
    arm = df["robot_temperature_c"].to_numpy()  # the fake controller's joint sensors read the warming arm
    assert np.all(np.diff(arm) >= 0) and np.ptp(arm) > 0
    training, validation = read_training_and_validation(path)
    assert set(training["step_id"]) == {"grid", "reference"} and validation is not None


def test_the_report_gives_each_reference_poses_drift_from_its_first_visit():
    import pandas as pd

    from hil.analysis.diagnosis.drift_monitor import drift_text, reference_drift

    q = np.tile([[0.1, -1.2, 1.0, -1.4, -1.5, 0.2], [0.6, -1.6, 1.6, -1.4, -1.5, 0.2]], (3, 1))
    grid = np.array([[0.3, -1.4, 1.2, -1.4, -1.5, 0.2]])
    p = np.array(
        [[1000, 0, 0], [0, 1000, 0], [1000.01, 0, 0], [0, 1000, 0.03], [1000.02, 0, 0], [0, 1000, 0.06]]
    )
    rows = np.vstack([q[:2], grid, q[2:4], grid, q[4:]])
    points = np.vstack([p[:2], [[500, 500, 0]], p[2:4], [[500, 500, 0]], p[4:]])
    df = pd.DataFrame(rows, columns=[f"q{j}_rad" for j in range(1, 7)])
    df[["x_mm", "y_mm", "z_mm"]] = points
    df["t_s"] = np.arange(len(df)) * 60.0
    df["temperature_c"] = 20.0 + 0.5 * np.arange(len(df))
    df["step_id"] = ["reference"] * 2 + ["grid"] + ["reference"] * 2 + ["grid"] + ["reference"] * 2
    drift = reference_drift(df)
    assert [len(s["norm_mm"]) for s in drift["poses"]] == [3, 3] and drift["visits"] == 6
    np.testing.assert_allclose(drift["poses"][1]["norm_mm"], [0.0, 0.03, 0.06], atol=1e-9)
    assert drift["max_mm"] == pytest.approx(0.06) and drift["span_k"] == pytest.approx(3.5)
    assert "2 reference pose(s), 6 visits" in drift_text(drift)
    assert reference_drift(df.drop(columns=["step_id"])) is None
