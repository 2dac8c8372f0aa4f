"""The measured pseudo-target loop on `hil sim` through ur-rtde and emScon, judged against the cell's truth.

The calibrated model comes from simulated grid data of the same cell (tests/calib_data.py, same seed);
the campaign holds a registration (and for three SMRs a tool fit) made through the drivers first.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from hil.compensation.model_based import PosePredictor
from hil.compensation.target_update import pose_errors
from hil.geometry.se3 import fit_rigid, transform_points
from procedures import pseudo_target, registration, tool_fit
from tests.sim_session import running_cell, session_on

sys.path.insert(0, str(Path(__file__).parent))
from calib_data import cell_datasets, true_effect_model  # noqa: E402

pytestmark = [pytest.mark.sim, pytest.mark.timeout(300)]
SEED = 3


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """One simulated cell; a campaign with its registration and tool fit; a model calibrated on grid data."""
    folder = tmp_path_factory.mktemp("ptloop")
    _, train, _ = cell_datasets(step_m=0.2, n_val=1, seed=SEED)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    with running_cell(folder, seed=SEED, time_scale=200.0) as (running, config):
        base = folder / "registered.sqlite"
        with session_on(config, base) as session:
            registration.PROCEDURE(session)
            tool_fit.PROCEDURE(session, check_poses=6, validation_poses=4)
        yield {"config": config, "model": model, "base": base, "folder": folder}


def campaign(cell, name: str) -> Path:
    """A fresh campaign that already holds the registration and tool fit."""
    path = cell["folder"] / f"{name}.sqlite"
    shutil.copy(cell["base"], path)
    return path


def true_tool_poses(q: np.ndarray) -> np.ndarray:
    """Where the cell really puts SMR 1 (as the tracker sees its centre) and the flange, tracker frame."""
    sim = SimulatedCell(SimCellConfig(seed=SEED))
    truth = sim.ground_truth()
    _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
    T = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
    nest1 = np.asarray(truth["tool_nests_flange_m"][0])
    T[:, :3, 3] = T[:, :3, :3] @ nest1 + T[:, :3, 3] + np.asarray(truth["smr_centering_m"][0])
    return T


def true_layout_poses(q: np.ndarray, layout: np.ndarray) -> np.ndarray:
    """The tool's pose as the loop defines it (the nest layout of the tool fit fitted to the three nests),
    from the true, noise-free nest centres: judges the loop, not how well the tool fit fixed the flange frame."""
    sim = SimulatedCell(SimCellConfig(seed=SEED))
    truth = sim.ground_truth()
    T_flange = true_tool_poses(q)
    T_flange[:, :3, 3] -= T_flange[:, :3, :3] @ np.asarray(truth["tool_nests_flange_m"][0]) + np.asarray(
        truth["smr_centering_m"][0]
    )
    nests_true = np.asarray(truth["tool_nests_flange_m"])
    centering = np.asarray(truth["smr_centering_m"])[:3]
    out = []
    for T in T_flange:
        p = nests_true @ T[:3, :3].T + T[:3, 3] + centering
        T_fit, _ = fit_rigid(layout, p)
        T_fit[:3, 3] = p[0]
        out.append(T_fit)
    return np.array(out)


def noise_floor_m(p_tracker: np.ndarray, shots: int) -> float:
    """RMS 3-D error of one measured point: the cell's tracker sigma at those distances, averaged over the shots."""
    sigma = SimulatedCell(SimCellConfig(seed=SEED)).tracker_sigma_m(
        np.linalg.norm(p_tracker, axis=1)
    ) / np.sqrt(shots)
    return float(np.sqrt(3.0 * np.mean(sigma**2)))


