"""hil run on a robot whose controller couples its joints (issue 34): the simulated LR Mate's controller speaks
RTDE in FANUC's joints (J3 against the horizontal) while its hidden arm is the kinematic one; the runner plans
in kinematic joints, sends and records the controller's, and calibration of the campaign reaches the noise."""

from __future__ import annotations

import contextlib
import io
import os

import numpy as np
import pandas as pd
import pytest

from fakes.launch import sim_cell
from hil.cli import main
from hil.commands.campaign_targets import read_campaign_targets
from hil.commands.sim_cell import write_sim_cell
from hil.console.station import CheckedRun
from hil.console.views import plan_view
from hil.data.store import Q_COLUMNS, Q_TARGET_COLUMNS, CampaignStore
from hil.geometry.coupling import CouplingLimit, JointCoupling
from hil.runner.cell_config import load_cell_config
from hil.runner.controller_joints import kinematic_campaign
from hil.runner.envelope import EnvelopeError
from hil.runner.procedure import ParameterError
from procedures import grid_sampling, program_accuracy
from tests.cli_in_process import run_hil

pytestmark = [pytest.mark.sim, pytest.mark.timeout(300)]

ROBOT = "lrmate200id"
# A box the arm reaches extended, towards the tracker, where most grid vertices have a clear configuration (at
# a 100 mm step 118 of 140; the default box, centred just beyond joint 1's 170 deg, keeps 22 of 36: the others
# are reached only with the elbow folded past the upper arm, or not at all; tests/test_clear_plans_any_arm.py).
BOX_MIN_M, BOX_MAX_M = (-0.6, -0.3, 0.0), (-0.3, 0.3, 0.4)
GRID = (
    "--step-mm", "120", "--validation", "20",
    "--box-min-mm", *(f"{1e3 * v:g}" for v in BOX_MIN_M), "--box-max-mm", *(f"{1e3 * v:g}" for v in BOX_MAX_M),
)  # fmt: skip


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A dry run, the registration and a small grid on the simulated coupled cell (geometric errors only), then
    `hil calibrate` of the campaign, and of its grid exported to CSV with the validation predicted."""
    folder = tmp_path_factory.mktemp("coupled")
    out: dict = {"folder": folder}

    def hil(*args: str) -> str:
        printed, here = io.StringIO(), os.getcwd()
        os.chdir(folder)
        try:
            with contextlib.redirect_stdout(printed):
                code = main(list(args))
        finally:
            os.chdir(here)
        assert code == 0, printed.getvalue()
        return printed.getvalue()

    with sim_cell(robot=ROBOT, seed=3, time_scale=200.0, extra_args=("--effects", "none")) as cell:
        write_sim_cell(folder / "cell.toml", cell.info, cell.control.call("ground_truth"), 100.0)
        run = ("--cell", "cell.toml", "--campaign", "job.sqlite")
        out["dry_run"] = hil("run", "grid_sampling", *run, *GRID, "--dry-run")
        hil("run", "registration", *run)
        hil("run", "grid_sampling", *run, *GRID)
    out["calibrate"] = hil("calibrate", "job.sqlite", "--robot", ROBOT, "-o", "model.json")
    for step in ("grid", "validation"):
        hil("campaign", "export", "job.sqlite", "--step", step, "--csv", f"{step}.csv")
    hil("calibrate", "grid.csv", "--robot", ROBOT, "--joint-convention", "controller", "-o", "grid.json")
    for convention in ("controller", "kinematic"):  # the right reading, and the wrong one as a control
        hil("predict", "grid.json", "validation.csv", "--joint-convention", convention,
            "-o", f"predicted-{convention}.csv")  # fmt: skip
    out["config"] = load_cell_config(folder / "cell.toml")
    out["plan"] = grid_sampling.PROCEDURE.make_plan(  # GRID's
        out["config"], step_m=0.12, validation=20, box_min_m=BOX_MIN_M, box_max_m=BOX_MAX_M
    )
    return out


def _held_out_rms_mm(folder, convention: str) -> float:
    measured = pd.read_csv(folder / "validation.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy()
    predicted = pd.read_csv(folder / f"predicted-{convention}.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy()
    return float(np.sqrt(np.mean(np.sum((predicted - measured) ** 2, axis=1))))


def test_the_campaign_holds_the_controllers_joints_of_the_kinematic_plan(job):
    config = job["config"]
    coupling = config.coupling
    assert coupling is not None and coupling.coupled_rows() == [2]
    with CampaignStore(job["folder"] / "job.sqlite") as store:
        rows = store.measurements("grid_sampling")
        pinned = store.step_result("grid_sampling", "plan")
        assert store.snapshots()[-1]["joint_convention"] == "controller"
    planned = dict(zip(pinned["point_ids"], np.asarray(pinned["q_rad"]).reshape(-1, 6), strict=True))
    q_target = rows[list(Q_TARGET_COLUMNS)].to_numpy()
    expected = coupling.to_controller(np.array([planned[p] for p in rows["point_id"]]))
    np.testing.assert_allclose(q_target, expected, atol=1e-8)
    # the controller's J3 is the forearm against the horizontal: not the elbow angle the plan holds
    assert np.abs(coupling.to_kinematic(q_target)[:, 2] - q_target[:, 2]).min() > np.deg2rad(1)
    # what the controller reported after settling: the commanded joints within its encoder noise
    assert np.abs(rows[list(Q_COLUMNS)].to_numpy() - q_target).max() < 1e-4


def test_the_dry_run_shows_the_pendants_joints(job):
    config = job["config"]
    text = job["dry_run"]
    assert "controller joints J1..J6 (deg, the pendant's)" in text
    plan = job["plan"]
    first = next(line for line in text.splitlines() if line.split()[:2] == ["1", plan.poses[0].point_id])
    shown = np.array(first.split()[4:10], float)  # after number, point, step and where the SMR sits
    pendant = np.rad2deg(config.coupling.to_controller(plan.joints()[:1])[0])
    np.testing.assert_allclose(shown, pendant, atol=0.006)
    assert np.abs(shown - np.rad2deg(plan.joints()[0])).max() > 1.0  # not the kinematic joints


def test_calibration_of_the_campaign_reaches_the_noise_floor(job):
    """The tracker's noise at 2.5 m is about 15 um per axis (26 um in 3-D); the nominal LR Mate is ~1 mm off.
    Read as the kinematic joints, the same controller's readings give millimetres."""
    fit_rms_mm = [
        float(line.split("RMS")[1].split()[0]) for line in job["calibrate"].splitlines() if " RMS " in line
    ]
    assert fit_rms_mm and max(fit_rms_mm) < 0.03, job["calibrate"]
    held_out = _held_out_rms_mm(job["folder"], "controller")
    misread = _held_out_rms_mm(job["folder"], "kinematic")
    print(f"held-out RMS {held_out * 1e3:.1f} um (controller joints), misread as kinematic {misread:.3f} mm")
    assert held_out < 0.05
    assert misread > 10 * held_out


