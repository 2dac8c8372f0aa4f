"""`hil compensate model.json CAMPAIGN -o JOINTS.csv`: the targets a campaign file holds, compensated.

The campaign is written through CampaignStore as a session writes it (snapshot, registration, tool fit, grid
and validation measurements, the pseudo-target loop's pinned targets), no simulator. The model is the truth
here: its public `predict` at the written joints must land on the targets the test computes on its own.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from calib_data import compliant_ur10, ur10_joints
from scipy.spatial.transform import Rotation

from hil.commands.compensate import read_targets
from hil.data.dataset import make_dataset, orientations
from hil.data.store import CampaignStore, MeasurementRecord
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.robots import ROBOT_DIR, get_robot
from hil.geometry.se3 import make_transform, transform_points
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import make_effect
from hil.runner.cell_config import load_cell_config
from tests.cell_fixtures import sim_cell_toml
from tests.cli_in_process import hil_in_process

pytestmark = pytest.mark.timeout(120)
NESTS_MM = np.array([[30.0, -20.0, 110.0], [-40.0, 25.0, 95.0], [10.0, 45.0, 120.0]])  # the drawing
FIT_MM = NESTS_MM[:2] + [[0.05, -0.03, 0.02], [-0.04, 0.06, 0.01]]  # the tool fit (nests 1, 2)
Q_COLS = [f"q{i}_rad" for i in range(1, 7)]


def true_model(seed: int = 0) -> CalibratedModel:
    """A calibrated UR10 with geometric errors, gravity compliance on joints 2 and 3 and two nests' tool points."""
    tools = {1: FIT_MM[0] / 1e3 + 1e-4, 2: FIT_MM[1] / 1e3 - 1e-4}
    return compliant_ur10(seed, tools, FIT_MM[0] / 1e3, n_poses=100)


def registration(model: CalibratedModel) -> np.ndarray:
    """The campaign's registration: the model's base, off by about a millimetre (as a Kabsch fit is)."""
    return make_transform(
        Rotation.from_rotvec([2e-4, -1e-4, 3e-4]).as_matrix() @ model.T_tracker_base[:3, :3],
        model.T_tracker_base[:3, 3] + [8e-4, -5e-4, 3e-4],
    )


def record(
    step: str,
    point_id: str,
    q: np.ndarray,
    smr: int,
    t_s: float,
    location: str | None = None,
    no_temperature=False,
):
    return MeasurementRecord(
        procedure="grid_sampling" if step in ("grid", "validation") else "registration",
        step=step,
        point_id=point_id,
        q_target_rad=q,
        q_rad=q + 1e-5,
        T_base_flange=np.eye(4),
        p_tracker_m=[2.0, 0.3, 0.1],
        spread_m=[5e-6] * 3,
        std_m=[5e-6] * 3,
        shots=3,
        rejected_shots=(),
        smr=smr,
        location=location or f"nest{smr}",
        temperature_c=float("nan") if no_temperature else 20.0 + 0.01 * t_s,
        pressure_hpa=1013.0,
        humidity_pct=40.0,
        timestamp_s=1.7e9 + t_s,
    )


def write_campaign(
    path,
    model: CalibratedModel,
    loop_targets: np.ndarray | None = None,
    snapshot: dict | None = None,
    unread_temperature: str | None = None,
) -> dict:
    """A campaign as the runner leaves it; returns the commanded joints, nests and ids per step. `snapshot`
    replaces the minimal station snapshot; `unread_temperature` names a point measured without a temperature."""
    rng = np.random.default_rng(5)
    layout: dict = {}
    with CampaignStore(path) as store:
        store.add_snapshot(
            snapshot or {"cell": {"robot": {"model": "ur10"}, "tool": {"nests_flange_mm": NESTS_MM.tolist()}}}
        )
        store.record_measurement(record("poses", "r01", ur10_joints(rng, 1)[0], 1, 0.0))
        store.finish_step(
            "registration", "fit", {"T_tracker_base": registration(model).tolist(), "rms_mm": 0.9}
        )
        store.finish_step(
            "tool_fit", "fit", {"nests_flange_mm": {"1": FIT_MM[0].tolist(), "2": FIT_MM[1].tolist()}}
        )
        t = 10.0
        for step, n, prefix in (("grid", 8, "g1-"), ("validation", 5, "v")):
            q = ur10_joints(rng, n)
            smr = np.where(np.arange(n) % 3 == 2, 2, 1) if step == "grid" else np.ones(n, int)
            ids = [f"{prefix}{k:04d}" for k in range(n)]
            for i in range(n):
                unread = ids[i] == unread_temperature
                store.record_measurement(record(step, ids[i], q[i], int(smr[i]), t, no_temperature=unread))
                t += 4.0
            if step == "grid":  # a face probe of the same step: not in a nest, no target
                store.record_measurement(record(step, "g1-face", q[0], 0, t, location="face"))
            layout[step] = {"q": q, "smr": smr, "ids": ids}
        if loop_targets is not None:
            store.finish_step("pseudo_target", "targets", {"targets_m": loop_targets.tolist(), "smrs": 3})
    return layout


