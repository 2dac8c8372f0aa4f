"""Robot definitions from TOML files: the built-ins are such files, and any serial 6R is one more."""

import json

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from hil.analysis.calibration.solve import calibrate
from hil.data.dataset import make_dataset
from hil.geometry.ik import random_joints
from hil.geometry.kinematics import forward_kinematics, measured_point, tool_points
from hil.geometry.robots import ROBOT_DIR, ROBOT_NAMES, get_robot, load_robot_file
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import CalibratedModel, model_from_dict, model_to_dict
from tests.cli_in_process import run_hil


def test_every_builtin_is_a_robot_file():
    assert sorted(p.stem for p in ROBOT_DIR.glob("*.toml")) == sorted(ROBOT_NAMES)
    for name in ROBOT_NAMES:
        m = get_robot(name)
        assert m.name == name and m.n_joints == 6
        assert np.all(m.joint_limits[:, 0] < m.joint_limits[:, 1])
    ur10 = get_robot("UR-10")
    assert ur10.a[1] == pytest.approx(-0.612) and ur10.d[0] == pytest.approx(0.1273)
    assert list(ur10.uses_beta) == [False, True, True, False, False, False]
    assert not get_robot("ur10", use_beta=False).uses_beta.any()
    for name in ("ur5", "ur10", "ur5e", "ur10e"):  # aluminium links
        assert get_robot(name).expansion_per_k == pytest.approx(2.3e-5)
    assert get_robot("kr6r900").expansion_per_k is None  # optional: unknown material


def test_expansion_coefficient_survives_the_model_json(tmp_path):
    ur5 = get_robot("ur5")
    assert model_from_dict(json.loads(json.dumps(model_to_dict(ur5)))).expansion_per_k == 2.3e-5
    kr6 = model_to_dict(get_robot("kr6r900"))
    assert "expansion_per_k" not in kr6 and model_from_dict(kr6).expansion_per_k is None
    path = tmp_path / "steel.toml"
    path.write_text(
        (ROBOT_DIR / "kr6r900.toml")
        .read_text()
        .replace('convention = "dh"', 'convention = "dh"\nexpansion_per_k = 1.2e-5')
    )
    assert load_robot_file(path).expansion_per_k == 1.2e-5


def test_link_masses_are_read_checked_and_survive_the_model_json(tmp_path):
    # Universal Robots publish every link's mass (their dynamics parameters); the other makers the arm's total.
    assert get_robot("ur10").link_masses_kg == (7.1, 12.7, 4.27, 2.0, 2.0, 0.365)
    for name in ROBOT_NAMES:
        masses = get_robot(name).link_masses_kg
        assert (masses is not None) == name.startswith("ur")
    ur5 = get_robot("ur5")
    assert model_from_dict(json.loads(json.dumps(model_to_dict(ur5)))).link_masses_kg == ur5.link_masses_kg
    kr6 = model_to_dict(get_robot("kr6r900"))
    assert "link_masses_kg" not in kr6 and model_from_dict(kr6).link_masses_kg is None
    text = (ROBOT_DIR / "ur10.toml").read_text()
    bad = {
        "partial.toml": (text.replace("mass_kg = 0.365\n", ""), r"but not on \[6\]"),
        "grams.toml": (text.replace("mass_kg = 12.7", "mass_kg = 12700"), "not grams"),
        "zero.toml": (text.replace("mass_kg = 12.7", "mass_kg = 0"), "joint 2: mass_kg = 0 is outside"),
    }
    for name, (body, words) in bad.items():
        (tmp_path / name).write_text(body)
        with pytest.raises(ValueError, match=words):
            load_robot_file(tmp_path / name)


