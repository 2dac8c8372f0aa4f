"""The shop-floor procedures end to end on `hil sim`, through ur-rtde and emScon: registration, tool fit,
grid sampling; the figures are judged against the simulated cell's hidden truth."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from fakes.control_client import ControlClient
from hil.data.store import CampaignStore
from hil.geometry.kinematics import tool_points
from hil.geometry.se3 import fit_rigid, transform_points
from procedures import grid_sampling, registration, tool_fit
from tests.cli_in_process import run_hil
from tests.sim_session import running_cell, session_on

pytestmark = [pytest.mark.sim, pytest.mark.timeout(400)]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Run the three procedures once on a fresh cell; yield results, truth and the campaign path."""
    folder = tmp_path_factory.mktemp("procedures")
    path = folder / "campaign.sqlite"
    with running_cell(folder, seed=3, time_scale=200.0) as (cell, config):
        truth = cell.control.call("ground_truth")
        with session_on(config, path) as session:
            reg = registration.PROCEDURE(session)
            fit = tool_fit.PROCEDURE(session)
            grid = grid_sampling.PROCEDURE(session, step_m=0.2, validation=8)
            plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=8)
            measured = len(session.store.measurements())
        with session_on(config, path) as session:  # the same job again: a resume with nothing left to do
            again = grid_sampling.PROCEDURE(session, step_m=0.2, validation=8)
            measured_again = len(session.store.measurements())
        # the sessions' own channels to the cell (the simulated operator's hands, the cell's clock), still open
        left_open = [
            c for c in gc.get_objects()
            if isinstance(c, ControlClient) and c is not cell.control and c.port == cell.control.port
            and c._sock is not None
        ]  # fmt: skip
        yield {
            "truth": truth, "config": config, "registration": reg, "tool_fit": fit, "grid": grid, "plan": plan,
            "measured": measured, "again": again, "measured_again": measured_again, "path": path, "folder": folder,
            "left_open": len(left_open),
        }  # fmt: skip


def test_a_closed_session_leaves_no_channel_to_the_cell_open(campaign):
    """A session on a simulated cell opens the cell's control channel for the operator's hands and for the
    cell's clock; its close lets both go (a console serving run after run would otherwise hold one per run)."""
    assert campaign["left_open"] == 0


def test_registration_is_within_the_noise_of_the_best_possible_fit(campaign):
    """The nominal model is ~1 mm off, so registration is judged against the rigid fit that noise-free
    readings of the same poses would give (the simulated cell's truth, same seed): they agree to tens of um."""
    reg = campaign["registration"]
    assert reg.fit.inliers.all() and 0.1e-3 < reg.fit.rms_m < 3e-3
    cell = SimulatedCell(SimCellConfig(seed=3))
    truth = campaign["truth"]
    with CampaignStore(campaign["path"]) as store:
        rows = store.measurements("registration", "poses")
    q = rows[[f"q{i}_rad" for i in range(1, 7)]].to_numpy()
    nest_true = np.asarray(truth["tool_nests_flange_m"][0])
    p_true = []
    for qk in q:
        cell.set_commanded_joints(qk)
        p_true.append(transform_points(cell.T_tracker_base @ cell.T_base_flange_true(), nest_true[None])[0])
    p_nominal = tool_points(campaign["config"].nominal, q, campaign["config"].nests_flange_m[0])
    T_best, _ = fit_rigid(p_nominal, np.array(p_true))
    box_points = grid_sampling.sampling_box(campaign["config"], None, None).corners()
    gap = np.linalg.norm(
        transform_points(reg.fit.T_tracker_base, box_points) - transform_points(T_best, box_points), axis=1
    )
    assert gap.max() < 0.05e-3, gap


def test_tool_fit_finds_every_nest_within_30_um(campaign):
    fit = campaign["tool_fit"]
    true_nests = np.asarray(campaign["truth"]["tool_nests_flange_m"])
    for j, p in fit.nests_flange_m.items():
        error = np.linalg.norm(p - true_nests[j - 1])
        assert error < 0.03e-3, (j, error)
        assert fit.uncertainty_m[j] < 0.03e-3
    assert fit.circle_residual_m < 0.03e-3
    assert fit.distance_check_m < 3e-3


