"""The simulated cell as a process (`python -m fakes.sim`, `hil sim`): its ready line, its control channel, a clean exit
on SIGINT/SIGTERM, and a started cell that a Ctrl-C leaves to its starter."""

from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fakes import launch
from fakes.control_client import ControlClient, ControlError
from fakes.launch import (
    EXIT_ADDRESS_IN_USE,
    exit_status,
    random_loopback_host,
    sim_cell,
    start_cell,
    stop_cell,
    stop_process,
)

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cell():
    with sim_cell(robot="ur5e", seed=7, time_scale=2.0) as running:
        yield running


@pytest.mark.timeout(20)
def test_ready_line_names_every_server(cell):
    robot = cell.info["robot"]
    assert robot["host"] == cell.host and robot["model"] == "ur5e"
    assert (robot["rtde_port"], robot["dashboard_port"]) == (30004, 29999)
    assert robot["personality"] == "eseries" and robot["frequency_hz"] == 500.0
    host, port = cell.info["control"].rsplit(":", 1)
    assert host == cell.host and int(port) > 0
    assert cell.info["tracker"]["url"] == f"socket://{cell.host}:7000"
    for port in (30004, 29999, 30001, 30002, 30003, 7000):
        socket.create_connection((cell.host, port), timeout=2).close()


@pytest.mark.timeout(20)
def test_control_channel_commands(cell):
    control = cell.control
    assert "robot.fault" in control.call("help")
    truth = control.call("ground_truth")
    assert isinstance(truth, dict) and truth
    t0 = control.call("ping")["time_s"]
    assert control.call("set_time_scale", value=4.0) == 4.0
    assert control.call("time_scale") == 4.0
    deadline = time.monotonic() + 5
    while control.call("ping")["time_s"] <= t0:  # the clock ticks between requests
        assert time.monotonic() < deadline
    placed = control.call("place_smr", smr_id=1, kind="nest", index=2)
    assert len(placed["center_tracker_m"]) == 3
    assert control.call("smr_location", smr_id=1)["kind"] == "nest"
    state = control.call("cell.state")
    assert np.shape(state["T_base_flange_true"]) == (4, 4)
    with pytest.raises(ControlError, match="unknown command"):
        control.call("no.such.command")
    with pytest.raises(ControlError, match="unknown fault"):
        control.call("robot.fault", kind="meteor")
    with pytest.raises(ControlError, match="time scale"):
        control.call("set_time_scale", value=-1)
    # a malformed line gets an error reply and the channel keeps working
    host, port = cell.info["control"].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=2) as sock:
        sock.sendall(b"this is not json\n")
        assert json.loads(sock.makefile().readline())["ok"] is False
    with ControlClient(cell.info["control"]) as again:
        assert again.call("time_scale") == 4.0


@pytest.mark.timeout(30)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_exits_cleanly_on_signals(sig):
    """`python -m fakes.sim` as a user starts it: Ctrl-C or SIGTERM ends it cleanly."""
    args = [sys.executable, "-m", "fakes.sim", "--host", random_loopback_host(), "--robot", "ur10"]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        assert json.loads(process.stdout.readline())["robot"]["model"] == "ur10"  # ready
        process.send_signal(sig)
        assert process.wait(10) == 0
    finally:
        stop_process(process)


@pytest.mark.timeout(30)
def test_a_started_cell_outlives_a_ctrl_c_and_its_starter_stops_it():
    """A cell started for a program (fakes.launch: hil demo, the tests) stands for a controller and a tracker:
    a Ctrl-C in the terminal, which reaches the whole process group, leaves it running so the program can
    still stop the robot and record the interruption; the program stops it with SIGTERM."""
    cell = start_cell(robot="ur10", time_scale=1.0)
    try:
        cell.process.send_signal(signal.SIGINT)
        with pytest.raises(subprocess.TimeoutExpired):  # a cell that took it exits within milliseconds
            cell.process.wait(1.0)
        assert cell.control.call("time_scale") == 1.0  # still answering after the Ctrl-C
        cell.process.send_signal(signal.SIGTERM)
        assert cell.process.wait(10) == 0
    finally:
        stop_cell(cell)


@pytest.mark.timeout(150)
def test_second_cell_on_a_taken_address_fails_clearly(cell):
    # the second process exits as soon as it finds the address taken; the wait only bounds a loaded start-up
    with pytest.raises(RuntimeError, match="address in use"):
        start_cell(host=cell.host, ready_timeout_s=120)


@pytest.mark.timeout(60)
def test_a_start_whose_address_is_taken_moves_to_another(monkeypatch):
    """A cell started on an address of its own choosing (hil demo's first, the tests') that finds it taken
    exits with EXIT_ADDRESS_IN_USE, and the start tries another address."""
    taken = random_loopback_host()
    hosts = iter([taken])
    monkeypatch.setattr(launch, "random_loopback_host", lambda: next(hosts, None) or random_loopback_host())
    with socket.socket() as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind((taken, 30004))  # the RTDE port, the first the cell binds
        holder.listen()
        with sim_cell(robot="ur10", time_scale=10.0) as cell:
            assert cell.host != taken and cell.control.call("time_scale") == 10.0
    assert next(hosts, None) is None  # the taken address was tried first


