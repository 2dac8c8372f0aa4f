"""`hil tracker` (state / aim / measure as JSON) and the stand-alone fake tracker process."""

import argparse
import json
import os
import select
import signal
import subprocess
import sys

import numpy as np
import pytest

from drivers.emscon import EmsconConfig, EmsconTracker
from fakes.cell import SimCellConfig, SimulatedCell
from fakes.emscon_server import EmsconServer, EmsconServerConfig, ServerThread
from fakes.launch import stop_process
from hil.commands import tracker as tracker_command

pytestmark = [
    pytest.mark.sim,
    pytest.mark.timeout(60),
]  # starts a simulated cell or a fake server over sockets
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    tracker_command.add_parser(parser.add_subparsers())
    args = parser.parse_args(["tracker", *argv])
    return args.func(args)


def test_hil_tracker_aims_measures_and_prints_si_json(capsys):
    cell = SimulatedCell(SimCellConfig(seed=3))
    server = EmsconServer(cell, config=EmsconServerConfig(init_delay_s=0.01))
    with ServerThread(server):
        p = cell.smr_center_tracker(3)
        argv = ["--url", server.url, "--shots", "3", "--meas-time", "0.01", "--wire-units", "mm"]
        assert _run([*argv, "--aim", *map(str, p + 0.005)]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["state"]["target_locked"] and out["state"]["tracker_info"]["name"] == "AT901-LR"
        m = out["measurement"]
        assert np.linalg.norm(np.array([m["x_m"], m["y_m"], m["z_m"]]) - p) < 1e-3
        assert m["shots"] == 3 and m["rejected_shots"] == []
        assert _run(["--url", server.url, "--aim", "0", "0", "-3"]) == 1  # nothing to lock there
        out = json.loads(capsys.readouterr().out)
        assert out["error"]["type"] == "NoTargetError"


def test_standalone_fake_tracker_process():
    env = {**os.environ, "PYTHONPATH": ROOT}
    args = [sys.executable, "-m", "fakes.emscon_server", "--port", "0", "--lock", "2", "--pty"]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, env=env, cwd=ROOT)
    try:
        ready, _, _ = select.select([process.stdout], [], [], 20)
        assert ready, "the fake tracker did not announce itself"
        info = json.loads(process.stdout.readline())["tracker"]
        for url in (info["url"], info["pty"]):
            with EmsconTracker(EmsconConfig(url=url, meas_time_s=0.01)) as tracker:
                assert tracker.state().target_locked
                assert np.all(np.isfinite(tracker.measure(shots=2).p_tracker_m))
    finally:
        stop_process(process, signal.SIGINT)