def test_tool_fit_runs_in_the_papers_order_validates_and_redoes_the_registration(campaign):
    """Bare flange first, the tool mounted by the operator without a move, the nests, then the two methods'
    check and the 20-pose validation; the registration is then refitted with the fitted nest."""
    with CampaignStore(campaign["path"]) as store:
        rows = store.measurements("tool_fit")
        events = " | ".join(store.events()["message"])
        registration_fit = store.step_result("registration", "fit")
        fit = store.step_result("tool_fit", "fit")
    assert list(dict.fromkeys(rows["step"])) == ["flange", "nests", "distance_check", "validation"]
    flange = rows[rows["step"].isin(["flange", "nests"])]
    assert (
        len(flange) == 11
        and np.ptp(flange[[f"q{i}_rad" for i in range(1, 7)]].to_numpy(), axis=0).max() < 1e-4
    )
    assert events.index("Take SMR 1 out of its nest and the tool off") < events.index("Mount the tool")
    assert (
        registration_fit["tool"] == "tool_fit"
        and registration_fit["nest_flange_mm"] == fit["nests_flange_mm"]["1"]
    )
    assert fit["validation"]["poses"] == 20 and 0.1 < fit["validation"]["rms_mm"] < 3


def test_the_engine_judged_the_tool_fits_declared_measurements_and_the_campaign_shows_them(campaign, capsys):
    """Each declared measurement is recorded with its outcome; the gate computed at run time is the limit of
    the methods' disagreement; a measurement without a limit is recorded as not judged."""
    with CampaignStore(campaign["path"]) as store:
        outcomes = {o.measurement: o for o in store.outcomes() if o.procedure == "tool_fit"}
        fit = store.step_result("tool_fit", "fit")
    assert set(outcomes) == {m.name for m in tool_fit.PROCEDURE.measurements}
    judged = {name: o.verdict.value for name, o in outcomes.items()}
    assert judged == {**dict.fromkeys(outcomes, "pass"), "validation_rms": "not judged"}
    circle = outcomes["circle_residual"]
    assert circle.value == pytest.approx(
        fit["flange"]["circle_residual_mm"] / 1e3
    ) and circle.limit_value == pytest.approx(30e-6)
    gate = outcomes["method_disagreement"]
    assert gate.limit_value == pytest.approx(fit["distance_check"]["gate_mm"] / 1e3)
    done = run_hil("campaign", "show", str(campaign["path"]), cwd=campaign["path"].parent, capsys=capsys)
    assert done.returncode == 0, done.stderr
    shown = done.stdout
    assert "outcomes: 7 pass, 0 fail, 1 not judged" in shown
    assert "tool_fit" in shown and "circle_residual" in shown


def test_grid_records_every_planned_reachable_point_once(campaign):
    grid, plan = campaign["grid"], campaign["plan"]
    assert grid.recorded == grid.planned == sum(p.step == "grid" for p in plan.poses)
    assert grid.validation_recorded == grid.validation_planned == 8
    assert campaign["again"].recorded == grid.planned
    assert campaign["measured_again"] == campaign["measured"]  # nothing measured twice on the resume


def test_the_campaign_holds_the_snapshot_the_log_and_the_step_results(campaign):
    with CampaignStore(campaign["path"]) as store:
        snapshot = store.snapshots()[0]
        log = " ".join(store.log_lines()["message"])
        assert store.step_result("registration", "fit")["inliers"] == 12
        assert set(store.step_result("tool_fit", "fit")["nests_flange_mm"]) == {"1", "2", "3"}
        kinds = set(store.events()["kind"])
    assert snapshot["cell"]["robot"]["model"] == "ur10" and snapshot["software"]["numpy"]
    assert snapshot["station"]["robot_controller_version"]
    assert "registration:" in log
    assert "operator" in kinds  # every manual step is an event


def test_the_export_is_a_dataset_diagnose_reads(campaign, capsys):
    out = campaign["folder"] / "grid.csv"
    done = run_hil(
        "campaign", "export", str(campaign["path"]), "--csv", str(out), cwd=campaign["folder"], capsys=capsys
    )
    assert done.returncode == 0, done.stderr
    from hil.data.dataset import load_dataset

    df = load_dataset(out)
    assert len(df) == campaign["grid"].recorded + campaign["grid"].validation_recorded


def test_dry_run_prints_the_plan_and_connects_to_nothing(campaign, tmp_path, capsys):
    cell_toml = campaign["folder"] / "cell.toml"
    text = cell_toml.read_text().replace(campaign["config"].robot_host, "127.254.254.254")
    offline = tmp_path / "cell.toml"
    offline.write_text(text)  # nothing listens at that address: a dry run must not try
    done = run_hil(
        "run", "grid_sampling", "--cell", str(offline), "--campaign", str(tmp_path / "c.sqlite"), "--dry-run", "--step-mm", "150",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "plan of grid_sampling" in done.stdout and "estimated duration" in done.stdout
    assert "tool points sweep" in done.stdout
    assert not (tmp_path / "c.sqlite").exists()