def test_one_smr_brings_the_mean_error_to_the_noise_floor_in_three_iterations(cell):
    config, model = cell["config"], cell["model"]
    with session_on(config, campaign(cell, "one")) as session:
        result = pseudo_target.PROCEDURE(
            session, model=model, targets=20, smrs=1, max_iter=3, seed=1, measure_uncompensated=True
        )
        targets = np.array(session.step_result("pseudo_target", "targets")["targets_m"])
    visited = result.visited
    assert len(visited) == 20 and all(t.iterations <= 3 for t in visited)
    q_final = np.array([t.q_rad for t in visited])
    q_start = np.array([session_row_q(cell, "one", t.target_id) for t in visited])
    final = np.linalg.norm(true_tool_poses(q_final)[:, :3, 3] - targets, axis=1)
    start = np.linalg.norm(true_tool_poses(q_start)[:, :3, 3] - targets, axis=1)
    floor = noise_floor_m(targets, config.shots_per_point)
    print(
        f"true error: model-based start {start.mean() * 1e3:.4f} mm, loop {final.mean() * 1e3:.4f} mm, floor {floor * 1e3:.4f} mm"
    )
    assert final.mean() < 1.2 * floor
    assert start.mean() > final.mean()  # the measurements did something the model could not
    summary = result.summary()["position_mm"]
    assert summary["uncompensated"]["mean"] > 0.3  # there was an error to compensate
    assert summary["final"]["n"] == 20 and summary["final"]["mean"] <= summary["start"]["mean"]


def session_row_q(cell, name: str, target_id: str) -> np.ndarray:
    from hil.data.store import CampaignStore

    with CampaignStore(cell["folder"] / f"{name}.sqlite") as store:
        rows = store.measurements("pseudo_target", "loop")
    return np.asarray(rows.loc[rows["point_id"] == f"{target_id}/i0", "q_target_rad"].iloc[0])


def test_three_smrs_correct_the_orientation(cell):
    config, model = cell["config"], cell["model"]
    with session_on(config, campaign(cell, "three")) as session:
        result = pseudo_target.PROCEDURE(
            session, model=model, targets=6, smrs=3, max_iter=2, seed=2, shots=10
        )
        targets = np.array(session.step_result("pseudo_target", "targets")["targets_m"])
        nests = {int(r[-1]) for r in session.store.measurements("pseudo_target", "loop")["point_id"]}
        layout = np.array([session.nest_flange_m(k) for k in (1, 2, 3)])
    assert nests == {1, 2, 3} and len(result.visited) == 6
    q = np.array([t.q_rad for t in result.visited])
    dp, dr = pose_errors(true_layout_poses(q, layout), targets)
    print(f"true orientation error mean {np.rad2deg(dr.mean()):.4f} deg, position {dp.mean() * 1e3:.4f} mm")
    assert np.rad2deg(dr.mean()) < 0.01
    assert result.summary()["orientation_deg"]["start"]["mean"] > np.rad2deg(dr.mean())


class KilledError(Exception):
    pass


def test_a_killed_loop_resumes_without_measuring_twice(cell):
    config, model = cell["config"], cell["model"]
    path = campaign(cell, "killed")
    budget = [5]
    with session_on(config, path) as session:
        measure = session.measure_point

        def limited(*args, **kwargs):
            if budget[0] == 0:
                raise KilledError
            budget[0] -= 1
            return measure(*args, **kwargs)

        session.measure_point = limited  # type: ignore[method-assign]
        with pytest.raises(KilledError):
            pseudo_target.PROCEDURE(
                session, model=model, targets=4, smrs=1, max_iter=2, seed=3, threshold_m=1e-6
            )
        first = session.store.measurements("pseudo_target", "loop")
    assert len(first) == 5
    with session_on(config, path) as session:
        result = pseudo_target.PROCEDURE(
            session, model=model, targets=4, smrs=1, max_iter=2, seed=3, threshold_m=1e-6
        )
        rows = session.store.measurements("pseudo_target", "loop")
    assert rows["point_id"].is_unique
    assert rows["point_id"].tolist()[:5] == first["point_id"].tolist()
    assert np.allclose(np.stack(rows["p_tracker_m"][:5]), np.stack(first["p_tracker_m"]))
    assert len(result.visited) == 4
    assert all(t.status in ("ok", "max_iter", "no_improvement") for t in result.visited)
    # every iteration and the kept joints' fresh reading measured exactly once
    assert len(rows) == sum(len(t.errors_m) + (t.fresh is not None) for t in result.visited)
    with session_on(config, path) as session:  # a finished loop re-run measures nothing
        pseudo_target.PROCEDURE(session, model=model, targets=4, smrs=1, max_iter=2, seed=3, threshold_m=1e-6)
        assert len(session.store.measurements("pseudo_target", "loop")) == len(rows)