def commanded_points(
    model: CalibratedModel, q: np.ndarray, smr: np.ndarray, robot: KinematicModel | None = None
) -> np.ndarray:
    """Where the commanded joints aim the SMR: nominal robot (UR10), the tool fit's nest, the campaign's registration."""
    T = forward_kinematics(robot or get_robot("ur10"), q)
    p_flange = FIT_MM[smr - 1] / 1e3
    p_base = np.einsum("nij,nj->ni", T[:, :3, :3], p_flange) + T[:, :3, 3]
    return transform_points(registration(model), p_base)


def predicted(model: CalibratedModel, q: np.ndarray, smr: np.ndarray, temperature_c=None) -> np.ndarray:
    """The model's public prediction of the SMR centre, per row's nest (at a temperature per row)."""
    return model.predict(make_dataset(q, np.zeros((len(q), 3)), smr=smr, temperature_c=temperature_c))


@pytest.fixture(scope="module")
def model():
    return true_model()


def test_grid_and_validation_targets_are_the_commanded_points_compensated_per_nest(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    layout = write_campaign(tmp_path / "job.sqlite", model)
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "val.csv", cwd=tmp_path, capsys=capsys
    )
    assert code == 0, err
    assert "5 validation targets" in err  # no loop in the campaign: the validation step is the default
    df = pd.read_csv(tmp_path / "val.csv")
    assert list(df["point_id"]) == layout["validation"]["ids"] and set(df["step_id"]) == {"validation"}

    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "grid_joints.csv", "--step", "grid", "--threshold-mm", "0.001",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    df = pd.read_csv(tmp_path / "grid_joints.csv")
    grid = layout["grid"]
    assert list(df["point_id"]) == grid["ids"]  # the face probe has no nest: no target
    np.testing.assert_array_equal(df["smr"], grid["smr"])
    target = commanded_points(model, grid["q"], grid["smr"])
    np.testing.assert_allclose(df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3, target, atol=1e-9)
    assert (df["status"] == "ok").all() and (df["error_mm"] < 0.001).all()
    assert (df["initial_error_mm"] > 0.05).all()  # there was something to compensate
    reached = predicted(model, df[Q_COLS].to_numpy(), grid["smr"])
    assert np.linalg.norm(reached - target, axis=1).max() < 1e-6  # each nest on its own target
    wrong_nest = predicted(model, df[Q_COLS].to_numpy(), np.ones(len(df), int))
    assert np.linalg.norm(wrong_nest - target, axis=1)[grid["smr"] == 2].min() > 0.05
    assert np.abs(df[Q_COLS].to_numpy() - grid["q"]).max() < 0.01  # the commanded posture, corrected
    np.testing.assert_allclose(
        df["t_s"], 10.0 + 4.0 * np.arange(len(df))
    )  # time of each point, for thermal models


