"""Coupled joints (issue 34, part 2): a robot file's [coupling] read and checked, data converted at the edge
only when it says which joints it holds, and the round trip of a FANUC-like arm whose controller reports J3
against the horizontal: sweeps in the pendant's joints -> `hil axes --robot` -> robot file with the coupling
-> `hil calibrate` with three SMRs per pose -> held-out error at the noise."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from hil.data.dataset import DatasetError, make_dataset
from hil.data.joint_conventions import joints_to_kinematic
from hil.geometry.coupling import JointConvention, coupling_from_table
from hil.geometry.kinematics import measured_point
from hil.geometry.robots import get_robot, robot_coupling, robot_from_text
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import CalibratedModel
from hil.runner.cell_config import load_cell_config
from tests.cell_fixtures import sim_cell_toml
from tests.cli_in_process import run_hil

SIGMA_M = 15e-6  # per-axis 1-sigma of one tracker reading
FANUC_ELBOW = [[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, -1, -1, 0, 0, 0],
               [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 1]]  # fmt: skip
TOOLS = {1: np.array([0.04, -0.03, 0.06]), 2: np.array([-0.05, 0.04, 0.05]), 3: np.array([0.03, 0.06, 0.04])}
Q_REF = np.array([0.1, 0.2, -0.3, 0.4, -0.6, 0.2])  # kinematic joints of the reference pose


def test_the_builtin_fanuc_declares_its_elbow_as_the_sum_of_two_readings():
    coupling = robot_coupling("lrmate200id")
    assert coupling is not None and coupling.describe() == "kinematic q3 = -J2 - J3"
    assert robot_coupling("ur10") is None
    # the pendant's J3 = -J2 in a J2 sweep holds the forearm level: the elbow does not turn
    j2 = np.deg2rad(np.linspace(-30, 30, 7))
    q_pendant = np.zeros((7, 6))
    q_pendant[:, 1], q_pendant[:, 2] = j2, -j2
    q = coupling.to_kinematic(q_pendant)
    assert np.ptp(q[:, 2]) == 0 and np.ptp(q[:, 1]) > 1.0
    assert coupling.to_controller(q) == pytest.approx(q_pendant, abs=1e-15)


def test_an_interaction_limit_is_a_linear_inequality_on_the_readings():
    coupling = coupling_from_table(
        {"kinematic_from_controller": FANUC_ELBOW, "limit": [{"controller": [0, 1, 1, 0, 0, 0], "range_deg": [-70, 80]}]},
        6,
        "arm.toml",
    )  # fmt: skip
    assert coupling.limits[0].describe() == "-70 <= J2 + J3 <= 80 deg"
    q = np.zeros((3, 6))
    q[:, 1] = np.deg2rad([50, 50, -50])
    q[:, 2] = np.deg2rad([20, 40, -30])  # J2 + J3 = 70, 90, -80
    assert coupling.within_limits(q).tolist() == [True, False, False]


@pytest.mark.parametrize(
    ("table", "words"),
    [
        ({"kinematic_from_controller": [[1, 0], [0, 1]]}, "6 rows of 6 numbers"),
        ({"kinematic_from_controller": [r[:] for r in FANUC_ELBOW[:2]] * 3}, "singular"),
        ({"kinematic_from_controller": FANUC_ELBOW, "limit": [{"controller": [0, 1, 1], "range_deg": [0, 1]}]}, "6 numbers"),
        ({"kinematic_from_controller": FANUC_ELBOW, "limit": [{"controller": [0] * 6, "range_deg": [0, 1]}]}, "non-zero"),
        ({"matrix": FANUC_ELBOW}, "kinematic_from_controller"),
    ],
)  # fmt: skip
def test_a_bad_coupling_is_refused_with_what_to_write(table, words):
    text = 'name = "arm"\n' + "".join("[[joint]]\nd_mm = 100\na_mm = 50\nalpha_deg = 90\n" for _ in range(6))
    text += "[coupling]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in table.items() if k != "limit")
    for limit in table.get("limit", []):
        text += "[[coupling.limit]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in limit.items())
    with pytest.raises(ValueError, match=words):
        robot_from_text(text, "arm.toml")


def test_data_of_a_coupled_robot_must_say_which_joints_it_holds():
    coupling = robot_coupling("lrmate200id")
    q = np.tile(np.deg2rad([10.0, 20.0, -5.0, 0.0, 30.0, 0.0]), (2, 1))
    df = make_dataset(q, np.zeros((2, 3)))
    with pytest.raises(
        DatasetError, match="--joint-convention controller .* or --joint-convention kinematic"
    ):
        joints_to_kinematic(df, coupling, None, "data.csv")
    converted = joints_to_kinematic(df, coupling, JointConvention.CONTROLLER, "data.csv")
    assert converted["q3_rad"].to_numpy() == pytest.approx(np.deg2rad(-15.0))
    assert converted.attrs["joints_read_as"] == "controller"
    again = joints_to_kinematic(converted, coupling, None, "data.csv")  # converted once, never twice
    assert again["q3_rad"].to_numpy() == pytest.approx(np.deg2rad(-15.0))
    df.attrs["joint_convention"] = "controller"  # a campaign's recorded convention stands for the option
    assert joints_to_kinematic(df, coupling, None, "c.sqlite")["q3_rad"].to_numpy() == pytest.approx(
        np.deg2rad(-15.0)
    )
    with pytest.raises(DatasetError, match="recorded its joints as the controller joints"):
        joints_to_kinematic(df, coupling, "kinematic", "c.sqlite")
    del df.attrs["joint_convention"]
    kept = joints_to_kinematic(df, coupling, "kinematic", "data.csv")
    assert kept["q3_rad"].to_numpy() == pytest.approx(np.deg2rad(-5.0))
    assert joints_to_kinematic(df, None, None, "data.csv") is df  # no coupling: nothing to choose


# ------------------------------------------------------------------------ the FANUC-like round trip
@pytest.fixture(scope="module")
def fanuc():
    """An LR Mate 200iD-like arm with random geometric errors, its controller's coupling and a tracker 2 m off."""
    rng = np.random.default_rng(11)
    nominal = get_robot("lrmate200id")
    true = nominal.with_errors(
        {k: rng.normal(0, 3e-4 if k[0] in "ad" else 5e-4) for k in nominal.param_names}
    )
    T = make_transform(Rotation.from_rotvec([0.02, -0.05, 2.5]).as_matrix(), [1.8, 0.6, -0.4])
    return {"true": true, "T": T, "coupling": robot_coupling("lrmate200id"), "rng": rng}