def test_below_the_noise_floor_each_target_stops_for_no_improvement_and_keeps_its_best(cell):
    """A threshold the tracker cannot resolve: without the no-improvement rule every target would spend all
    eight corrections; with it each stops once two corrections in a row gain nothing beyond the noise, and
    keeps the last joints that gained beyond it."""
    config, model = cell["config"], cell["model"]
    path = campaign(cell, "stall")
    options = dict(model=model, targets=3, smrs=1, max_iter=8, seed=5, threshold_m=5e-7, patience=2)
    with session_on(config, path) as session:
        result = pseudo_target.PROCEDURE(session, **options)
        rows = session.store.measurements("pseudo_target", "loop")
        stored = session.step_result("pseudo_target", "summary")
    assert len(result.visited) == 3
    q_of = dict(zip(rows["point_id"], rows["q_target_rad"], strict=True))
    for t in result.visited:
        print(t.target_id, [f"{e * 1e3:.4f}" for e in t.errors_m], f"noise {t.noise_m[-1] * 1e3:.4f} mm")
        assert t.status == "no_improvement", t.to_dict()
        assert 2 <= t.iterations < 8
        errors, noise = np.array(t.errors_m), np.array(t.noise_m)
        # the joints kept: the start, replaced only by a correction that beat them by more than the noise (a
        # smaller reading within the noise is the luck of the draw, and picking it would bias the figure low)
        kept, kept_before = 0, []
        for i in range(1, len(errors)):
            kept_before.append(errors[kept])
            if errors[i] < errors[kept] - pseudo_target.GAIN_SIGMAS * noise[i]:
                kept = i
        assert np.all(errors[-2:] >= np.array(kept_before[-2:]) - pseudo_target.GAIN_SIGMAS * noise[-2:])
        assert t.best_iteration == kept and t.error_m == errors[kept]
        np.testing.assert_array_equal(t.q_rad, q_of[f"{t.target_id}/i{t.best_iteration}"])
        assert 0.002 < noise[-1] * 1e3 < 0.05  # a per-axis tracker sigma of a few shots, mm
    assert stored["summary"]["statuses"] == {"no_improvement": 3}
    assert [s["status"] for s in stored["targets"]] == ["no_improvement"] * 3
    # The reported figure is the kept joints measured once more (`t001/f`), not the best of the noisy readings:
    # the minimum stays in the record beside it.
    for t in result.visited:
        np.testing.assert_array_equal(q_of[f"{t.target_id}/f"], t.q_rad)
    position = stored["summary"]["position_mm"]
    assert position["final"]["mean"] == pytest.approx(np.mean([t.fresh[0] for t in result.visited]) * 1e3)
    assert position["best_of_iterations"]["mean"] == pytest.approx(
        np.mean([t.error_m for t in result.visited]) * 1e3
    )
    assert len(rows) == sum(len(t.errors_m) + 1 for t in result.visited)
    with session_on(config, path) as session:  # the replay of what is recorded stops at the same place
        again = pseudo_target.PROCEDURE(session, **options)
        assert len(session.store.measurements("pseudo_target", "loop")) == len(rows)
    for t, u in zip(result.targets, again.targets, strict=True):
        assert (u.status, u.errors_m, u.best_iteration, u.noise_m) == (
            t.status,
            t.errors_m,
            t.best_iteration,
            t.noise_m,
        )
        assert (
            u.fresh is not None and t.fresh is not None and u.fresh[0] == t.fresh[0]
        )  # replayed, not measured