def test_a_non_ur_arm_from_its_file_calibrates(tmp_path):
    # A KR 6 R900 with hidden errors, defined by a copy of the built-in file under another name.
    text = (ROBOT_DIR / "kr6r900.toml").read_text().replace('name = "kr6r900"', 'name = "my_cell_robot"')
    (tmp_path / "robot.toml").write_text(text)
    nominal = load_robot_file(tmp_path / "robot.toml")
    assert nominal.name == "my_cell_robot"
    rng = np.random.default_rng(2)
    true = nominal.with_errors(
        {n: rng.normal(0, 2e-4 if n[0] in "ad" else 3e-4) for n in nominal.param_names}
    )
    lim = nominal.joint_limits
    q = rng.uniform(
        lim[:, 0] * 0.5 + lim[:, 1] * 0.5 - 0.4 * np.ptp(lim, axis=1) / 2,
        lim[:, 0] * 0.5 + lim[:, 1] * 0.5 + 0.4 * np.ptp(lim, axis=1) / 2,
        (150, 6),
    )
    T = make_transform(Rotation.from_rotvec([0.0, 0.1, 2.5]).as_matrix(), [2.0, -0.5, 0.2])
    p = measured_point(true, q, T, np.array([0.02, 0.01, 0.09])) + rng.normal(0, 10e-6, (150, 3))
    result = calibrate(make_dataset(q, p), str(tmp_path / "robot.toml"))
    assert result.model.robot == "my_cell_robot"
    assert result.rms_mm < 0.03 and not [n for n in result.notes if n.startswith("implausible")]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("alpha_deg = 0\n", "", 1), "missing ['alpha_deg']"),
        (
            lambda t: t.replace('convention = "dh"', 'convention = "hartenberg"'),
            "convention 'hartenberg' is not supported; write convention = one of 'dh'",
        ),
        (lambda t: t.replace("[[joint]]", "[[joint]", 1), "not a valid TOML"),
        (lambda t: t.replace("d_mm = 0\n", "d_m = 0\n", 1), "unknown key(s) ['d_m']"),
        (lambda t: t.replace("limits_deg = [-170, 170]", "limits_deg = [170, -170]"), "lower < upper"),
        (lambda t: t.replace("d_mm = 400", 'd_mm = "400"'), "joint 1: d_mm must be a finite number"),
        (
            lambda t: t.replace('convention = "dh"', 'convention = "dh"\nexpansion_per_k = 23'),
            "expansion_per_k = 23 is outside 1e-06..5e-05 per K",
        ),
        (
            lambda t: t.replace('convention = "dh"', 'convention = "dh"\nexpansion_per_k = 5e-7'),
            "outside 1e-06..5e-05 per K",
        ),
        (
            lambda t: t.replace('convention = "dh"', 'convention = "dh"\nexpansion_per_k = "2.3e-5"'),
            "expansion_per_k must be a finite number",
        ),
    ],
)
def test_a_bad_robot_file_is_named_with_what_to_fix(tmp_path, edit, message):
    path = tmp_path / "bad.toml"
    path.write_text(edit((ROBOT_DIR / "kr6r900.toml").read_text()))
    with pytest.raises(ValueError) as exc:
        load_robot_file(path)
    assert str(path) in str(exc.value) and message in str(exc.value)


# ------------------------------------------------------------------------------------ modified DH (Craig)

# The KR 6 R900 of the built-in DH file, written as Craig's table by hand: row i holds the link before
# axis i (alpha_{i-1}, a_{i-1}) and joint i's own (d_i, theta_i); beta on row 3, between parallel axes 2, 3.
KR6_MDH = """
name = "kr6r900_mdh"
convention = "modified_dh"
[[joint]]
alpha_deg = 0
a_mm = 0
d_mm = 400
limits_deg = [-170, 170]
[[joint]]
alpha_deg = -90
a_mm = 25
d_mm = 0
limits_deg = [-190, 45]
[[joint]]
alpha_deg = 0
a_mm = 455
d_mm = 0
theta_offset_deg = -90
hayati_beta = true
limits_deg = [-120, 156]
[[joint]]
alpha_deg = -90
a_mm = 35
d_mm = 420
limits_deg = [-185, 185]
[[joint]]
alpha_deg = 90
a_mm = 0
d_mm = 0
limits_deg = [-120, 120]
[[joint]]
alpha_deg = -90
a_mm = 0
d_mm = 80
limits_deg = [-350, 350]
"""


def _tx(a):
    T = np.eye(4)
    T[0, 3] = a
    return T


def _tz(d):
    T = np.eye(4)
    T[2, 3] = d
    return T


def _rot(R):
    T = np.eye(4)
    T[:3, :3] = R
    return T


def craig_tool_point(rows, q, p_tool, beta=None):
    """Tool point by Craig's product written out: Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta_{i-1}) Rz(q_i + theta_i)
    Tz(d_i) per row; rows (n, 4) = (alpha, a, theta, d) in SI, beta (n,) on the rows' prefix."""
    from hil.geometry.se3 import rot_x, rot_y, rot_z

    beta = np.zeros(len(rows)) if beta is None else beta
    out = []
    for qk in np.atleast_2d(q):
        T = np.eye(4)
        for (al, a, th, d), b, qi in zip(rows, beta, qk, strict=True):
            T = T @ _rot(rot_x(al)) @ _tx(a) @ _rot(rot_y(b)) @ _rot(rot_z(qi + th)) @ _tz(d)
        out.append(T[:3, :3] @ p_tool + T[:3, 3])
    return np.array(out)


