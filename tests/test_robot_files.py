"""Robot definitions from TOML files: the built-ins are such files, and any serial 6R is one more."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hil.calibration import calibrate
from hil.dataset import make_dataset
from hil.kinematics import measured_point
from hil.robots import ROBOT_DIR, ROBOT_NAMES, get_robot, load_robot_file
from hil.se3 import make_transform


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
        (lambda t: t.replace('convention = "dh"', 'convention = "mdh"'), "convention 'mdh' is not supported"),
        (lambda t: t.replace("[[joint]]", "[[joint]", 1), "not a valid TOML"),
        (lambda t: t.replace("d_mm = 0\n", "d_m = 0\n", 1), "unknown key(s) ['d_m']"),
        (lambda t: t.replace("limits_deg = [-170, 170]", "limits_deg = [170, -170]"), "lower < upper"),
    ],
)
def test_a_bad_robot_file_is_named_with_what_to_fix(tmp_path, edit, message):
    path = tmp_path / "bad.toml"
    path.write_text(edit((ROBOT_DIR / "kr6r900.toml").read_text()))
    with pytest.raises(ValueError) as exc:
        load_robot_file(path)
    assert str(path) in str(exc.value) and message in str(exc.value)
