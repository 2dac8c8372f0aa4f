"""Robots from URDF: the converted model's forward kinematics are the URDF's (read by yourdfpy, a URDF library
independent of hil), it calibrates as its robot file does, and what it cannot hold is refused with the fix."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from urdf_arms import FAMILIES, LRMATE_WORLD_XYZ, Joint, family_urdf, kr6_joints, ur10_joints, urdf_text

from hil.analysis.calibration.solve import calibrate
from hil.data.dataset import make_dataset
from hil.geometry.kinematics import forward_kinematics, link_frames, measured_point
from hil.geometry.robots import get_robot, robot_body
from hil.geometry.se3 import make_transform
from hil.geometry.urdf_import import import_urdf
from hil.geometry.urdf_read import UrdfError

FK_TOL_M = 1e-6  # the brief's 1 um


@pytest.fixture(scope="module")
def urdf_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("urdf")
    paths = {}
    for robot in FAMILIES:
        paths[robot] = folder / f"{robot}.urdf"
        paths[robot].write_text(family_urdf(robot))
    return paths


def _random_joints(model, rng, n):
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    return rng.uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi), (n, model.n_joints))


def _yourdfpy_flanges(path, imported, q):
    """T_root_flange by yourdfpy for each joint set (its joints in the URDF's actuated order)."""
    robot = _yourdfpy().URDF.load(str(path), load_meshes=False)
    assert list(robot.actuated_joint_names) == list(imported.joint_names)
    out = []
    for row in q:
        robot.update_cfg(row)
        out.append(robot.get_transform(imported.chain.flange, imported.chain.root))
    return np.array(out)


@pytest.mark.parametrize("robot", list(FAMILIES))
def test_the_models_forward_kinematics_are_the_urdfs(urdf_files, robot):
    imported = import_urdf(urdf_files[robot].read_text(), str(urdf_files[robot]))
    model = get_robot(str(urdf_files[robot]))
    assert np.array_equal(model.params, imported.model.params)  # --robot FILE.urdf reads the same model
    q = _random_joints(model, np.random.default_rng(7), 100)
    want = _yourdfpy_flanges(urdf_files[robot], imported, q)
    got = imported.T_root_base @ forward_kinematics(model, q)
    position_um = np.max(np.linalg.norm(got[:, :3, 3] - want[:, :3, 3], axis=1)) * 1e6
    turn_rad = np.max(np.abs(got[:, :3, :3] - want[:, :3, :3]))
    print(f"{robot}: FK from the URDF (yourdfpy) vs the converted model, max {position_um:.2e} um")
    assert position_um < FK_TOL_M * 1e6 and turn_rad < 1e-9
    # The test's URDF is the built-in file's arm, joint zeros and directions included: one fixed transform
    # (the URDF's root to the file's base) maps the file's flanges onto the URDF's on every pose.
    builtin = forward_kinematics(get_robot(robot), q)
    root_to_file = want[0] @ np.linalg.inv(builtin[0])
    assert np.max(np.abs(root_to_file @ builtin - want)) < 1e-9


def test_the_chain_is_read_as_a_robot_file_would_give_it(urdf_files):
    ur10 = import_urdf(urdf_files["ur10"].read_text(), str(urdf_files["ur10"]))
    builtin = get_robot("ur10")
    assert ur10.model.name == "ur10_urdf" and ur10.chain.flange == "tool0"  # tool0 before ee_link
    assert list(ur10.model.uses_beta) == list(builtin.uses_beta)  # beta on the parallel joints 2 and 3
    assert ur10.model.link_masses_kg == builtin.link_masses_kg  # base_link's mass moves with no joint
    assert np.allclose(np.abs(ur10.model.a), np.abs(builtin.a)) and np.allclose(ur10.model.d, builtin.d)
    assert np.array_equal(ur10.T_root_base, np.eye(4)) and not ur10.notes  # joint 1 on base_link's z axis
    kr6 = get_robot(str(urdf_files["kr6r900"]))
    assert kr6.link_masses_kg is None and list(kr6.uses_beta) == [False, True, False, False, False, False]
    assert kr6.joint_limits[1].tolist() == [-3.316, 0.785]  # the URDF's limits, radians
    assert not get_robot(str(urdf_files["kr6r900"]), use_beta=False).uses_beta.any()
    # The FANUC-like arm stands on `world` away from joint 1's axis: the base frame moves onto the axis.
    lrmate = import_urdf(urdf_files["lrmate200id"].read_text(), str(urdf_files["lrmate200id"]))
    assert np.allclose(lrmate.T_root_base[:3, 3], [LRMATE_WORLD_XYZ[0], LRMATE_WORLD_XYZ[1], 0.0])
    assert len(lrmate.notes) == 1 and "[400.000, -250.000, 0.000] mm in 'world'" in lrmate.notes[0]
    body = robot_body(str(urdf_files["lrmate200id"]))  # collisions: a body along the DH table
    assert len(body.names) > 0 and "no primitives in" in body.source and "along the DH table" in body.source


def test_centres_of_mass_follow_their_links(urdf_files):
    """Each joint's moved centre of mass, kept in its DH frame, sits where yourdfpy puts the link's."""
    imported = import_urdf(urdf_files["ur10"].read_text(), str(urdf_files["ur10"]))
    robot = _yourdfpy().URDF.load(str(urdf_files["ur10"]), load_meshes=False)
    q = _random_joints(imported.model, np.random.default_rng(3), 5)
    frames = link_frames(imported.model, q)
    coms = {"upper_arm_link": (1, (0, 0, 0.306)), "forearm_link": (2, (0, 0, 0.28615))}
    for row, F in zip(q, frames, strict=True):
        robot.update_cfg(row)
        for link, (i, com) in coms.items():
            want = robot.get_transform(link, "base_link") @ np.append(com, 1.0)
            got = imported.T_root_base @ F[i + 1] @ np.append(imported.com_frame_m[i], 1.0)
            assert np.allclose(got, want, atol=1e-12)


def _with(joints, **changes):
    return [Joint(**{**j.__dict__, **changes.get(j.name, {})}) for j in joints]


@pytest.mark.parametrize(
    ("text", "spec", "words"),
    [
        (
            urdf_text("a", _with(kr6_joints(), joint_a4={"kind": "prismatic", "limits": (0, 0.1)})),
            "arm.urdf",
            "joint 'joint_a4' is prismatic (it slides); hil's model turns every joint",
        ),
        (
            urdf_text("a", _with(kr6_joints(), joint_a3={"mimic": "joint_a2"})),
            "arm.urdf",
            "joint 'joint_a3' mimics joint 'joint_a2'",
        ),
        (
            '<robot name="a" xmlns:xacro="http://www.ros.org/wiki/xacro"><xacro:include filename="x"/></robot>',
            "arm.urdf",
            "not read; expand it first with ROS's xacro tool (`xacro arm.urdf > arm.urdf`",
        ),
        (urdf_text("a", kr6_joints()), "arm.urdf.xacro", "`xacro arm.urdf.xacro > arm.urdf`"),
        (
            urdf_text("a", ur10_joints()),
            "arm.urdf#flange",
            "no link named 'flange' (the flange after '#')",
        ),
        (
            urdf_text("a", [*kr6_joints()[:-1], Joint("joint_a6-camera", "link_6", "camera", axis=None)]),
            "arm.urdf",
            "the chain ends in several links (camera, flange); name the flange: arm.urdf#camera",
        ),
        ("<robot name='a'><link name='x'></robot>", "arm.urdf", "not valid XML"),
    ],
)
def test_what_a_calibration_model_cannot_hold_is_refused_with_the_fix(text, spec, words):
    with pytest.raises(UrdfError) as exc:
        import_urdf(text, spec)
    assert words in str(exc.value)


def test_a_tree_is_cut_at_the_named_flange():
    """A gripper's sliding fingers after tool0 are no part of the arm: '#tool0' names the flange, and a
    flange link turned on the last one gives the same chain seen from another frame."""
    fingers = [
        Joint("tool0-hand", "tool0", "hand", (0, 0, 0.05), axis=None),
        Joint("finger_l", "hand", "finger_l_link", axis=(0, 1, 0), kind="prismatic", limits=(0, 0.04)),
        Joint("finger_r", "hand", "finger_r_link", axis=(0, 1, 0), kind="prismatic", limits=(0, 0.04)),
    ]
    text = urdf_text("kr6_gripper", [*kr6_joints(), *fingers])
    with pytest.raises(UrdfError, match="several links"):
        import_urdf(text, "arm.urdf")
    to_tool0 = import_urdf(text, "arm.urdf#tool0").model
    to_hand = import_urdf(text, "arm.urdf#hand").model
    q = _random_joints(to_tool0, np.random.default_rng(1), 20)
    hand_in_tool0 = make_transform(np.eye(3), [0, 0, 0.05])
    assert np.allclose(
        forward_kinematics(to_tool0, q) @ hand_in_tool0, forward_kinematics(to_hand, q), atol=1e-12
    )
    with pytest.raises(UrdfError, match="joint 'finger_l' is prismatic"):
        import_urdf(text, "arm.urdf#finger_l_link")


@pytest.mark.parametrize("robot", list(FAMILIES))
def test_a_calibration_from_the_urdf_reaches_the_files_held_out_error(urdf_files, robot):
    """The same synthetic campaign (a built-in arm with hidden geometric errors, 10 um noise) calibrated
    from the URDF and from the built-in file: the same held-out error, at the noise."""
    rng = np.random.default_rng(11)
    builtin = get_robot(robot)
    truth = builtin.with_errors(
        {n: rng.normal(0, 2e-4 if n[0] in "ad" else 3e-4) for n in builtin.param_names}
    )
    mid, half = (
        builtin.joint_limits.mean(axis=1),
        0.35 * np.minimum(np.ptp(builtin.joint_limits, axis=1), 2 * np.pi),
    )
    q = rng.uniform(mid - half, mid + half, (200, 6))
    T = make_transform(Rotation.from_rotvec([0.02, -0.05, 1.9]).as_matrix(), [2.1, 0.3, -0.4])
    tool = np.array([0.02, -0.01, 0.08])
    p_true = measured_point(truth, q, T, tool)
    p = p_true + rng.normal(0, 10e-6, p_true.shape)
    train, held_out = make_dataset(q[:140], p[:140]), make_dataset(q[140:], p[140:])
    rms_um = {}
    for start in (str(urdf_files[robot]), robot):
        model = calibrate(train, start).model
        rms_um[start] = np.sqrt(np.mean(np.sum((model.predict(held_out) - p_true[140:]) ** 2, axis=1))) * 1e6
    from_urdf, from_file = rms_um[str(urdf_files[robot])], rms_um[robot]
    print(f"{robot}: held-out RMS from the URDF {from_urdf:.3f} um, from the file {from_file:.3f} um")
    assert from_urdf < 10.0 and abs(from_urdf - from_file) < 0.1


def test_a_cell_names_a_urdf_and_its_flange_and_the_campaign_keeps_it(tmp_path, urdf_files):
    """[robot] model = "ur10.urdf#tool0" beside cell.toml: the nominal model is the URDF's chain to tool0,
    and the station snapshot's copy rebuilds the same robot when the file is gone."""
    from hil.commands.campaign_targets import campaign_robot
    from hil.data.store import CampaignStore
    from hil.runner.cell_config import CellConfigError, load_cell_config
    from hil.runner.cell_warnings import cell_warnings
    from tests.cell_fixtures import sim_cell_toml

    (tmp_path / "arm.urdf").write_text(urdf_files["ur10"].read_text())
    path = tmp_path / "cell.toml"
    path.write_text(sim_cell_toml().replace('model = "ur10"', 'model = "arm.urdf#ee_link"'))
    config = load_cell_config(path)
    assert config.robot_model == f"{tmp_path / 'arm.urdf'}#ee_link" and config.nominal.name == "ur10_urdf"
    q = _random_joints(config.nominal, np.random.default_rng(0), 10)
    assert np.allclose(
        forward_kinematics(config.nominal, q), forward_kinematics(get_robot(config.robot_model), q)
    )
    with CampaignStore(tmp_path / "job.sqlite") as store:
        store.add_snapshot(config.snapshot())
        (tmp_path / "arm.urdf").unlink()
        kept = campaign_robot(store, tmp_path / "job.sqlite")
    assert np.allclose(forward_kinematics(kept, q), forward_kinematics(config.nominal, q), atol=1e-12)
    assert not [w for w in cell_warnings(config) if w.startswith("robot.model")]  # on base_link's z axis
    (tmp_path / "fanuc.urdf").write_text(urdf_files["lrmate200id"].read_text())
    path.write_text(sim_cell_toml().replace('model = "ur10"', 'model = "fanuc.urdf"'))
    assert any(
        "robot.model: base frame: joint 1 does not turn about 'world'" in w
        for w in cell_warnings(load_cell_config(path))
    )
    path.write_text(sim_cell_toml().replace('model = "ur10"', 'model = "arm.urdf.xacro"'))
    (tmp_path / "arm.urdf.xacro").write_text(urdf_files["ur10"].read_text())
    with pytest.raises(CellConfigError, match=r"robot.model: .*expand it first with ROS's xacro tool"):
        load_cell_config(path)


def test_calibrate_takes_a_urdf(tmp_path, urdf_files, capsys):
    """`hil calibrate --robot arm.urdf` on a synthetic FANUC-like campaign: the note on the moved base frame
    is printed, and the model written predicts held-out poses at the noise."""
    from hil.model.calibrated_model import CalibratedModel
    from tests.cli_in_process import run_hil

    (tmp_path / "arm.urdf").write_text(urdf_files["lrmate200id"].read_text())
    rng = np.random.default_rng(4)
    nominal = get_robot("lrmate200id")
    truth = nominal.with_errors(
        {n: rng.normal(0, 2e-4 if n[0] in "ad" else 3e-4) for n in nominal.param_names}
    )
    mid, half = nominal.joint_limits.mean(axis=1), 0.35 * np.ptp(nominal.joint_limits, axis=1)
    q = rng.uniform(mid - half, mid + half, (180, 6))
    T = make_transform(Rotation.from_rotvec([0.0, 0.03, 0.7]).as_matrix(), [1.9, -0.2, 0.1])
    p_true = measured_point(truth, q, T, np.array([0.0, 0.03, 0.07]))
    make_dataset(q[:140], p_true[:140] + rng.normal(0, 10e-6, (140, 3))).to_csv(
        tmp_path / "train.csv", index=False
    )
    out = run_hil(
        "calibrate", "train.csv", "--robot", "arm.urdf#tool0", "-o", "kin.json", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode == 0, out.stderr
    assert "note: arm.urdf#tool0: base frame: joint 1 does not turn about 'world''s z axis" in out.stderr
    model = CalibratedModel.load(tmp_path / "kin.json")
    assert model.robot == "lrmate200id_urdf"
    pred = model.predict(make_dataset(q[140:], p_true[140:]))
    assert np.sqrt(np.mean(np.sum((pred - p_true[140:]) ** 2, axis=1))) < 10e-6
    out = run_hil(
        "calibrate", "train.csv", "--robot", "arm.urdf#nowhere", "-o", "k.json", cwd=tmp_path, capsys=capsys
    )
    assert out.returncode != 0 and "no link named 'nowhere'" in out.stderr


def _yourdfpy():
    """yourdfpy, imported where a test reads a URDF with it: it brings trimesh, networkx and shapely (1.5 s),
    which every other test worker would otherwise import while collecting."""
    import yourdfpy

    return yourdfpy
