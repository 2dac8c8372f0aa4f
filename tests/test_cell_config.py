"""cell.toml: a good file loads in SI units; a broken one is refused with every problem and its key."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hil.runner.cell_config import CellConfigError, format_cell_toml, load_cell_config, parse_cell_config
from tests.cell_fixtures import sim_cell_toml
from tests.cli_in_process import run_hil


def test_simulated_cell_config_loads_in_si_units(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text(sim_cell_toml())
    config = load_cell_config(path)
    assert config.robot_model == "ur10" and config.robot_host == "127.0.0.9"
    assert config.nests_flange_m.shape == (3, 3) and np.allclose(
        config.nests_flange_m[0], [0.03, -0.02, 0.11]
    )
    assert np.all(config.envelope.box_max_m > config.envelope.box_min_m)
    assert 1.0 < np.linalg.norm(config.p_base_tracker_m) < 4.0
    assert config.simulator_control == "127.0.0.9:4000"
    assert config.robot_mapping()["host"] == "127.0.0.9"
    # what is written is what is read
    again = parse_cell_config(tomllib.loads(format_cell_toml(tomllib.loads(sim_cell_toml()))))
    assert np.allclose(again.p_base_tracker_m, config.p_base_tracker_m)


def test_the_robot_may_be_a_robot_file_beside_the_cell_file(tmp_path):
    """A cell's own robot definition (here the UR10's file with d1 1 mm longer), relative to cell.toml."""
    from hil.geometry.robots import ROBOT_DIR, get_robot

    text = (ROBOT_DIR / "ur10.toml").read_text()
    (tmp_path / "our_ur10.toml").write_text(
        text.replace('name = "ur10"', 'name = "our_ur10"').replace("d_mm = 127.3", "d_mm = 128.3", 1)
    )
    path = tmp_path / "cell.toml"
    path.write_text(sim_cell_toml().replace('model = "ur10"', 'model = "our_ur10.toml"'))
    config = load_cell_config(path)
    assert config.nominal.name == "our_ur10"
    assert np.isclose(config.nominal.d[0] - get_robot("ur10").d[0], 0.001)
    path.write_text(sim_cell_toml().replace('model = "ur10"', 'model = "missing.toml"'))
    with pytest.raises(CellConfigError, match=r"robot.model: robot file not found: .*missing.toml"):
        load_cell_config(path)


def test_every_problem_is_reported_with_its_key():
    data = tomllib.loads(sim_cell_toml())
    del data["robot"]["host"]
    data["robot"]["model"] = "ur99"
    data["robot"]["joint_sped"] = 1.0  # a typo
    data["tracker"]["meas_time_s"] = -1
    data["tracker"]["position_base_mm"] = [10, 0]
    data["tool"]["nests_flange_mm"] = [[30, -20]]
    data["envelope"]["box_min_mm"] = [0, 0, 2000]
    data["envelope"]["joint_max_deg"] = [400] * 6
    data["rig"] = {"x": 1}
    with pytest.raises(CellConfigError) as info:
        parse_cell_config(data)
    text = str(info.value)
    for key in (
        "robot.host: missing", "robot.model: unknown robot 'ur99'", "robot.joint_sped: unknown setting",
        "tracker.meas_time_s: must be positive", "tracker.position_base_mm: must be a list of 3",
        "tool.nests_flange_mm", "envelope.box_max_mm", "[rig]: unknown section",
    ):  # fmt: skip
        assert key in text, key
    assert len(info.value.problems) >= 8


def test_joint_limits_beyond_the_robot_and_a_tracker_on_the_base_axis_are_refused():
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["joint_max_deg"] = [400] * 6
    data["tracker"]["position_base_mm"] = [0, 100, 0]
    with pytest.raises(CellConfigError) as info:
        parse_cell_config(data)
    assert "beyond the robot's own limits" in str(info.value)
    assert "at least 300 mm from the robot's base axis" in str(info.value)


def test_cell_check_command(tmp_path, capsys):
    good = tmp_path / "cell.toml"
    good.write_text(sim_cell_toml())
    ok = run_hil("cell", "check", str(good), cwd=tmp_path, capsys=capsys)
    assert ok.returncode == 0 and "the configuration is valid" in ok.stdout and "ur10" in ok.stdout
    # the collision checks are on by default, with their margins and the body's source
    assert "collisions checked: 10 mm between links, 50 mm from the tracker" in ok.stdout
    # the simulated cell runs at full speed; a new cell (the key left out) at reduced speed until the operator
    # says otherwise, and the check says how
    assert "full speed ([motion] reduced_speed = false)" in ok.stdout
    new = tmp_path / "new.toml"
    new.write_text(sim_cell_toml().replace("reduced_speed = false\n", "", 1))
    slow = run_hil("cell", "check", str(new), cwd=tmp_path, capsys=capsys)
    assert slow.returncode == 0 and "reduced speed, 25 % of the joint and linear speeds" in slow.stdout
    assert f"set [motion] reduced_speed = false in {new}" in slow.stdout
    # instruments that do not answer: no "OK" before the failures, each with a remedy in the user's terms
    down = run_hil("cell", "check", str(good), "--connect", cwd=tmp_path, capsys=capsys)
    assert down.returncode == 2 and "OK" not in down.stdout
    assert "2 of 2 instruments did not answer" in down.stderr and down.stderr.count("what to do:") == 2
    assert "recover()" not in down.stderr and "-- next" not in down.stderr
    missing = run_hil("cell", "check", str(tmp_path / "nowhere.toml"), cwd=tmp_path, capsys=capsys)
    assert missing.returncode == 2 and "hil sim --write-cell" in missing.stderr
    assert "fix each key" not in missing.stderr
    bad = tmp_path / "bad.toml"
    text = (
        sim_cell_toml()
        .replace("settle_s = ", "settle_s = -")
        .replace("socket://127.0.0.9:7000", "tracker-host")
    )
    bad.write_text(text)
    out = run_hil("cell", "check", str(bad), cwd=tmp_path, capsys=capsys)
    assert out.returncode == 2
    assert "motion.settle_s" in out.stderr and "tracker.url" in out.stderr and "what to do" in out.stderr
    broken = tmp_path / "broken.toml"
    broken.write_text("[robot\nmodel = ")
    out = run_hil("cell", "check", str(broken), cwd=tmp_path, capsys=capsys)
    assert out.returncode == 2 and "not valid TOML" in out.stderr and "broken.toml" in out.stderr