def test_unreachable_and_singular_targets_are_reported_and_not_visited(cell):
    """Pose targets (three SMRs): one 4 m from the base, one in a wrist singularity (q5 = 0), one usable."""
    config, model = cell["config"], cell["model"]
    good = pseudo_target.random_targets(config, model, 1, seed=4, full_pose=True)
    far = good.copy()
    far[0, :3, 3] = transform_points(model.T_tracker_base, np.array([[4.0, 0.0, 0.5]]))[0]
    q_singular = np.array(config.q_home_rad, float)
    q_singular[1:3], q_singular[4] = (-1.2, 1.0), 0.0
    singular = PosePredictor(model, smr=1)(q_singular[None])
    targets = np.concatenate([far, singular, good])
    with session_on(config, campaign(cell, "bad")) as session:
        result = pseudo_target.PROCEDURE(session, model=model, targets=targets, smrs=3, max_iter=1)
        rows = session.store.measurements("pseudo_target", "loop")
    status = [t.status for t in result.targets]
    assert status[0] == "unreachable" and status[1] == "singular", status
    assert status[2] in ("ok", "max_iter")
    assert {p.split("/")[0] for p in rows["point_id"]} == {"t003"}
    assert "unreachable" in result.table() and "singular" in result.table()


def test_cli_dry_run_plans_the_first_poses_and_bad_options_exit_2(cell, tmp_path, capsys):
    from tests.cli_in_process import run_hil

    model_path = tmp_path / "model.json"
    cell["model"].save(model_path)
    text = (cell["folder"] / "cell.toml").read_text().replace(cell["config"].robot_host, "127.254.254.254")
    offline = tmp_path / "cell.toml"
    offline.write_text(text)  # nothing listens there: a dry run must not try
    base = [
        "run",
        "pseudo_target",
        "--cell",
        str(offline),
        "--campaign",
        str(tmp_path / "c.sqlite"),
    ]
    done = run_hil(
        *base,
        "--dry-run",
        "--model",
        str(model_path),
        "--targets",
        "5",
        "--smrs",
        "3",
        cwd=tmp_path,
        capsys=capsys,
    )
    assert done.returncode == 0, done.stderr
    assert "plan of pseudo_target: 5 poses" in done.stdout and "t005/i0" in done.stdout
    for bad in (
        ["--model", str(tmp_path / "none.json")],
        ["--model", str(model_path), "--threshold-mm", "0"],
        ["--model", str(model_path), "--patience", "-1"],
    ):
        done = run_hil(*base, "--dry-run", *bad, cwd=tmp_path, capsys=capsys)
        assert done.returncode == 2 and "what to do" in done.stderr, done.stderr
    assert not (tmp_path / "c.sqlite").exists()


def test_the_pt_paper_experiment_starts_nominal_and_gains_at_each_measured_iteration(cell):
    """--pt-paper: no model, three SMRs, ZYZ, two corrections: the first measured correction takes the mean
    position and orientation errors down by an order of magnitude (the paper: 1.1257 -> 0.0262 mm, 0.3155 ->
    0.012 deg); the second one stays there, within the measurement noise (the simulated cell's noise floor is
    reached in one correction)."""
    with session_on(cell["config"], campaign(cell, "paper")) as session:
        result = pseudo_target.PROCEDURE(session, pt_paper=True, targets="3", seed=4, shots=3)
    s = result.summary()
    assert (s["smrs"], s["generator"], s["start"]) == (3, "zyz", "nominal IK")
    errors = np.array([t.errors_m for t in result.visited])
    assert errors.shape == (3, 3)  # every target: the nominal start and two measured corrections
    mean = errors.mean(axis=0)
    noise = np.mean([t.noise_m for t in result.visited])
    assert mean[0] > 0.3e-3 and mean[1] < mean[0] / 10 and mean[2] < mean[1] + 3 * noise
    rotation = np.array([t.rotation_errors_rad for t in result.visited]).mean(axis=0)
    assert rotation[1] < rotation[0] / 5 and rotation[2] < rotation[0] / 5
    assert s["position_mm"]["final"]["mean"] < s["position_mm"]["start"]["mean"] / 10


