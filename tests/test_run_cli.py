"""`hil run` refuses a broken config, bad options and out-of-envelope plans before connecting to anything;
grid plans in random order and from both directions."""

from __future__ import annotations

import tomllib

import numpy as np

from hil.runner.cell_config import format_cell_toml, parse_cell_config
from procedures import grid_sampling
from tests.cell_fixtures import sim_cell_toml
from tests.cli_in_process import run_hil

# Nothing listens there: a command that tried to connect would fail with a connection error instead.
OFFLINE_HOST = "127.254.254.254"


def _run(tmp_path, cell_text: str, *args: str, capsys):
    """`hil run` in process (the entry point as a process: test_campaign_faults)."""
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text.replace("127.0.0.9", OFFLINE_HOST))
    command = ["run", *args[:1], "--cell", str(cell), "--campaign", str(tmp_path / "c.sqlite"), *args[1:]]
    return run_hil(*command, cwd=tmp_path, capsys=capsys)


def test_a_broken_config_is_refused_before_anything_connects(tmp_path, capsys):
    text = sim_cell_toml().replace("[envelope]\n", "[envelope]\nbox_size_mm = 3\n")
    done = _run(tmp_path, text, "grid_sampling", capsys=capsys)
    assert done.returncode == 2
    assert "envelope.box_size_mm: unknown setting" in done.stderr and "what to do" in done.stderr
    assert not (tmp_path / "c.sqlite").exists()


def test_a_sampling_box_outside_the_envelope_is_refused_before_any_motion(tmp_path, capsys):
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["box_min_mm"] = [-1500.0, -1500.0, 300.0]  # nothing may go below z = 300 mm
    done = _run(
        tmp_path,
        format_cell_toml(data),
        "grid_sampling",
        "--box-min-mm",
        "200",
        "200",
        "0",
        "--box-max-mm",
        "700",
        "700",
        "250",
        capsys=capsys,
    )
    assert done.returncode == 2
    assert "inside the envelope" in done.stderr and "what to do" in done.stderr, done.stderr
    assert not (tmp_path / "c.sqlite").exists()


def test_an_unreachable_robot_is_a_clear_error(tmp_path, capsys):
    done = _run(tmp_path, sim_cell_toml(), "registration", capsys=capsys)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 2, done.stderr  # the cause, then what to do: once each
    assert lines[0].startswith("hil run: cannot connect to the robot") and OFFLINE_HOST in lines[0]
    assert "what to do:" in lines[1] and "robot.host" in lines[1] and "run the same command again" in lines[1]
    assert "recover()" not in done.stderr and "-- next" not in done.stderr  # no Python API in CLI terms
    assert not (tmp_path / "c.sqlite").exists()  # a failed start leaves no empty campaign
    assert "reduced speed" not in done.stdout  # the simulated cell's config runs at full speed


def test_a_new_cell_says_it_moves_at_reduced_speed_before_anything_moves(tmp_path, capsys):
    new_cell = sim_cell_toml().replace("reduced_speed = false\n", "", 1)  # the key left out: a new cell
    done = _run(tmp_path, new_cell, "registration", capsys=capsys)
    assert done.returncode == 2 and "cannot connect to the robot" in done.stderr  # nothing there to move
    assert done.stdout.startswith("hil run: reduced speed, 25 % of the joint and linear speeds")
    assert "set [motion] reduced_speed = false in" in done.stdout


def test_bad_procedure_options_are_refused(tmp_path, capsys):
    done = _run(tmp_path, sim_cell_toml(), "grid_sampling", "--step-mm", "5", capsys=capsys)
    assert done.returncode == 2 and "--step-mm 5" in done.stderr and "20..500 mm" in done.stderr
    done = _run(tmp_path, sim_cell_toml(), "tool_fit", "--check-poses", "3", capsys=capsys)
    assert done.returncode == 2 and "--check-poses 3" in done.stderr and "at least 6" in done.stderr
    assert not (tmp_path / "c.sqlite").exists()


def test_a_flag_in_another_unit_or_an_unknown_procedure_is_refused(tmp_path, capsys):
    done = _run(
        tmp_path, sim_cell_toml(), "grid_sampling", "--step-m", "0.1", capsys=capsys
    )  # metres, not millimetres
    assert done.returncode == 2 and "use --step-mm" in done.stderr and "20..500 mm" in done.stderr
    done = _run(tmp_path, sim_cell_toml(), "grid_sampling", "--tilt-rad", "0.2", capsys=capsys)
    assert done.returncode == 2 and "use --tilt-deg" in done.stderr
    done = _run(tmp_path, sim_cell_toml(), "no_such_procedure", capsys=capsys)
    assert done.returncode == 2 and "registration" in done.stderr and "grid_sampling" in done.stderr
    assert not (tmp_path / "c.sqlite").exists()


def test_help_lists_every_procedure_and_its_declared_parameters(tmp_path, capsys):
    listing = run_hil("run", "--help", cwd=tmp_path, capsys=capsys)
    for name in ("registration", "tool_fit", "grid_sampling", "pseudo_target"):
        assert name in listing.stdout
    assert "flange frame" in listing.stdout  # tool_fit's purpose
    own = run_hil("run", "grid_sampling", "--help", cwd=tmp_path, capsys=capsys)
    assert "--step-mm MM" in own.stdout and "20..500 mm; default 100" in own.stdout
    assert "--tilt-deg DEG" in own.stdout


def test_random_order_and_both_directions():
    config = parse_cell_config(tomllib.loads(sim_cell_toml()))
    travel = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0)
    shuffled = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0, order="random")
    assert sorted(p.point_id for p in travel.poses) == sorted(p.point_id for p in shuffled.poses)
    assert [p.point_id for p in travel.poses] != [p.point_id for p in shuffled.poses]
    assert shuffled.estimated_duration_s() > travel.estimated_duration_s()
    both = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0, both_directions=True)
    assert len(both.poses) == 2 * len(travel.poses)
    pose = both.poses[0]
    below = grid_sampling.approach_pose(pose.point_id, pose.q_rad)
    above = grid_sampling.approach_pose(both.poses[1].point_id, both.poses[1].q_rad)
    assert np.all(below < pose.q_rad) and np.all(above > both.poses[1].q_rad)
