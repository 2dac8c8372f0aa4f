"""`hil model export`: the calibrated chain as a URDF (read back by yourdfpy), as the UR description's
kinematics file (read back by the UR description's convention, written out here) and as a DH table; a model
with terms a chain cannot hold is replaced by its best chain, and the printed cost is what the file leaves."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
import yaml
from calib_data import compliant_ur10, ur10_joints
from scipy.spatial.transform import Rotation

from hil.data.dataset import make_dataset
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import CalibratedModel
from tests.cli_in_process import run_hil

UR_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]
TOOL = np.array([0.03, -0.02, 0.11])


def _kinematic_model(robot: str, seed: int, flange_errors: bool = True) -> CalibratedModel:
    """A purely kinematic calibrated model: the built-in arm with hidden errors (beta included; on the last
    joint's a and alpha only with `flange_errors`, which a calibration leaves to the tool point), a tracker
    2 m away, one tool point."""
    rng = np.random.default_rng(seed)
    nominal = get_robot(robot)
    names = [n for n in nominal.param_names if flange_errors or n not in ("a6", "alpha6")]
    kin = nominal.with_errors({n: rng.normal(0, 3e-4 if n[0] in "ad" else 5e-4) for n in names})
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    return CalibratedModel(robot, nominal, kin, T, {1: TOOL})


def _urdf_points(path, q, root, T_tracker_base, tool=TOOL):
    """Tracker-frame tool points of a written URDF's tool0 at joints q (yourdfpy's forward kinematics)."""
    robot = _yourdfpy().URDF.load(str(path), load_meshes=False)
    out = []
    for row in q:
        robot.update_cfg(row)
        T = T_tracker_base @ robot.get_transform("tool0", root)
        out.append(T[:3, :3] @ tool + T[:3, 3])
    return np.array(out), list(robot.actuated_joint_names)


def _ur_kinematics_flanges(text: str, q: np.ndarray) -> np.ndarray:
    """The UR description's chain from a kinematics file: base_link_inertia (the controller's base) ->
    each joint's origin (x y z, then fixed-axis roll pitch yaw), a turn about its z; tool0 is wrist_3_link."""
    data = yaml.safe_load(text)["kinematics"]
    assert re.fullmatch(r"calib_\d+", data["hash"])
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    for i, key in enumerate(("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")):
        v = data[key]
        origin = make_transform(
            Rotation.from_euler("xyz", [v["roll"], v["pitch"], v["yaw"]]).as_matrix(),
            [v["x"], v["y"], v["z"]],
        )
        turn = np.zeros((len(q), 4, 4))
        turn[:, :3, :3] = Rotation.from_rotvec(np.outer(q[:, i], [0, 0, 1])).as_matrix()
        turn[:, 3, 3] = 1.0
        T = T @ origin @ turn
    return T


def _dh_model(path) -> KinematicModel:
    """A model from a written DH table (its columns as any tool reads them)."""
    t = pd.read_csv(path)
    return KinematicModel(
        name="from_csv",
        theta=np.radians(t["theta_offset_deg"].to_numpy()),
        d=t["d_mm"].to_numpy() / 1e3,
        a=t["a_mm"].to_numpy() / 1e3,
        alpha=np.radians(t["alpha_deg"].to_numpy()),
        beta=np.radians(t["beta_deg"].to_numpy()),
        uses_beta=t["hayati_beta"].to_numpy(bool),
        joint_limits=np.radians(t[["lower_deg", "upper_deg"]].to_numpy()),
    )