def test_an_ensemble_measures_each_generators_proposal_and_keeps_the_best(cell):
    with session_on(cell["config"], campaign(cell, "ensemble")) as session:
        result = pseudo_target.PROCEDURE(
            session, generator="ensemble", ensemble="zyz,quaternion", targets="2", smrs=3, max_iter=1,
            patience=0, threshold_m=1e-6, seed=6, shots=3,
        )  # fmt: skip
        ids = set(session.store.measurements("pseudo_target", "loop")["point_id"])
    assert {"t001/i1/zyz/n1", "t001/i1/quaternion/n3", "t002/i0/n2"} <= ids
    assert not any("/i1/yin" in i for i in ids)  # only the chosen subset
    assert all(t.errors_m[1] < t.errors_m[0] for t in result.visited)


def test_cli_dry_run_of_the_pt_paper_plans_from_the_campaigns_registration(cell, tmp_path, capsys):
    from tests.cli_in_process import run_hil

    text = (cell["folder"] / "cell.toml").read_text().replace(cell["config"].robot_host, "127.254.254.254")
    offline = tmp_path / "cell.toml"
    offline.write_text(text)  # nothing listens there: a dry run must not try
    registered = campaign(cell, "dry")
    base = [
        "run",
        "pseudo_target",
        "--cell",
        str(offline),
        "--dry-run",
        "--pt-paper",
        "--targets",
        "circle:5",
    ]
    done = run_hil(*base, "--campaign", str(registered), cwd=tmp_path, capsys=capsys)
    assert done.returncode == 0, done.stderr
    assert "plan of pseudo_target: 5 poses" in done.stdout
    done = run_hil(*base, "--campaign", str(tmp_path / "new.sqlite"), cwd=tmp_path, capsys=capsys)
    assert done.returncode == 2 and "give --campaign with a registration" in done.stderr
    done = run_hil(*base, "--campaign", str(registered), "--model", "m.json", cwd=tmp_path, capsys=capsys)
    assert done.returncode == 2 and "drop --model" in done.stderr
    assert not (tmp_path / "new.sqlite").exists()


def test_the_start_is_compensated_for_the_cells_temperature_with_a_warning_outside_the_models(cell):
    # A model whose material growth was fitted around 5.5 degC (5..6 degC in its run record); the cell is at
    # ~20 degC: the loop reads the temperature from the campaign's latest measurement and says so.
    from dataclasses import replace

    from hil.data.store import CampaignStore
    from hil.model.effects import ThermalExpansion

    growth = ThermalExpansion(
        params=np.array([23e-6]),
        state={"driver": "temperature_c", "reference": 5.5, "material_per_k": 23e-6, "prior_std_per_k": 7e-6},
    )
    model = cell["model"]
    run = {"inputs": {"training": {"temperature_c_range": [5.0, 6.0]}}}
    cold = replace(model, effects=[*model.effects, growth], info={**model.info, "run": run})
    path = campaign(cell, "cold")
    with session_on(cell["config"], path) as session:
        pseudo_target.PROCEDURE(session, model=cold, targets=2, smrs=1, max_iter=0, seed=2)
    with CampaignStore(path) as store:
        events = store.events()
    said = dict(zip(events["kind"], events["message"], strict=True))
    assert "compensated for 20." in said["loop_temperature"]
    assert "outside the 5.0..6.0 degC" in said["temperature_outside_model"]