@pytest.mark.timeout(30)
def test_the_exit_status_of_a_child_that_ended_its_output_first_is_read_not_lost():
    """A child's stdout reaches its end a moment before it has exited: a poll() then still reads None.
    Held in that moment here (output closed, the child waiting on its stdin), the status is still read."""
    code = f"import os, sys; os.close(1); sys.stdin.read(); raise SystemExit({EXIT_ADDRESS_IN_USE})"
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.read() == b""  # the end of its output
        assert child.poll() is None  # not exited yet: what a poll() here used to take for the status
        child.stdin.close()  # let it exit
        assert exit_status(child) == EXIT_ADDRESS_IN_USE
    finally:
        stop_process(child)


@pytest.mark.timeout(40)
def test_hil_sim_is_the_same_cell_and_writes_its_cell_config(tmp_path):
    """`hil sim` takes the options of `python -m fakes.sim` and adds --write-cell (the runner's cell.toml)."""
    cell_toml = tmp_path / "cell.toml"
    host = random_loopback_host()
    args = [sys.executable, "-m", "hil", "sim", "--host", host, "--robot", "ur10e", "--seed", "3"]
    args += ["--time-scale", "5", "--effects", "none", "--write-cell", str(cell_toml)]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        info = json.loads(process.stdout.readline())
        assert info["robot"]["host"] == host and info["robot"]["model"] == "ur10e" and info["seed"] == 3
        text = cell_toml.read_text()
        assert 'model = "ur10e"' in text and info["tracker"]["url"] in text
    finally:
        stop_process(process)
    assert process.returncode == 0


@pytest.mark.sim
@pytest.mark.timeout(90)
def test_write_cell_gives_a_config_that_checks_and_connects(tmp_path, capsys):
    """`hil sim --write-cell` writes the cell.toml of the cell it starts; `hil cell check --connect` reaches
    the robot (ur-rtde) and the tracker (emScon) it names."""
    import subprocess
    import sys

    from fakes.launch import random_loopback_host, stop_process

    cell_toml = tmp_path / "cell.toml"
    host = random_loopback_host()
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", "sim", "--host", host, "--time-scale", "5", "--write-cell", str(cell_toml)],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    try:
        ready = json.loads(process.stdout.readline())  # printed once every server listens
        assert ready["robot"]["host"] == host
        from tests.cli_in_process import run_hil  # in process: the cell, not the check, is the process here

        check = run_hil("cell", "check", str(cell_toml), "--connect", cwd=tmp_path, capsys=capsys)
        assert check.returncode == 0, check.stdout + check.stderr
        assert "robot connected" in check.stdout and "tracker connected" in check.stdout
        assert f'host = "{host}"' in cell_toml.read_text()
    finally:
        stop_process(process)


@pytest.mark.timeout(90)
@pytest.mark.parametrize(
    ("extra", "air_c", "monitor"),
    [(("--tracker-air-c", "12.5"), 12.5, 1), (("--no-weather-monitor",), 20.0, 0)],
)
def test_the_tracker_options_reach_the_fake_tracker(extra, air_c, monitor):
    """--tracker-air-c: the station reads that air whatever the hall does (the tracker_scale rival of the
    arm's growth); --no-weather-monitor: the tracker has none and starts from the controller's default meteo."""
    from drivers.emscon import EmsconConfig, EmsconTracker

    running = start_cell(robot="ur10", seed=1, time_scale=2.0, extra_args=extra)
    try:
        with EmsconTracker(
            EmsconConfig(url=running.info["tracker"]["url"], command_timeout_s=10.0)
        ) as tracker:
            assert tracker.environment()[0] == pytest.approx(air_c)
            assert tracker.state().details["weather_monitor_status"] == monitor
    finally:
        stop_cell(running)


def test_bad_tracker_air_is_refused_before_the_cell_starts():
    from fakes.sim import SimOptionError, add_sim_arguments, sim_options

    parser = argparse.ArgumentParser()
    add_sim_arguments(parser)
    with pytest.raises(SimOptionError, match="degrees Celsius|outside"):
        sim_options(parser.parse_args(["--tracker-air-c", "293"]))  # kelvin given as Celsius
    with pytest.raises(
        SimOptionError, match="give one of them"
    ):  # a station's reading on a tracker without one
        sim_options(parser.parse_args(["--tracker-air-c", "18", "--no-weather-monitor"]))
    assert sim_options(parser.parse_args(["--tracker-air-c", "18"])).tracker_air_c == 18.0
    assert not sim_options(parser.parse_args(["--no-weather-monitor"])).weather_monitor