def measured(arm, q_kinematic: np.ndarray, smrs=(1, 2, 3)) -> pd.DataFrame:
    """Every SMR read at every pose, the joints written as the pendant shows them (degrees)."""
    q = np.repeat(q_kinematic, len(smrs), axis=0)
    smr = np.tile(np.array(smrs), len(q_kinematic))
    p = np.zeros((len(q), 3))
    for s in smrs:
        p[smr == s] = measured_point(arm["true"], q[smr == s], arm["T"], TOOLS[s])
    df = make_dataset(arm["coupling"].to_controller(q), p + arm["rng"].normal(0, SIGMA_M, p.shape), smr=smr)
    for i in range(1, 7):
        df[f"q{i}_deg"] = np.rad2deg(df.pop(f"q{i}_rad"))
    return df


def sweep_joints(span_rad: float = 1.6, points: int = 15) -> np.ndarray:
    """Each kinematic joint turned alone about Q_REF: in the pendant's joints J3 moves in the J2 sweep."""
    rows = []
    for j in range(6):
        for v in np.linspace(-span_rad / 2, span_rad / 2, points):
            row = Q_REF.copy()
            row[j] += v
            rows.append(row)
    return np.array(rows)


def random_joints(rng: np.random.Generator, n: int) -> np.ndarray:
    lo, hi = np.deg2rad([[-120, -40, -60, -150, -100, -180], [120, 80, 60, 150, 100, 180]])
    return rng.uniform(lo, hi, (n, 6))