def test_a_ur_model_exported_is_what_hil_predict_says(tmp_path, capsys):
    model = _kinematic_model("ur10", 1, flange_errors=False)
    model.save(tmp_path / "m.json")
    q = ur10_joints(np.random.default_rng(2), 60)
    make_dataset(q, np.zeros((len(q), 3)), smr=1).to_csv(tmp_path / "q.csv", index=False)
    out = run_hil(
        "model", "export", "m.json", "--urdf", "ur.urdf", "--ur-kinematics", "ur.yaml", "--dh", "dh.csv",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "purely kinematic: its chain is written as calibrated" in out.stdout
    assert run_hil("predict", "m.json", "q.csv", "-o", "p.csv", cwd=tmp_path, capsys=capsys).returncode == 0
    predicted = pd.read_csv(tmp_path / "p.csv")[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3
    # The UR description's `base` is the controller's base frame, the model's.
    points, joints = _urdf_points(tmp_path / "ur.urdf", q, "base", model.T_tracker_base)
    assert joints == UR_JOINTS
    urdf_um = np.max(np.linalg.norm(points - predicted, axis=1)) * 1e6
    yaml_flanges = _ur_kinematics_flanges((tmp_path / "ur.yaml").read_text(), q)
    model_flanges = forward_kinematics(model.kinematic, q)  # base_link_inertia is the controller's base
    yaml_um = np.max(np.linalg.norm(yaml_flanges[:, :3, 3] - model_flanges[:, :3, 3], axis=1)) * 1e6
    dh_um = (
        np.max(
            np.abs(
                forward_kinematics(_dh_model(tmp_path / "dh.csv"), q) - forward_kinematics(model.kinematic, q)
            )
        )
        * 1e6
    )
    # A flange off wrist_3_link's frame cannot go into the UR file (the description fixes tool0 there).
    _kinematic_model("ur10", 1).save(tmp_path / "flange_off.json")
    out = run_hil(
        "model", "export", "flange_off.json", "--ur-kinematics", "f.yaml", cwd=tmp_path, capsys=capsys
    )
    assert (
        out.returncode != 0
        and "off wrist_3_link's frame, which the UR description fixes as tool0" in out.stderr
    )
    print(
        f"UR10 export: URDF vs hil predict max {urdf_um:.2e} um, UR kinematics file {yaml_um:.2e} um, DH table {dh_um:.2e} um"
    )
    assert urdf_um < 1.0 and yaml_um < 1.0 and dh_um < 1.0
    assert np.allclose(yaml_flanges[:, :3, :3], model_flanges[:, :3, :3], atol=1e-9)


def test_another_arm_gets_generic_names_and_no_ur_file(tmp_path, capsys):
    model = _kinematic_model("kr6r900", 3)
    model.save(tmp_path / "m.json")
    out = run_hil("model", "export", "m.json", "--urdf", "kr6.urdf", cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    lim = model.nominal.joint_limits
    q = np.random.default_rng(4).uniform(lim[:, 0], lim[:, 1], (40, 6))
    points, joints = _urdf_points(tmp_path / "kr6.urdf", q, "base_link", model.T_tracker_base)
    assert joints == [f"joint_{i}" for i in range(1, 7)]
    predicted = model.predict(make_dataset(q, np.zeros((len(q), 3)), smr=1))
    assert np.max(np.linalg.norm(points - predicted, axis=1)) < 1e-6
    out = run_hil("model", "export", "m.json", "--ur-kinematics", "k.yaml", cwd=tmp_path, capsys=capsys)
    assert out.returncode != 0 and "read by the Universal Robots description only" in out.stderr
    assert not (tmp_path / "k.yaml").exists()


@pytest.fixture(scope="module")
def compliant(tmp_path_factory):
    """A UR10 whose joints 2 and 3 yield under gravity, its training joints and its export over them."""
    folder = tmp_path_factory.mktemp("export")
    q = ur10_joints(np.random.default_rng(8), 150)
    model = compliant_ur10(8, {1: TOOL}, TOOL, len(q))
    model.info["training_joint_range_rad"] = [q.min(axis=0).tolist(), q.max(axis=0).tolist()]
    model.save(folder / "m.json")
    make_dataset(q, np.zeros((len(q), 3)), smr=1).to_csv(folder / "train.csv", index=False)
    return folder, model, q


def test_gravity_yield_is_replaced_by_the_best_chain_and_its_cost_printed(compliant, capsys):
    folder, model, q = compliant
    out = run_hil(
        "model", "export", "m.json", "--urdf", "ur.urdf", "--dh", "dh.csv", "--joints", "train.csv",
        cwd=folder, capsys=capsys,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert (
        "left out (not kinematics, a URDF cannot hold them): gravity_compliance (joint 2), gravity_compliance (joint 3)"
        in out.stdout
    )
    rms_mm, max_mm = map(float, re.search(r"off it by ([\d.]+) mm RMS, ([\d.]+) mm max", out.stdout).groups())
    assert "note: --dh: the table's base frame is the model's moved by" in out.stdout
    full = model.predict(make_dataset(q, np.zeros((len(q), 3)), smr=1))
    points, _ = _urdf_points(folder / "ur.urdf", q, "base", model.T_tracker_base)
    urdf_off = np.linalg.norm(points - full, axis=1)
    own_geometry = CalibratedModel(
        model.robot, model.nominal, model.kinematic, model.T_tracker_base, model.tools
    )
    own_off = np.linalg.norm(
        own_geometry.predict(make_dataset(q, np.zeros((len(q), 3)), smr=1)) - full, axis=1
    )
    print(
        f"gravity-yield UR10: export cost printed {rms_mm:.4f} mm RMS, {max_mm:.4f} mm max; the URDF's tool point "
        f"{np.sqrt(np.mean(urdf_off**2)) * 1e3:.4f} mm RMS off the full model; the model's geometry alone "
        f"{np.sqrt(np.mean(own_off**2)) * 1e3:.4f} mm RMS"
    )
    # The URDF's tool point is off the full model by about the printed figure (which also counts the three
    # orientation points), and by much less than the model's own geometry without its gravity terms.
    assert rms_mm > 0.01 and np.sqrt(np.mean(urdf_off**2)) * 1e3 <= 1.2 * rms_mm
    assert np.max(urdf_off) * 1e3 <= 1.2 * max_mm
    assert np.sqrt(np.mean(urdf_off**2)) < 0.5 * np.sqrt(np.mean(own_off**2))


def test_an_export_names_what_is_missing(compliant, capsys):
    folder, _, _ = compliant
    out = run_hil("model", "export", "m.json", cwd=folder, capsys=capsys)
    assert out.returncode != 0 and "give at least one of --urdf OUT.urdf" in out.stderr
    (folder / "taken.urdf").write_text("")
    out = run_hil("model", "export", "m.json", "--urdf", "taken.urdf", cwd=folder, capsys=capsys)
    assert out.returncode != 0 and "taken.urdf" in out.stderr and (folder / "taken.urdf").read_text() == ""


def test_a_ur_read_from_its_urdf_goes_back_out_at_its_base_link(tmp_path, capsys):
    """URDF in, URDF out: a UR read at its `base_link` (joint 1 half a turn from the controller's base)
    is written with the UR names and the same base_link, its tool0 where the model puts the flange."""
    from urdf_arms import family_urdf

    (tmp_path / "in.urdf").write_text(family_urdf("ur10"))
    nominal = get_robot(str(tmp_path / "in.urdf"))
    model = CalibratedModel("ur10_urdf", nominal, nominal, np.eye(4), {1: TOOL})
    model.save(tmp_path / "m.json")
    out = run_hil("model", "export", "m.json", "--urdf", "out.urdf", cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    q = ur10_joints(np.random.default_rng(5), 30)
    points, joints = _urdf_points(tmp_path / "out.urdf", q, "base_link", np.eye(4))
    assert joints == UR_JOINTS
    T = forward_kinematics(nominal, q)
    assert np.max(np.linalg.norm(points - (T[:, :3, :3] @ TOOL + T[:, :3, 3]), axis=1)) < 1e-6


def _yourdfpy():
    """yourdfpy, imported where a test reads a URDF with it: it brings trimesh, networkx and shapely (1.5 s),
    which every other test worker would otherwise import while collecting."""
    import yourdfpy

    return yourdfpy
