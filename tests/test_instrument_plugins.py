"""Instruments plug in through the `hil.instruments` entry-point group: hil finds a driver shipped in a package
of its own, and a missing or wrong plug-in is a clear error that names it, before anything connects."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from hil.instruments.plugins import (
    GROUP,
    PluginError,
    cell_simulator,
    installed,
    load,
    robot_driver,
    tracker_driver,
)
from hil.runner.cell_config import format_cell_toml
from tests.cell_fixtures import sim_cell_toml

ROOT = Path(__file__).resolve().parents[1]

# A shop-floor team's own instruments, in a package of their own: one module and its installed metadata.
SHOP_MODULE = '''
"""A team's robot and tracker drivers (a stand-in: they report fixed states)."""
import numpy as np

from hil.instruments.robot import RobotState
from hil.instruments.tracker import TrackerState


class ShopRobot:
    def __init__(self, settings):
        self.version = "shop-arm 2.1 at " + settings["host"]

    def state(self):
        return RobotState(True, "RUNNING", "NORMAL", True, False, False, 0.0)

    def joints(self):
        return np.zeros(6)

    def close(self):
        pass


class ShopTracker:
    def __init__(self, settings):
        self.reflector = settings["reflector"] or 42

    def state(self):
        return TrackerState(True, True, True, reflector_id=self.reflector)

    def close(self):
        pass


class RobotDriver:
    kind = "robot"
    summary = "the shop's arm"

    def open(self, settings):
        return ShopRobot(settings)


class TrackerDriver:
    kind = "tracker"
    summary = "the shop's tracker"

    def open(self, settings):
        return ShopTracker(settings)


robot = RobotDriver()
tracker = TrackerDriver()
'''


@pytest.fixture
def shop_site(tmp_path) -> Path:
    """A folder that holds an installed distribution `shop-instruments` (module + dist-info), as pip would
    leave it in site-packages; on PYTHONPATH, importlib.metadata finds its entry points."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "shop_instruments.py").write_text(SHOP_MODULE)
    info = site / "shop_instruments-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: shop-instruments\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{GROUP}]\nshop_arm = shop_instruments:robot\nshop_tracker = shop_instruments:tracker\n"
    )
    return site


def _cell(tmp_path: Path, robot_driver_name: str | None, tracker_driver_name: str | None) -> Path:
    data = tomllib.loads(sim_cell_toml())
    data["robot"]["host"] = "127.254.254.254"  # nothing listens there: the UR driver could not connect
    if robot_driver_name:
        data["robot"]["driver"] = robot_driver_name
    if tracker_driver_name:
        data["tracker"]["driver"] = tracker_driver_name
    path = tmp_path / "cell.toml"
    path.write_text(format_cell_toml(data))
    return path


def _hil(*args: str, extra_path: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    paths = [str(ROOT)] + ([str(extra_path)] if extra_path else []) + [env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(p for p in paths if p)
    return subprocess.run(
        [sys.executable, "-m", "hil", *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_a_driver_package_from_outside_the_repository_is_found_and_used(tmp_path, shop_site):
    cell = _cell(tmp_path, "shop_arm", "shop_tracker")
    done = _hil("cell", "check", str(cell), "--connect", extra_path=shop_site)
    assert done.returncode == 0, done.stderr
    assert (
        "robot connected: controller shop-arm 2.1 at 127.254.254.254" in done.stdout
    )  # its settings reached it
    assert "robot joints inside the envelope's limits" in done.stdout
    assert "tracker connected: initialized True, target locked True, reflector 42" in done.stdout


def test_without_the_package_the_missing_plugin_is_named_before_anything_connects(tmp_path):
    cell = _cell(tmp_path, "shop_arm", None)
    done = _hil("cell", "check", str(cell), "--connect")
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "no instrument plug-in named 'shop_arm' is installed" in done.stderr
    assert "emscon, sim, ur" in done.stderr and "what to do: install the package" in done.stderr
    assert "robot connected" not in done.stdout


def test_the_repository_registers_its_drivers_and_the_simulated_cell():
    names = installed()
    assert {"ur", "emscon", "sim"} <= set(names)
    assert names["ur"].value == "drivers.ur:plugin" and names["sim"].value == "fakes.plugin:plugin"
    assert robot_driver().kind == "robot" and tracker_driver().kind == "tracker"
    assert cell_simulator().kind == "simulator"


def test_a_plugin_of_another_kind_is_refused_with_its_kind():
    with pytest.raises(PluginError, match="'emscon' .* is a tracker, not a robot"):
        load("emscon", "robot")
    with pytest.raises(PluginError, match="no instrument plug-in named 'kuka_rsi'"):
        robot_driver("kuka_rsi")


def test_a_plugin_that_fails_to_import_is_named(tmp_path):
    site = tmp_path / "site"
    (site / "broken_driver-0.1.dist-info").mkdir(parents=True)
    (site / "broken_driver-0.1.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: broken-driver\nVersion: 0.1\n"
    )
    (site / "broken_driver-0.1.dist-info" / "entry_points.txt").write_text(
        f"[{GROUP}]\nbroken = broken_driver:plugin\n"
    )
    (site / "broken_driver.py").write_text("raise ImportError('needs the vendor SDK')\n")
    code = textwrap.dedent(
        """
        from hil.instruments.plugins import PluginError, robot_driver
        try:
            robot_driver("broken")
        except PluginError as exc:
            print(exc.message)
        """
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(site)]))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert (
        "'broken' (broken_driver:plugin) failed to load: ImportError: needs the vendor SDK" in done.stdout
    ), done.stderr