def test_a_pose_beyond_the_interaction_limit_is_refused_naming_it_and_the_limit(job):
    """-70 <= J2 + J3 <= 60 deg (figures for the test): the controller's joints of a pose are checked."""
    config = job["config"]
    limit = CouplingLimit(np.array([0, 1, 1, 0, 0, 0.0]), np.deg2rad(-70), np.deg2rad(60))
    coupling = JointCoupling(config.coupling.kinematic_from_controller, (limit,))
    envelope = type(config.envelope)(
        config.envelope.box_min_m, config.envelope.box_max_m, config.envelope.joint_min_rad,
        config.envelope.joint_max_rad, None, coupling,
    )  # fmt: skip
    q_controller = np.deg2rad([[0, 10, 20, 0, -45, 0], [0, 30, 40, 0, -45, 0]])  # J2 + J3: 30, then 70 deg
    q = coupling.to_kinematic(q_controller)
    assert list(envelope.joint_violations(q)) == [False, True]
    with pytest.raises(
        EnvelopeError, match=r"far: 70\.0 deg breaks the interaction limit -70 <= J2 \+ J3 <= 60"
    ):
        envelope.check_poses(config.nominal, q[1:], config.nests_flange_m, ["far"])


def test_the_consoles_plan_shows_the_pendants_joints_too(job, tmp_path):
    config = job["config"]
    plan = job["plan"]
    checked = CheckedRun(grid_sampling.PROCEDURE, {}, tmp_path / "job.sqlite", plan)
    rows = plan_view(checked, config).first_poses
    pendant = np.rad2deg(config.coupling.to_controller(plan.joints()[: len(rows)]))
    np.testing.assert_allclose([r.joints_deg for r in rows], pendant, atol=0.006)


def test_a_campaign_seen_by_the_runner_gives_back_the_kinematic_joints_it_was_given(job, tmp_path):
    """What the session records is stored as the controller's joints and read back exactly (a resume compares
    recorded targets with the plan to 1e-6 rad); the stored file itself holds the controller's."""
    coupling = job["config"].coupling
    with CampaignStore(job["folder"] / "job.sqlite") as store:
        stored = store.records("grid_sampling", "grid")
        seen = kinematic_campaign(store, coupling).records("grid_sampling", "grid")
        frame = kinematic_campaign(store, coupling).measurement_columns(
            ["q3_rad", "x_m"], "grid_sampling", "grid"
        )
    q_stored = np.array([r.q_target_rad for r in stored])
    q_seen = np.array([r.q_target_rad for r in seen])
    np.testing.assert_allclose(q_seen, coupling.to_kinematic(q_stored), atol=1e-12)
    np.testing.assert_allclose(coupling.to_controller(q_seen), q_stored, atol=1e-12)
    assert list(frame.columns) == ["id", "q3_rad", "x_m"]
    np.testing.assert_allclose(frame["q3_rad"], [r.q_rad[2] for r in seen], atol=1e-12)