def test_loop_targets_are_poses_by_default_and_unreachable_ones_stay_marked(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    q = ur10_joints(np.random.default_rng(7), 4)
    T = forward_kinematics(model.kinematic, q)
    T[:, :3, 3] = predicted(model, q, np.ones(4, int))
    T[:, :3, :3] = model.T_tracker_base[:3, :3] @ T[:, :3, :3]  # near the model's reach, orientation kept
    T[3, :3, 3] = transform_points(model.T_tracker_base, np.array([[4.0, 0.0, 0.5]]))[0]
    write_campaign(tmp_path / "job.sqlite", model, loop_targets=T)
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "loop.csv", "--threshold-mm", "0.002",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "4 loop targets" in err
    df = pd.read_csv(tmp_path / "loop.csv")
    assert list(df["point_id"]) == ["t001", "t002", "t003", "t004"] and set(df["step_id"]) == {"loop"}
    assert list(df["status"]) == ["ok"] * 3 + ["unreachable"]
    assert df.loc[3, Q_COLS].isna().all()
    # rx/ry/rz_deg as a dataset has them: the targeted frame's orientation, xyz-extrinsic Euler
    np.testing.assert_allclose(orientations(df), T[:, :3, :3], atol=1e-9)
    targets, _ = read_targets(str(tmp_path / "loop.csv"))  # what it writes reads back as the same targets
    np.testing.assert_allclose(targets, T, atol=1e-9)
    assert (df["rotation_error_deg"][:3] < 1e-3).all() and (df["error_mm"][:3] < 0.002).all()
    reached = predicted(model, df[Q_COLS].to_numpy()[:3], np.ones(3, int))
    assert np.linalg.norm(reached - T[:3, :3, 3], axis=1).max() < 2e-6


def test_bad_campaign_input_exits_2_with_what_to_do(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    CampaignStore(tmp_path / "empty.sqlite").close()
    with CampaignStore(tmp_path / "reg.sqlite") as store:
        store.record_measurement(record("poses", "r01", ur10_joints(np.random.default_rng(1), 1)[0], 1, 0.0))
    write_campaign(tmp_path / "job.sqlite", model)
    with CampaignStore(tmp_path / "nest3.sqlite") as store:
        store.add_snapshot(
            {"cell": {"robot": {"model": "ur10"}, "tool": {"nests_flange_mm": NESTS_MM.tolist()}}}
        )
        store.finish_step("registration", "fit", {"T_tracker_base": registration(model).tolist()})
        store.record_measurement(
            record("grid", "g1-0000", ur10_joints(np.random.default_rng(2), 1)[0], 3, 1.0)
        )
    pd.DataFrame({"x_mm": [2000.0], "y_mm": [0.0], "z_mm": [0.0]}).to_csv(tmp_path / "t.csv", index=False)
    cases = [
        (["empty.sqlite"], "holds no targets (it holds: no measurements)"),
        (["reg.sqlite"], "holds no targets (it holds: registration/poses (1))"),
        (["job.sqlite", "--step", "hole3"], "--step 'hole3' is not a target source"),
        (["job.sqlite", "--step", "loop"], "has no loop targets; it has: validation (5), grid (8)"),
        (["nest3.sqlite"], "targets of SMR nest(s) [3], but the model has tool points for nests [1, 2]"),
        (["t.csv", "--step", "grid"], "--step picks the targets of a campaign file"),
    ]
    for args, message in cases:
        code, out, err = hil_in_process(
            "compensate", "model.json", *args, "-o", "j.csv", cwd=tmp_path, capsys=capsys
        )
        assert code == 2, (args, err)
        assert message in err and "what to do: " in err, err
    assert not (tmp_path / "j.csv").exists()
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "job.sqlite", cwd=tmp_path, capsys=capsys
    )
    assert code == 2 and "would be overwritten" in err


def loop_poses(model: CalibratedModel, n: int = 3) -> np.ndarray:
    """Pose targets the model reaches: its predicted SMR centre and flange orientation at some joints."""
    q = ur10_joints(np.random.default_rng(7), n)
    T = forward_kinematics(model.kinematic, q)
    T[:, :3, 3] = predicted(model, q, np.ones(n, int))
    T[:, :3, :3] = model.T_tracker_base[:3, :3] @ T[:, :3, :3]
    return T


def test_loop_orientations_follow_the_orientation_convention_option(model, tmp_path, capsys):
    """Written and read in the convention --orientation-convention names (the dataset's option and parser)."""
    model.save(tmp_path / "model.json")
    T = loop_poses(model)
    write_campaign(tmp_path / "job.sqlite", model, loop_targets=T)
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "loop.csv", "--orientation-convention", "xyz-intrinsic",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    df = pd.read_csv(tmp_path / "loop.csv")
    angles = df[["rx_deg", "ry_deg", "rz_deg"]].to_numpy()
    np.testing.assert_allclose(
        Rotation.from_euler("XYZ", angles, degrees=True).as_matrix(), T[:, :3, :3], atol=1e-9
    )
    assert not np.allclose(orientations(df), T[:, :3, :3], atol=1e-3)  # not the extrinsic angles
    targets, _ = read_targets(str(tmp_path / "loop.csv"), "xyz-intrinsic")
    np.testing.assert_allclose(targets, T, atol=1e-9)


def test_a_robot_file_campaign_rebuilds_its_robot_from_the_copy_it_keeps(model, tmp_path, capsys):
    """robot.model = a robot file beside cell.toml (mixed-case name, d1 1 mm longer than the UR10's): the
    commanded points follow that file from any directory, even once the file is gone."""
    cell_dir = tmp_path / "Cell"
    cell_dir.mkdir()
    text = (ROBOT_DIR / "ur10.toml").read_text().replace('name = "ur10"', 'name = "Our_UR10"')
    (cell_dir / "Our_UR10.toml").write_text(text.replace("d_mm = 127.3", "d_mm = 128.3", 1))
    (cell_dir / "cell.toml").write_text(sim_cell_toml().replace('model = "ur10"', 'model = "Our_UR10.toml"'))
    config = load_cell_config(cell_dir / "cell.toml")
    robot = config.nominal
    assert np.isclose(robot.d[0] - get_robot("ur10").d[0], 0.001)
    snapshot = config.snapshot()
    assert snapshot["robot_definition"]["file_text"] == (cell_dir / "Our_UR10.toml").read_text()
    model.save(tmp_path / "model.json")
    layout = write_campaign(tmp_path / "job.sqlite", model, snapshot=snapshot)
    older = {k: v for k, v in snapshot.items() if k != "robot_definition"}  # before campaigns kept the text
    write_campaign(tmp_path / "old.sqlite", model, snapshot=older)
    (tmp_path / "our_ur10.toml").write_text(
        (ROBOT_DIR / "ur5.toml").read_text()
    )  # a decoy where lower case points
    grid = layout["grid"]
    target = commanded_points(model, grid["q"], grid["smr"], robot)
    assert np.abs(target - commanded_points(model, grid["q"], grid["smr"])).max() > 5e-4  # the file matters

    def grid_targets(campaign: str) -> tuple[int, str]:
        code, out, err = hil_in_process(
            "compensate",
            "model.json",
            campaign,
            "-o",
            "grid.csv",
            "--force",  # each call writes the same file again
            "--step",
            "grid",
            cwd=tmp_path,
            capsys=capsys,
        )
        if code == 0:
            df = pd.read_csv(tmp_path / "grid.csv")
            np.testing.assert_allclose(df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3, target, atol=1e-9)
        return code, err

    code, err = grid_targets("old.sqlite")  # the file found beside the cell file the snapshot names
    assert code == 0, err
    (cell_dir / "Our_UR10.toml").unlink()
    code, err = grid_targets("job.sqlite")  # the campaign describes itself
    assert code == 0, err
    assert "the campaign's robot is Our_UR10, the model's ur10" in err
    code, err = grid_targets("old.sqlite")
    assert code == 2 and "names the robot file 'Our_UR10.toml' but keeps no copy of it" in err, err
    assert f"put the robot file back at {cell_dir / 'Our_UR10.toml'}" in err


def thermal_model(model: CalibratedModel, driver: str) -> CalibratedModel:
    """The model plus link growth of 20 ppm per K (driver temperature_c, reference 20 degC) or a base drift
    with time (driver t_s)."""
    if driver == "temperature_c":
        eff = make_effect("thermal_expansion")
        eff.state, eff.params = {"driver": "temperature_c", "reference": 20.0}, np.array([2e-5])
    else:
        eff = make_effect("thermal_drift")
        eff.state, eff.params = {"driver": "t_s", "reference": 30.0}, np.array([1e-7, 0.0, -1e-7])
    return replace(model, effects=[*model.effects, eff])


def test_thermal_models_take_the_cell_temperature_and_refuse_time_from_another_clock(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    hot = thermal_model(model, "temperature_c")
    hot.save(tmp_path / "hot.json")
    thermal_model(model, "t_s").save(tmp_path / "drift.json")
    T = loop_poses(model)
    layout = write_campaign(tmp_path / "job.sqlite", model, loop_targets=T, unread_temperature="g1-0003")

    def run(*args):
        return hil_in_process(
            "compensate",
            *args,
            "-o",
            "j.csv",
            "--force",
            "--threshold-mm",
            "0.002",
            cwd=tmp_path,
            capsys=capsys,
        )

    code, out, err = run("hot.json", "job.sqlite")  # loop targets carry no temperature
    assert code == 2 and "3 of 3 targets have none" in err and "give --temperature-c C" in err, err
    code, out, err = run("hot.json", "job.sqlite", "--step", "grid")  # one point without a reading
    assert code == 2 and "1 of 8 targets have none" in err and "--temperature-c" in err, err
    with pytest.raises(SystemExit) as exit_info:  # argparse refuses it before any work
        run("hot.json", "job.sqlite", "--temperature-c", "300")
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--temperature-c: 300 is outside [-20, 60]" in err, err

    reached = {}
    for temperature in (20.0, 30.0):
        code, out, err = run("hot.json", "job.sqlite", "--temperature-c", str(temperature))
        assert code == 0, err
        df = pd.read_csv(tmp_path / "j.csv")
        assert (df["temperature_c"] == temperature).all() and (df["status"] == "ok").all()
        q = df[Q_COLS].to_numpy()
        at = predicted(hot, q, np.ones(len(q), int), np.full(len(q), temperature))
        assert np.linalg.norm(at - T[:, :3, 3], axis=1).max() < 2e-6  # on target at that temperature
        reached[temperature] = q
    assert np.abs(reached[30.0] - reached[20.0]).max() > 1e-5  # 10 K of growth moved the joints

    code, out, err = run("hot.json", "job.sqlite", "--step", "grid", "--temperature-c", "24")
    assert code == 0, err
    df = pd.read_csv(tmp_path / "j.csv")
    grid = layout["grid"]
    measured = 20.0 + 0.01 * (10.0 + 4.0 * np.arange(len(df)))
    expected = np.where(df["point_id"] == "g1-0003", 24.0, measured)
    np.testing.assert_allclose(df["temperature_c"], expected)  # the option only where no reading was taken
    at = predicted(hot, df[Q_COLS].to_numpy(), grid["smr"], expected)
    assert np.linalg.norm(at - commanded_points(model, grid["q"], grid["smr"]), axis=1).max() < 2e-6

    code, out, err = run("model.json", "job.sqlite", "--temperature-c", "25")
    assert code == 0 and "--temperature-c changes nothing" in err, err

    for step in ("grid", "loop"):  # t_s of a campaign counts from its own start, not from the model's data
        code, out, err = run("drift.json", "job.sqlite", "--step", step)
        assert code == 2 and "thermal_drift effect is driven by time" in err and "not on that clock" in err, (
            err
        )

    points = pd.DataFrame(T[:, :3, 3] * 1e3, columns=["x_mm", "y_mm", "z_mm"])
    points.to_csv(tmp_path / "p.csv", index=False)
    code, out, err = run("hot.json", "p.csv")
    assert code == 2 and "TARGETS has no temperature_c value there" in err and "--temperature-c" in err, err
    assert run("hot.json", "p.csv", "--temperature-c", "21")[0] == 0
    code, out, err = run("drift.json", "p.csv")  # a CSV's t_s is on the model's clock: it must be there
    assert code == 2 and "every target needs t_s" in err, err
    points.assign(t_s=[100.0, 200.0, 300.0]).to_csv(tmp_path / "p.csv", index=False)
    assert run("drift.json", "p.csv")[0] == 0


def test_a_path_stays_in_one_nest(model, tmp_path, capsys):
    """compensate_path's continuity runs per nest, so a path across nests is refused; --smr makes it one."""
    model.save(tmp_path / "model.json")
    write_campaign(tmp_path / "job.sqlite", model)
    code, out, err = hil_in_process(
        "compensate",
        "model.json",
        "job.sqlite",
        "--step",
        "grid",
        "--path",
        "-o",
        "p.csv",
        cwd=tmp_path,
        capsys=capsys,
    )
    assert code == 2 and "nests [1, 2]" in err and "give --smr 1" in err, err
    assert not (tmp_path / "p.csv").exists()
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "--step", "grid", "--path", "--smr", "1", "-o", "p.csv",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    df = pd.read_csv(tmp_path / "p.csv")
    assert (df["smr"] == 1).all() and "branch_jump" in df.columns


def test_targets_warmer_than_the_fitted_range_are_warned_about(model, tmp_path, capsys):
    hot = thermal_model(model, "temperature_c")
    hot.info["run"] = {
        "inputs": {"training": {"temperature_c_range": [19.0, 23.0]}}
    }  # as diagnose records it
    hot.save(tmp_path / "hot.json")
    write_campaign(tmp_path / "job.sqlite", model, loop_targets=loop_poses(model))
    for temperature, warned in ((21.0, False), (23.4, False), (30.0, True)):
        code, _, err = hil_in_process(
            "compensate", "hot.json", "job.sqlite", "-o", "j.csv", "--force", "--temperature-c", str(temperature),
            cwd=tmp_path, capsys=capsys,
        )  # fmt: skip
        assert code == 0, err
        assert ("outside the 19.0..23.0 degC the model's thermal effect was fitted on" in err) == warned, err


def test_the_run_record_keeps_the_training_temperatures():
    from hil.analysis.diagnosis.pipeline import run_record
    from hil.geometry.robots import get_robot

    df = pd.DataFrame({"x_mm": [1.0, 2.0, 3.0], "temperature_c": [21.5, "", 23.25]})
    record = run_record(get_robot("ur10"), {"training": df, "validation": df.drop(columns="temperature_c")})
    assert record["inputs"]["training"]["temperature_c_range"] == [21.5, 23.25]
    assert "temperature_c_range" not in record["inputs"]["validation"]