def test_an_mdh_file_and_its_dh_file_give_the_same_robot(tmp_path):
    (tmp_path / "kr6_mdh.toml").write_text(KR6_MDH)
    mdh, dh = load_robot_file(tmp_path / "kr6_mdh.toml"), get_robot("kr6r900")
    assert mdh.param_names == dh.param_names  # same identification parameters: a2 is Craig's a_2 too
    np.testing.assert_array_equal(mdh.joint_limits, dh.joint_limits)
    q = random_joints(dh, 300, np.random.default_rng(7))
    tool = np.array([0.03, -0.02, 0.11])
    np.testing.assert_allclose(tool_points(mdh, q, tool), tool_points(dh, q, tool), rtol=0, atol=1e-9)
    np.testing.assert_allclose(forward_kinematics(mdh, q), forward_kinematics(dh, q), rtol=0, atol=1e-9)


def test_an_mdh_table_loads_as_craigs_product_with_beta_where_the_parallel_axes_are(tmp_path):
    # A random Craig table (not a real robot), axes 3 and 4 parallel; FK against the product written out.
    rng = np.random.default_rng(11)
    alpha = np.r_[0.0, rng.uniform(-150, 150, 2), 0.0, rng.uniform(-150, 150, 2)]
    a = np.r_[0.0, rng.uniform(-400, 400, 5)]
    d, theta = rng.uniform(-300, 300, 6), rng.uniform(-180, 180, 6)
    text = 'convention = "craig"\n' + "".join(
        f"[[joint]]\nalpha_deg = {alpha[i]:.17g}\na_mm = {a[i]:.17g}\nd_mm = {d[i]:.17g}\n"
        f"theta_offset_deg = {theta[i]:.17g}\n" + ("hayati_beta = true\n" if i == 3 else "")
        for i in range(6)
    )
    (tmp_path / "arm.toml").write_text(text)
    model = load_robot_file(tmp_path / "arm.toml")
    assert [n for n in model.param_names if n.startswith("beta")] == ["beta3"]
    rows = np.column_stack([np.deg2rad(alpha), a / 1e3, np.deg2rad(theta), d / 1e3])
    q, tool = rng.uniform(-np.pi, np.pi, (50, 6)), np.array([0.05, 0.02, 0.07])
    np.testing.assert_allclose(tool_points(model, q, tool), craig_tool_point(rows, q, tool), atol=1e-9)
    # Hayati's beta about the y axis where the normal from axis 3 meets axis 4 is the model's beta3.
    beta = np.zeros(6)
    beta[3] = 2e-3
    np.testing.assert_allclose(
        tool_points(model.with_errors({"beta3": 2e-3}), q, tool),
        craig_tool_point(rows, q, tool, beta),
        atol=1e-9,
    )


@pytest.mark.parametrize(
    ("name", "zero_flange_mm", "reach_mm"),
    [
        # LR Mate 200iD: flange at (50 + 335 + 80, 0, 330 + 330 + 35); data sheet reach 717 mm.
        ("lrmate200id", [465.0, 0.0, 695.0], 717.0),
        # IRB 4600-60/2.05: flange at (175 + 960 + 135, 0, 495 + 900 + 175); data sheet reach 2.05 m.
        ("irb4600", [1270.0, 0.0, 1570.0], 2050.0),
    ],
)
def test_mdh_builtins_match_their_data_sheets(name, zero_flange_mm, reach_mm):
    m = get_robot(name)
    assert m.n_joints == 6 and list(m.uses_beta) == [False, True, False, False, False, False]
    T0 = forward_kinematics(m, np.zeros(6))[0]
    np.testing.assert_allclose(T0[:3, 3] * 1e3, zero_flange_mm, atol=1e-9)
    np.testing.assert_allclose(T0[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)  # the flange faces forward
    # Reach: the farthest the wrist centre (axis 5, d6 behind the flange) gets from axis 1 over arm joints.
    q2, q3 = np.meshgrid(np.deg2rad(np.arange(60.0, 120.0, 0.2)), np.deg2rad(np.arange(-120.0, -60.0, 0.2)))
    q = np.zeros((q2.size, 6))
    q[:, 1], q[:, 2] = q2.ravel(), q3.ravel()
    T = forward_kinematics(m, q)
    wrist = T[:, :3, 3] - m.d[5] * T[:, :3, 2]
    assert np.hypot(wrist[:, 0], wrist[:, 1]).max() * 1e3 == pytest.approx(reach_mm, abs=1.0)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("alpha_deg = -90\na_mm = 50", "alpha_deg = -90\na_m = 50"), "unknown key(s) ['a_m']"),
        (lambda t: t.replace("alpha_deg = 0\na_mm = 0\nd_mm = 330", "alpha_deg = 0\na_mm = 25\nd_mm = 330"),
         "joint 1: a_mm = 25, alpha_deg = 0; in a modified-DH table the first row's a_mm and alpha_deg"),
        (lambda t: t.replace("hayati_beta = true\n", "").replace("a_mm = 35", "a_mm = 35\nhayati_beta = true"),
         "joint 4: hayati_beta = true but alpha_deg = -90: beta is for parallel axes i-1 and i"),
        (lambda t: t.replace("d_mm = 330\n", "d_mm = 330\nhayati_beta = true\n", 1),
         "joint 1: hayati_beta on the first row"),
        (lambda t: t.replace("hayati_beta = true", 'hayati_beta = "yes"'), "hayati_beta must be true or false"),
        (lambda t: t.replace('convention = "mdh"', 'convension = "mdh"'), "unknown key(s) ['convension']"),
        (lambda t: t.replace('convention = "mdh"', 'convention = "modified"'),
         "convention 'modified' is not supported; write convention = one of 'dh', 'standard_dh', 'mdh'"),
        (lambda t: t.replace("limits_deg = [-100, 145]", "limits_deg = [-100]"), "joint 2: limits_deg must be"),
    ],
)  # fmt: skip
def test_a_bad_mdh_file_is_named_with_the_key_and_what_to_fix(tmp_path, edit, message):
    text = (ROBOT_DIR / "lrmate200id.toml").read_text()
    assert edit(text) != text
    path = tmp_path / "bad.toml"
    path.write_text(edit(text))
    with pytest.raises(ValueError) as exc:
        load_robot_file(path)
    assert str(path) in str(exc.value) and message in str(exc.value)