def test_fanuc_like_round_trip_from_pendant_joints_to_a_calibration_at_the_noise(fanuc, tmp_path, capsys):
    measured(fanuc, sweep_joints()).to_csv(tmp_path / "sweeps.csv", index=False)
    rng = np.random.default_rng(3)
    for name, n in (("train", 60), ("val", 40)):
        measured(fanuc, random_joints(rng, n)).to_csv(tmp_path / f"{name}.csv", index=False)

    # the pendant's J3 moves in the J2 sweep: without the coupling, that is two joints moving
    r = run_hil("axes", "sweeps.csv", "-o", "plain.toml", cwd=tmp_path, capsys=capsys)
    assert r.returncode != 0 and "--robot" in r.stderr and "couples" in r.stderr
    # with it, the data must say which joints it holds
    r = run_hil("axes", "sweeps.csv", "-o", "arm.toml", "--robot", "lrmate200id", cwd=tmp_path, capsys=capsys)
    assert r.returncode != 0 and "--joint-convention controller" in r.stderr
    r = run_hil(
        "axes", "sweeps.csv", "-o", "arm.toml", "--robot", "lrmate200id", "--joint-convention", "controller",
        "--json", "axes.json", cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "axes.json").read_text())
    assert report["coupling"] == "kinematic q3 = -J2 - J3"
    assert all(j["direction_sigma_deg"] < 0.01 for j in report["joints"]), report["joints"]
    text = (tmp_path / "arm.toml").read_text()
    assert robot_coupling(str(tmp_path / "arm.toml")).describe() == "kinematic q3 = -J2 - J3"
    assert "limits_deg = [-100, 145]" in text  # the maker's limits, not the sweeps'

    held_out = {}
    for robot in ("arm.toml", "lrmate200id"):
        r = run_hil(
            "calibrate", "train.csv", "--robot", robot, "--joint-convention", "controller", "-o", f"{robot}.json",
            cwd=tmp_path, capsys=capsys,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        model = CalibratedModel.load(tmp_path / f"{robot}.json")
        val = joints_to_kinematic(
            pd.read_csv(tmp_path / "val.csv").pipe(_in_radians), fanuc["coupling"], "controller", "val.csv"
        )
        err = model.predict(val) - val[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3
        held_out[robot] = float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) * 1e3
    _predict_and_compensate_in_the_pendants_joints(tmp_path, capsys, fanuc["coupling"])
    noise_mm = SIGMA_M * math.sqrt(3) * 1e3  # the 3D RMS of the tracker's noise alone
    print(f"FANUC-like round trip, held-out RMS (mm): {held_out}; tracker noise {noise_mm:.4f} mm")
    assert held_out["arm.toml"] < 1.3 * noise_mm, held_out
    assert held_out["arm.toml"] < held_out["lrmate200id"] + 0.005, held_out


def _predict_and_compensate_in_the_pendants_joints(tmp_path, capsys, coupling) -> None:
    """The model keeps the coupling: predict reads the pendant's joints and compensate writes them, each
    only when told which joints it handles."""
    r = run_hil("predict", "arm.toml.json", "val.csv", "-o", "p.csv", cwd=tmp_path, capsys=capsys)
    assert r.returncode != 0 and "--joint-convention controller" in r.stderr
    r = run_hil(
        "predict", "arm.toml.json", "val.csv", "-o", "p.csv", "--joint-convention", "controller",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    val, predicted = pd.read_csv(tmp_path / "val.csv"), pd.read_csv(tmp_path / "p.csv")
    given_j3 = np.deg2rad(val["q3_deg"].to_numpy())
    assert predicted["q3_rad"].to_numpy() == pytest.approx(given_j3)  # the pendant's, as given
    xyz = ["x_mm", "y_mm", "z_mm"]
    assert (
        np.abs(predicted[xyz].to_numpy() - val[xyz].to_numpy()).max() < 0.15
    )  # the noise, not a wrong joint
    val[xyz].head(8).to_csv(tmp_path / "targets.csv", index=False)  # SMR 1's nest on each (a CSV's default)
    r = run_hil("compensate", "arm.toml.json", "targets.csv", "-o", "q.csv", cwd=tmp_path, capsys=capsys)
    assert r.returncode != 0 and "--joint-convention controller" in r.stderr
    r = run_hil(
        "compensate", "arm.toml.json", "targets.csv", "-o", "q.csv", "--joint-convention", "controller",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = pd.read_csv(tmp_path / "q.csv")
    model = CalibratedModel.load(tmp_path / "arm.toml.json")
    q_pendant = out[[f"q{i}_rad" for i in range(1, 7)]].to_numpy()
    reached = model.predict(make_dataset(coupling.to_kinematic(q_pendant), np.zeros((8, 3)), smr=1))
    assert (out["status"] == "ok").all()
    assert np.abs(reached * 1e3 - out[xyz].to_numpy()).max() < 1e-3  # the pendant joints put each SMR there


def _in_radians(df: pd.DataFrame) -> pd.DataFrame:
    for i in range(1, 7):
        df[f"q{i}_rad"] = np.deg2rad(df.pop(f"q{i}_deg"))
    return df


def test_a_sweep_the_coupling_does_not_make_single_is_refused_naming_it(fanuc, tmp_path, capsys):
    """J2 turned with the pendant's J3 held: the elbow turns too, two kinematic joints move in one sweep."""
    df = measured(fanuc, sweep_joints(points=8), smrs=(1,))
    df["sweep"] = np.repeat([f"j{j}" for j in range(1, 7)], 8)
    held_j3_deg = np.rad2deg(-Q_REF[1] - Q_REF[2])  # the pendant's J3 at the reference pose
    df.loc[df["sweep"] == "j2", "q3_deg"] = held_j3_deg
    df.to_csv(tmp_path / "sweeps.csv", index=False)
    r = run_hil(
        "axes", "sweeps.csv", "-o", "arm.toml", "--robot", "lrmate200id", "--joint-convention", "controller",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert r.returncode != 0
    assert "sweep j2: joint" in r.stderr and "moves too" in r.stderr
    assert "kinematic q3 = -J2 - J3" in r.stderr


def test_a_cell_of_a_coupled_robot_reads_its_home_as_the_pendant_shows_it(tmp_path):
    """The cell's [motion] home_deg is the controller's joints (what the pendant shows); the runner keeps the
    kinematic ones, and its envelope the robot's coupling (for the interaction limits)."""
    path = tmp_path / "cell.toml"
    text = sim_cell_toml().replace('model = "ur10"', 'model = "lrmate200id"')
    path.write_text(text)
    config = load_cell_config(path)
    assert config.coupling is not None and config.coupling.describe() == "kinematic q3 = -J2 - J3"
    home_pendant_deg = [0.0, 20.0, -30.0, 0.0, -60.0, 0.0]
    path.write_text(text + "\n[motion]\nhome_deg = " + str(home_pendant_deg) + "\n")
    if "[motion]" in text:  # the base config has its own [motion] table: set the key there instead
        path.write_text(text.replace("[motion]", "[motion]\nhome_deg = " + str(home_pendant_deg), 1))
    config = load_cell_config(path)
    np.testing.assert_allclose(np.rad2deg(config.q_home_rad), [0.0, 20.0, 10.0, 0.0, -60.0, 0.0], atol=1e-9)