def test_program_accuracy_is_refused_on_a_coupled_robot_naming_the_coupling(job):
    options = program_accuracy.ProgramAccuracyOptions("job.script", None, "model.json", None)
    with pytest.raises(ParameterError, match=r"couples its joints \(kinematic q3 = -J2 - J3\)"):
        program_accuracy.plan(job["config"], options)


def test_compensation_targets_of_the_campaign_are_where_the_controllers_joints_aimed(job):
    """hil compensate CAMPAIGN --step validation: the commanded points come from the recorded (controller's)
    joints, converted, on the nominal arm and the registration: within the nominal arm's ~1 mm of the
    measured points (read as kinematic joints they would lie hundreds of mm away)."""
    targets = read_campaign_targets(job["folder"] / "job.sqlite", "validation")
    measured = pd.read_csv(job["folder"] / "validation.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy()
    gap_mm = np.linalg.norm(targets.targets * 1e3 - measured, axis=1)
    assert gap_mm.max() < 3.0, gap_mm


def test_a_proposed_plan_is_written_in_the_joints_the_campaign_holds(job, capsys):
    """The campaign holds the controller's joints: the poses `hil diagnose --propose` designs (in kinematic
    joints) are written as the controller's, which the pendant shows and its programs take."""
    plan_csv = job["folder"] / "plan.csv"
    done = run_hil(
        "diagnose", "job.sqlite", "--robot", ROBOT, "--propose", "6", "--plan", str(plan_csv),
        cwd=job["folder"], capsys=capsys,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "in the controller's joints" in done.stdout
    coupling = job["config"].coupling
    written = pd.read_csv(plan_csv)[[f"q{j}_rad" for j in range(1, 7)]].to_numpy()
    assert len(written)
    kinematic = coupling.to_kinematic(written)
    # the elbow the design turned is the kinematic one; the file's J3 is the forearm against the horizontal
    np.testing.assert_allclose(written[:, 2], -(kinematic[:, 1] + kinematic[:, 2]), atol=1e-12)
    assert np.abs(written[:, 2] - kinematic[:, 2]).min() > np.deg2rad(1)
    limits = np.array(job["config"].nominal.joint_limits)
    assert np.all((kinematic >= limits[:, 0] - 1e-9) & (kinematic <= limits[:, 1] + 1e-9))


class _PendantArm:
    """A robot as a coupled controller reports it, in memory: it stands at the joints it was last sent (the
    controller's), so the wrapper's reading and command are what a driver of such a robot would see."""

    def __init__(self, q_controller: np.ndarray):
        self.q = np.asarray(q_controller, float)
        self.sent: list[np.ndarray] = []

    def joints(self) -> np.ndarray:
        return self.q

    def move_joints(self, q: np.ndarray, speed: float | None = None, accel: float | None = None) -> None:
        self.sent.append(np.asarray(q, float))
        self.q = self.sent[-1]


def test_a_script_s_compensated_moves_read_and_send_the_controllers_joints(job):
    """The online wrapper on a coupled robot: the model's kinematic joints never reach the controller."""
    from hil.compensation.online import CompensatedRobot
    from hil.model.calibrated_model import CalibratedModel

    model = CalibratedModel.load(job["folder"] / "model.json")
    coupling = job["config"].coupling
    plan_q = job["plan"].joints()[:3]  # poses the arm reaches, kinematic
    arm = _PendantArm(coupling.to_controller(plan_q[:1])[0])
    robot = CompensatedRobot(arm, model)  # the SMR point as TCP
    T_base_tracker = np.linalg.inv(model.T_tracker_base)
    for q_kinematic in plan_q[1:]:
        T_tracker_smr = model.predict_poses(q_kinematic[None] + 0.02)[0]  # a pose the model says it reaches
        T_base_tcp = T_base_tracker @ T_tracker_smr
        commanded = robot.move_to(T_base_tcp)
        np.testing.assert_array_equal(commanded, arm.sent[-1])
        reached = model.predict_poses(coupling.to_kinematic(commanded[None]))[0]
        assert np.linalg.norm(reached[:3, 3] - T_tracker_smr[:3, 3]) < 2e-5  # the loop's threshold, 10 um
        # read as kinematic joints, the command would put the arm elsewhere
        misread = model.predict_poses(commanded[None])[0]
        assert np.linalg.norm(misread[:3, 3] - T_tracker_smr[:3, 3]) > 1e-2