def test_calibrate_and_diagnose_take_an_mdh_robot_file(tmp_path, capsys):
    """`hil calibrate/diagnose --robot my.toml` on a simulated LR Mate 200iD campaign with hidden
    geometric errors: the calibrated model predicts held-out poses to the noise, the nominal one is mm off."""
    text = (
        (ROBOT_DIR / "lrmate200id.toml").read_text().replace('name = "lrmate200id"', 'name = "cell7_fanuc"')
    )
    (tmp_path / "fanuc.toml").write_text(text)
    nominal = load_robot_file(tmp_path / "fanuc.toml")
    rng = np.random.default_rng(5)
    true = nominal.with_errors(
        {n: rng.normal(0, 2e-4 if n[0] in "ad" else 3e-4) for n in nominal.param_names}
    )
    T = make_transform(Rotation.from_rotvec([0.0, -0.05, 1.2]).as_matrix(), [1.8, 0.4, -0.3])
    tool = np.array([0.01, -0.02, 0.06])
    mid, half = nominal.joint_limits.mean(axis=1), 0.35 * np.ptp(nominal.joint_limits, axis=1)
    q = rng.uniform(mid - half, mid + half, (260, 6))
    p_true = measured_point(true, q, T, tool)
    p = p_true + rng.normal(0, 10e-6, p_true.shape)
    make_dataset(q[:200], p[:200]).to_csv(tmp_path / "train.csv", index=False)
    make_dataset(q[200:], p[200:]).to_csv(tmp_path / "val.csv", index=False)

    def hil(*args):  # in this process: what is tested is the robot file, not the interpreter's start
        out = run_hil(*args, cwd=tmp_path, capsys=capsys)
        assert out.returncode == 0, out.stderr
        return out

    # the file declares FANUC's J2/J3 coupling: the data says its joints are already the kinematic ones
    hil(
        "calibrate", "train.csv", "--robot", "fanuc.toml", "--joint-convention", "kinematic", "-o", "kin.json"
    )
    assert json.loads((tmp_path / "kin.json").read_text())["info"]["run"]["robot"] == "cell7_fanuc"
    pred = CalibratedModel.load(tmp_path / "kin.json").predict(pd.read_csv(tmp_path / "val.csv"))
    rms = np.sqrt(np.mean(np.sum((pred - p_true[200:]) ** 2, axis=1)))
    nominal_rms = np.sqrt(
        np.mean(np.sum((measured_point(nominal, q[200:], T, tool) - p_true[200:]) ** 2, axis=1))
    )
    assert rms < 0.02e-3 and nominal_rms > 0.5e-3  # errors recovered to the 10 um noise; they were > 0.5 mm

    hil(
        "diagnose", "train.csv", "--robot", "fanuc.toml", "--joint-convention", "kinematic", "--validate",
        "val.csv", "--json", "report.json",
    )  # fmt: skip
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["run"]["robot"] == "cell7_fanuc"
    assert report["stages"][-1]["rms_mm"] < 0.03
