"""The cell configuration (`cell.toml`): robot, tracker, tool, safety envelope and motion settings.

Lengths in the file are millimetres and angles degrees, named in the keys (`_mm`, `_deg`); everything is
converted to SI here. `load_cell_config` checks the whole file and reports every problem with its key and
what to fix, before anything connects or moves.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from hil.geometry.body import ArmBody
from hil.geometry.collision import CellBodies, KeepOutBox
from hil.geometry.coupling import JointConvention, JointCoupling
from hil.geometry.kinematics import KinematicModel
from hil.geometry.robots import (
    ROBOT_NAMES,
    get_robot,
    is_robot_file,
    robot_body,
    robot_coupling,
    robot_file_path,
    robot_from_text,
    with_file_path,
)
from hil.instruments.plugins import DEFAULT_ROBOT_DRIVER, DEFAULT_TRACKER_DRIVER
from hil.runner.envelope import Envelope

SMR_RADIUS_MM = 19.05  # 1.5" sphere
# The cell's collision margins: to the tracker and the keep-out boxes (what a tape measure and the nominal
# model leave unknown: tens of mm), and between the arm's own links (the nominal model is good to a few mm;
# the UR wrist housings face each other across d5 with ~20 mm between their capsules, so more would refuse
# every pose).
CLEARANCE_MM = 50.0
SELF_CLEARANCE_MM = 10.0
# The tracker's keep-out: a vertical capsule through its position, 250 mm above (the head) and 1500 mm below
# (the stand), of this radius: a Leica AT9x0 head is about 230 mm wide and 480 mm tall (Leica's data sheet);
# 300 mm covers the head turning and the top of the stand. Give your own with tracker.keep_out_radius_mm.
TRACKER_KEEP_OUT_RADIUS_MM = 300.0
TRACKER_HEAD_ABOVE_M, TRACKER_STAND_BELOW_M = 0.25, 1.5
# The tool as a capsule from the flange to each nest: a 1.5" SMR in its nest on a holder about that wide.
TOOL_RADIUS_MM = 25.0
# The first motions of a new cell run at this fraction of the configured speeds until the operator confirms.
REDUCED_SPEED_FRACTION = 0.25
DEFAULT_JOINT_SPEED_RAD_S, DEFAULT_LINEAR_SPEED_M_S = 1.05, 0.25  # drivers.ur.URConfig's defaults

# Settings of the robot section that belong to the robot driver (drivers.ur.URConfig), passed through.
ROBOT_DRIVER_KEYS: tuple[str, ...] = (
    "joint_speed", "joint_accel", "linear_speed", "linear_accel", "max_joint_speed", "max_joint_accel",
    "max_linear_speed", "max_linear_accel", "connect_timeout_s", "connect_attempts", "settle_dwell_s",
    "settle_timeout_s", "stale_after_s", "move_timeout_margin_s", "reach_tolerance_rad",
    "recover_timeout_s", "power_on_at_connect",
)  # fmt: skip


class CellConfigError(ValueError):
    """A cell configuration with problems; `problems` lists each as 'key: what is wrong; what to do'."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        super().__init__(f"{source}: {len(problems)} problem(s):\n" + "\n".join(f"  - {p}" for p in problems))


@dataclass(frozen=True)
class CellConfig:
    """One robot cell as the runner sees it (SI units)."""

    robot_model: str
    robot_host: str
    robot_driver: dict[str, Any]  # drivers.ur.URConfig settings besides the host
    tracker_url: str
    tracker_reflector: str | None
    meas_time_s: float
    shots_per_point: int
    p_base_tracker_m: np.ndarray  # approximate tracker position in the robot base frame (plans facing poses)
    nests_flange_m: np.ndarray  # (K, 3) SMR nest centres on the tool, flange frame, from the drawing
    smr_radius_m: float
    hole_circle_radius_m: float
    hole7_radius_m: float
    hole_diameter_m: float
    envelope: Envelope
    settle_s: float
    q_home_rad: np.ndarray  # kinematic joints ([motion] home_deg: the controller's, converted when read)
    simulator_control: str | None = None  # control channel of a simulated cell (scripted operator)
    console_token: str | None = None  # [console] token: what `hil serve` asks of every request off loopback
    robot_file_text: str | None = None  # the robot definition file's text when robot_model is a file
    robot_driver_name: str = (
        DEFAULT_ROBOT_DRIVER  # robot.driver: the instrument plug-in that drives the robot
    )
    tracker_driver_name: str = DEFAULT_TRACKER_DRIVER  # tracker.driver: the plug-in that drives the tracker
    source: str = "cell.toml"
    raw: dict = field(default_factory=dict)
    drift_poses: int = 0  # [drift_monitor] poses: reference poses re-measured during a grid (0: none)
    drift_every_points: int = 0  # [drift_monitor] every_points: grid points between two reference rounds
    grid_orientation: str = "varied"  # [grid] orientation: "varied" (calibration) or "fixed" (the grid paper)
    grid_fixed_rpy_rad: np.ndarray | None = (
        None  # [grid] fixed_rpy_deg: the fixed tool orientation, base frame
    )
    reduced_speed: bool = True  # [motion] reduced_speed: new cell, speeds scaled until the operator confirms
    reduced_speed_fraction: float = REDUCED_SPEED_FRACTION
    bodies: CellBodies | None = (
        None  # the arm, tool, tracker and keep-outs, whether or not collisions are checked
    )
    cell_name: str = ""  # [cell] name: how the plant names this cell (a key of its campaigns)
    operator_name: str = ""  # [cell] operator: who runs it, unless hil run --operator-name says otherwise
    # [store] password_file: the shared campaign database's password (a postgresql:// --campaign), read at
    # connection time and never recorded; relative to the cell file's folder
    store_password_file: Path | None = None

    @property
    def coupling(self) -> JointCoupling | None:
        """How the robot's controller couples its joints (its robot file's [coupling]), None when it reports
        the kinematic joints: the session converts every move and reading at the robot's edge."""
        return self.envelope.coupling

    @cached_property
    def nominal(self) -> KinematicModel:
        """The nominal model of the configured robot (read once: planners and path checks ask per pose)."""
        return _nominal(self.robot_model, self.robot_file_text)

    def robot_mapping(self) -> dict[str, Any]:
        """Settings for drivers.ur.URConfig.from_mapping: the host and the driver keys; with
        `reduced_speed` on, the default joint and linear speeds scaled by `reduced_speed_fraction`."""
        mapping = {"host": self.robot_host, **self.robot_driver}
        if self.reduced_speed:
            joint = float(mapping.get("joint_speed", DEFAULT_JOINT_SPEED_RAD_S))
            linear = float(mapping.get("linear_speed", DEFAULT_LINEAR_SPEED_M_S))
            mapping["joint_speed"] = joint * self.reduced_speed_fraction
            mapping["linear_speed"] = linear * self.reduced_speed_fraction
        return mapping

    def speed_text(self) -> str:
        """How fast the robot moves, in the operator's words: a new cell's reduced speed and how to end it."""
        if self.reduced_speed:
            return (
                f"reduced speed, {100 * self.reduced_speed_fraction:g} % of the joint and linear speeds (a new "
                f"cell's first motions); once they look right, set [motion] reduced_speed = false in {self.source}"
            )
        return "full speed ([motion] reduced_speed = false)"

    def tracker_mapping(self) -> dict[str, Any]:
        """Settings for the tracker driver: its URL, measuring time and reflector."""
        return {"url": self.tracker_url, "meas_time_s": self.meas_time_s, "reflector": self.tracker_reflector}

    def snapshot(self) -> dict:
        """The configuration as read, for the campaign's station snapshot; `robot_definition` holds what
        rebuilds the nominal robot without the cell's files: the built-in name, or the robot file's
        resolved path and text (so the campaign describes itself)."""
        if self.robot_file_text is None:
            robot: dict[str, str] = {"model": self.robot_model}
        else:
            robot = {"model": self.robot_model, "file": self.robot_model, "file_text": self.robot_file_text}
        # the joints a session records are what the robot's controller reports (hil.geometry.coupling)
        return {
            "source": self.source,
            "cell": self.raw,
            "robot_definition": robot,
            "joint_convention": str(JointConvention.CONTROLLER),
        }


class _Reader:
    """Reads typed values from nested TOML tables and collects every problem instead of stopping at one."""

    def __init__(self, data: dict):
        self.data = data
        self.problems: list[str] = []
        self.used: dict[str, set[str]] = {}

    def table(self, name: str) -> dict:
        value = self.data.get(name, {})
        if not isinstance(value, dict):
            self.problems.append(f"[{name}]: must be a table; write it as a [{name}] section")
            return {}
        return value

    def get(self, section: str, key: str, kind: str, default: Any = None, required: bool = False) -> Any:
        self.used.setdefault(section, set()).add(key)
        table = self.table(section)
        full = f"{section}.{key}"
        if key not in table:
            if required:
                self.problems.append(f"{full}: missing; add it to the [{section}] section")
            return default
        value = table[key]
        if kind == "str" and not isinstance(value, str):
            self.problems.append(f"{full}: must be a string in quotes, got {value!r}")
            return default
        if kind in ("float", "positive", "nonneg"):
            if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
                self.problems.append(f"{full}: must be a number, got {value!r}")
                return default
            if kind == "positive" and value <= 0:
                self.problems.append(f"{full}: must be positive, got {value!r}")
                return default
            if kind == "nonneg" and value < 0:
                self.problems.append(f"{full}: must be zero or positive, got {value!r}")
                return default
            return float(value)
        if kind == "bool":
            if not isinstance(value, bool):
                self.problems.append(f"{full}: must be true or false, got {value!r}")
                return default
            return value
        if kind == "int" and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            self.problems.append(f"{full}: must be a whole number >= 1, got {value!r}")
            return default
        return value

    def vector(self, section: str, key: str, length: int, default: Any = None, required: bool = False):
        value = self.get(section, key, "any", default=None, required=required)
        if value is None:
            return None if default is None else np.asarray(default, float)
        arr = _numbers(value)
        if arr is None or arr.shape != (length,):
            self.problems.append(f"{section}.{key}: must be a list of {length} numbers, got {value!r}")
            return None if default is None else np.asarray(default, float)
        return arr

    def unknown_keys(self, known_extra: dict[str, tuple[str, ...]]) -> None:
        for section, table in self.data.items():
            if section not in SECTIONS:
                self.problems.append(f"[{section}]: unknown section; known: {', '.join(SECTIONS)}")
                continue
            if not isinstance(table, dict):
                continue
            allowed = self.used.get(section, set()) | set(known_extra.get(section, ()))
            for key in sorted(set(table) - allowed):
                self.problems.append(
                    f"{section}.{key}: unknown setting (a typo?); known: {', '.join(sorted(allowed))}"
                )


SECTIONS = (
    *("robot", "tracker", "tool", "envelope", "motion", "simulator", "drift_monitor", "grid"),
    *("console", "cell", "store"),
)

# [grid] orientation: every vertex in its own tool orientation facing the tracker (what a calibration wants:
# the wrist joints move), or one tool orientation at every vertex (the grid paper's setting).
GRID_ORIENTATIONS: tuple[str, ...] = ("varied", "fixed")


def _numbers(value: Any) -> np.ndarray | None:
    if not isinstance(value, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        return None
    arr = np.asarray(value, float)
    return arr if np.all(np.isfinite(arr)) else None


def _robot_model(
    r: _Reader, model: str | None, source: str
) -> tuple[str | None, str | None, KinematicModel | None]:
    """A built-in name (lower case), or a robot definition file relative to the cell file's folder and its
    text, with the nominal model read from it; Nones with the problem noted when it is neither."""
    if model is None:
        return None, None, None
    if is_robot_file(model):
        file = robot_file_path(model)  # a URDF's '#flange_link' aside
        path = file if file.is_absolute() else Path(source).parent / file
        try:
            text = path.read_text()
        except FileNotFoundError:
            r.problems.append(f"robot.model: robot file not found: {path}; check the path")
            return None, None, None
        except (OSError, UnicodeDecodeError) as exc:
            r.problems.append(
                f"robot.model: cannot read robot file {path} ({exc}); give a readable TOML or URDF file"
            )
            return None, None, None
        # resolved now: the snapshot must not depend on a later cwd
        resolved = with_file_path(model, path.resolve())
        try:
            return resolved, text, _nominal(resolved, text)
        except ValueError as exc:
            r.problems.append(f"robot.model: {exc}")
            return None, None, None
    if model.lower() not in ROBOT_NAMES:
        r.problems.append(
            f"robot.model: unknown robot {model!r}; choose one of {', '.join(ROBOT_NAMES)} or give a robot file (.toml, .urdf)"
        )
        return None, None, None
    return model.lower(), None, _nominal(model.lower(), None)


def _nominal(robot_model: str, robot_file_text: str | None) -> KinematicModel:
    """The nominal model: from the robot file's text when the cell names a file, else the built-in."""
    return (
        get_robot(robot_model) if robot_file_text is None else robot_from_text(robot_file_text, robot_model)
    )


def _coupling(model: str | None, robot_file_text: str | None) -> JointCoupling | None:
    """The robot's joint coupling when its controller couples its joints (hil.geometry.coupling), else None."""
    if model is None:
        return None
    coupling = robot_coupling(model, robot_file_text)
    return coupling if coupling is not None and coupling.coupled_rows() else None


def parse_cell_config(data: dict, source: str = "cell.toml") -> CellConfig:
    """Build and check a CellConfig from parsed TOML; raises CellConfigError listing every problem."""
    r = _Reader(data)
    model, robot_file_text, nominal = _robot_model(r, r.get("robot", "model", "str", required=True), source)
    coupling = _coupling(model, robot_file_text)
    host, driver = _read_robot_link(r)
    robot_driver_name = r.get("robot", "driver", "str", default=DEFAULT_ROBOT_DRIVER)
    n = nominal.n_joints if nominal else 6
    url, reflector, meas_time_s, shots, p_tracker_mm = _read_tracker(r)
    tracker_driver_name = r.get("tracker", "driver", "str", default=DEFAULT_TRACKER_DRIVER)
    nests_arr, smr_radius_mm, circle_mm, hole7_mm, hole_d_mm = _read_tool(r)
    box_min, box_max, jmin, jmax = _read_envelope(r, nominal, n)
    collisions = r.get("envelope", "collisions", "bool", default=True)
    clearance_mm = r.get("envelope", "clearance_mm", "nonneg", default=CLEARANCE_MM)
    self_clearance_mm = r.get("envelope", "self_clearance_mm", "nonneg", default=SELF_CLEARANCE_MM)
    keep_out = _read_keep_out(r)
    tracker_radius_mm = r.get("tracker", "keep_out_radius_mm", "nonneg", default=TRACKER_KEEP_OUT_RADIUS_MM)
    tool_radius_mm = r.get("tool", "capsule_radius_mm", "positive", default=TOOL_RADIUS_MM)
    body = _robot_body(r, model, robot_file_text)
    settle_s = r.get("motion", "settle_s", "nonneg", default=0.5)
    reduced_speed = r.get("motion", "reduced_speed", "bool", default=True)
    reduced_fraction = r.get("motion", "reduced_speed_fraction", "positive", default=REDUCED_SPEED_FRACTION)
    if reduced_fraction is not None and reduced_fraction > 1:
        r.problems.append(
            f"motion.reduced_speed_fraction: {reduced_fraction:g} is above 1; give a fraction of the speeds, e.g. 0.25"
        )
    home_rad = _read_home(r, nominal, n, coupling)
    simulator_control = r.get("simulator", "control", "str")
    console_token = r.get("console", "token", "str")
    drift_poses = r.get("drift_monitor", "poses", "int", default=0)
    drift_every = r.get("drift_monitor", "every_points", "int", default=0)
    if (drift_poses > 0) != (drift_every > 0):
        r.problems.append("[drift_monitor]: give both poses and every_points (or leave the section out)")
    grid_orientation, grid_fixed_rpy_deg = _read_grid(r)
    cell_name = r.get("cell", "name", "str", default="")
    operator_name = r.get("cell", "operator", "str", default="")
    password_file = r.get("store", "password_file", "str")
    r.unknown_keys({"robot": ROBOT_DRIVER_KEYS})
    if r.problems:
        raise CellConfigError(source, r.problems)
    assert (
        nests_arr is not None and model is not None and nominal is not None and body is not None
    )  # a missing or malformed one is one of r.problems
    bodies = cell_bodies(
        body,
        nominal,
        nests_arr,
        tool_radius_mm / 1e3,
        p_tracker_mm / 1e3,
        tracker_radius_mm / 1e3,
        keep_out,
        clearance_mm / 1e3,
        self_clearance_mm / 1e3,
    )
    envelope = Envelope(
        box_min / 1e3,
        box_max / 1e3,
        np.deg2rad(jmin),
        np.deg2rad(jmax),
        bodies if collisions else None,
        coupling,
    )
    assert home_rad is not None  # a malformed one is one of r.problems
    _check_home(envelope, nominal, home_rad, nests_arr, source)
    return CellConfig(
        robot_model=model,
        robot_host=host,
        robot_driver=driver,
        tracker_url=url,
        tracker_reflector=reflector,
        meas_time_s=meas_time_s,
        shots_per_point=shots,
        p_base_tracker_m=p_tracker_mm / 1e3,
        nests_flange_m=nests_arr,
        smr_radius_m=smr_radius_mm / 1e3,
        hole_circle_radius_m=circle_mm / 1e3,
        hole7_radius_m=hole7_mm / 1e3,
        hole_diameter_m=hole_d_mm / 1e3,
        envelope=envelope,
        settle_s=settle_s,
        q_home_rad=home_rad,
        simulator_control=simulator_control,
        console_token=console_token,
        robot_file_text=robot_file_text,
        robot_driver_name=robot_driver_name,
        tracker_driver_name=tracker_driver_name,
        source=source,
        raw=data,
        drift_poses=drift_poses,
        drift_every_points=drift_every,
        grid_orientation=grid_orientation,
        grid_fixed_rpy_rad=None if grid_fixed_rpy_deg is None else np.deg2rad(grid_fixed_rpy_deg),
        reduced_speed=reduced_speed,
        reduced_speed_fraction=reduced_fraction,
        bodies=bodies,
        cell_name=cell_name,
        operator_name=operator_name,
        store_password_file=None if password_file is None else Path(source).parent / password_file,
    )


def cell_bodies(
    body: ArmBody,
    nominal: KinematicModel,
    nests_flange_m: np.ndarray,
    tool_radius_m: float,
    p_base_tracker_m: np.ndarray,
    tracker_radius_m: float,
    keep_out: tuple[KeepOutBox, ...],
    margin_m: float,
    self_margin_m: float,
) -> CellBodies:
    """The arm's body with the tool (a capsule from the flange to each nest, in the last link's frame), the
    tracker's keep-out capsule (vertical through its position) and the keep-out boxes, with the margins."""
    L = np.asarray(nominal.T_last_flange, float)
    nests = np.atleast_2d(nests_flange_m) @ L[:3, :3].T + L[:3, 3]
    n = nominal.n_joints
    tool = body.with_capsules(
        [f"tool (nest {k + 1})" for k in range(len(nests))],
        np.full(len(nests), n),
        np.tile(L[:3, 3], (len(nests), 1)),
        nests,
        np.full(len(nests), tool_radius_m),
    )
    p = np.asarray(p_base_tracker_m, float)
    up = np.array([0.0, 0.0, 1.0])
    return CellBodies(
        tool,
        p - TRACKER_STAND_BELOW_M * up if tracker_radius_m > 0 else None,
        p + TRACKER_HEAD_ABOVE_M * up if tracker_radius_m > 0 else None,
        tracker_radius_m,
        keep_out,
        margin_m,
        self_margin_m,
    )


def _robot_body(r: _Reader, model: str | None, robot_file_text: str | None) -> ArmBody | None:
    """The robot's body from its file (capsules, or sized along its DH table); None with the problem noted."""
    if model is None:
        return None
    try:
        return robot_body(model, robot_file_text)
    except ValueError as exc:
        r.problems.append(f"robot.model: {exc}")
        return None


def _read_keep_out(r: _Reader) -> tuple[KeepOutBox, ...]:
    """[[envelope.keep_out]]: boxes the arm must not enter (name, min_mm, max_mm in the robot base frame)."""
    tables = r.get("envelope", "keep_out", "any", default=[])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        r.problems.append("envelope.keep_out: write each box as an [[envelope.keep_out]] table")
        return ()
    boxes = []
    for k, table in enumerate(tables, start=1):
        where = f"envelope.keep_out {k}"
        unknown = set(table) - {"name", "min_mm", "max_mm"}
        lo, hi = _numbers(table.get("min_mm")), _numbers(table.get("max_mm"))
        if unknown or lo is None or hi is None or lo.shape != (3,) or hi.shape != (3,):
            r.problems.append(
                f"{where}: give name, min_mm = [x, y, z] and max_mm = [x, y, z] (robot base frame, mm)"
                + (f"; unknown key(s) {sorted(unknown)}" if unknown else "")
            )
            continue
        if np.any(hi <= lo):
            r.problems.append(f"{where}: every coordinate of max_mm must exceed min_mm's")
            continue
        boxes.append(KeepOutBox(str(table.get("name", f"box {k}")), lo / 1e3, hi / 1e3))
    return tuple(boxes)


def _read_grid(r: _Reader) -> tuple[str, np.ndarray | None]:
    """[grid]: orientation ("varied" or "fixed") and the fixed tool orientation as roll, pitch, yaw (deg)."""
    orientation = r.get("grid", "orientation", "str", default="varied")
    if orientation not in GRID_ORIENTATIONS:
        r.problems.append(
            f"grid.orientation: {orientation!r} is not one of {', '.join(GRID_ORIENTATIONS)}; "
            '"varied" for a calibration, "fixed" for the grid paper\'s one orientation at every vertex'
        )
        orientation = "varied"
    rpy = r.vector("grid", "fixed_rpy_deg", 3)
    if rpy is not None and orientation != "fixed":
        r.problems.append(
            'grid.fixed_rpy_deg: only used with orientation = "fixed"; set that or remove the key'
        )
    return orientation, rpy


def _read_robot_link(r: _Reader) -> tuple[Any, dict]:
    """[robot] host and the driver settings (positive numbers; power_on_at_connect a flag)."""
    host = r.get("robot", "host", "str", required=True)
    driver = {k: v for k, v in r.table("robot").items() if k in ROBOT_DRIVER_KEYS}
    for key, value in driver.items():
        if key != "power_on_at_connect" and (isinstance(value, bool) or not isinstance(value, int | float)):
            r.problems.append(f"robot.{key}: must be a number, got {value!r}")
        elif key != "power_on_at_connect" and value <= 0:
            r.problems.append(f"robot.{key}: must be positive, got {value!r}")
    return host, driver


def _read_tracker(r: _Reader) -> tuple:
    """[tracker]: url, reflector, measurement time (s), shots per point, position in the base frame (mm)."""
    url = r.get("tracker", "url", "str", required=True)
    if url is not None and "://" not in url and not url.startswith("/dev/"):
        r.problems.append(
            f"tracker.url: {url!r} is not a pyserial URL; use socket://HOST:PORT, rfc2217://HOST:PORT or /dev/tty..."
        )
    reflector = r.get("tracker", "reflector", "str")
    meas_time_s = r.get("tracker", "meas_time_s", "positive", default=1.0)
    shots = r.get("tracker", "shots_per_point", "int", default=3)
    p_tracker_mm = r.vector("tracker", "position_base_mm", 3, required=True)
    if p_tracker_mm is not None and np.linalg.norm(p_tracker_mm[:2]) < 300:
        r.problems.append(
            "tracker.position_base_mm: the tracker must stand at least 300 mm from the robot's base axis; "
            "give its approximate position in the robot base frame (a tape measure is enough)"
        )
    return url, reflector, meas_time_s, shots, p_tracker_mm


def _read_tool(r: _Reader) -> tuple:
    """[tool]: the nest centres (m, flange frame), SMR radius and flange hole pattern (mm)."""
    nests = r.get("tool", "nests_flange_mm", "any", required=True)
    nests_arr = None
    if nests is not None:
        rows = [_numbers(v) for v in nests] if isinstance(nests, list) else [None]
        if not rows or any(v is None or v.shape != (3,) for v in rows):
            r.problems.append(
                "tool.nests_flange_mm: must be a list of [x, y, z] nest centres in mm, e.g. [[30, -20, 110]]"
            )
        else:
            nests_arr = np.array(rows) / 1e3
            if np.any(np.linalg.norm(nests_arr, axis=1) > 0.5):
                r.problems.append(
                    "tool.nests_flange_mm: a nest lies over 500 mm from the flange: are these mm?"
                )
    smr_radius_mm = r.get("tool", "smr_radius_mm", "positive", default=SMR_RADIUS_MM)
    circle_mm = r.get("tool", "hole_circle_radius_mm", "positive", default=31.5)
    hole7_mm = r.get("tool", "hole7_radius_mm", "positive", default=45.0)
    hole_d_mm = r.get("tool", "hole_diameter_mm", "positive", default=6.6)
    if hole_d_mm is not None and smr_radius_mm is not None and hole_d_mm >= 2 * smr_radius_mm:
        r.problems.append(
            "tool.hole_diameter_mm: must be smaller than the SMR's diameter, or the SMR falls through"
        )
    return nests_arr, smr_radius_mm, circle_mm, hole7_mm, hole_d_mm


def _read_envelope(r: _Reader, nominal: KinematicModel | None, n: int) -> tuple:
    """[envelope]: the Cartesian box (mm) and joint ranges (deg), inside the robot's own limits."""
    box_min = r.vector("envelope", "box_min_mm", 3, required=True)
    box_max = r.vector("envelope", "box_max_mm", 3, required=True)
    if box_min is not None and box_max is not None and np.any(box_max <= box_min):
        r.problems.append("envelope.box_max_mm: every coordinate must exceed envelope.box_min_mm's")
    limits = nominal.joint_limits if nominal else np.tile([-2 * np.pi, 2 * np.pi], (n, 1))
    jmin = r.vector("envelope", "joint_min_deg", n, default=np.rad2deg(limits[:, 0]))
    jmax = r.vector("envelope", "joint_max_deg", n, default=np.rad2deg(limits[:, 1]))
    if jmin is not None and jmax is not None:
        if np.any(jmax <= jmin):
            r.problems.append("envelope.joint_max_deg: every limit must exceed envelope.joint_min_deg's")
        outside = np.flatnonzero(
            (np.deg2rad(jmin) < limits[:, 0] - 1e-9) | (np.deg2rad(jmax) > limits[:, 1] + 1e-9)
        )
        if outside.size:
            r.problems.append(
                f"envelope.joint_min_deg/joint_max_deg: joint(s) {', '.join(str(j + 1) for j in outside)} "
                "reach beyond the robot's own limits; stay inside them"
            )
    return box_min, box_max, jmin, jmax


def _check_home(
    envelope: Envelope, nominal: KinematicModel, home: np.ndarray, nests_m: np.ndarray, source: str
) -> None:
    """The home pose is the safe detour of moves: it must lie inside the envelope."""
    problem = envelope.pose_problems(nominal, home[None], nests_m)[0]
    if problem:
        raise CellConfigError(
            source,
            [
                f"motion.home_deg: the home pose leaves the envelope ({problem}); it is the safe detour of moves"
            ],
        )


def _read_home(
    r: _Reader, nominal: KinematicModel | None, n: int, coupling: JointCoupling | None
) -> np.ndarray | None:
    """[motion] home_deg, as the pendant shows it (the controller's joints of a robot that couples its
    joints), as the kinematic joints the runner plans in (rad); None when malformed (a problem recorded)."""
    default = _default_home(nominal, n)
    default = default if coupling is None else coupling.to_controller(default[None])[0]
    home_deg = r.vector("motion", "home_deg", n, default=np.rad2deg(default))
    if home_deg is None:
        return None
    home = np.deg2rad(home_deg)
    return home if coupling is None else coupling.to_kinematic(home[None])[0]


def _default_home(nominal: KinematicModel | None, n: int) -> np.ndarray:
    from hil.geometry.ik import default_home

    return default_home(nominal) if nominal is not None else np.zeros(n)


def load_cell_config(path: str | Path) -> CellConfig:
    """Read and check a cell.toml; raises CellConfigError (every problem, with its key) or names the file."""
    path = Path(path)
    if not path.is_file():
        raise CellConfigError(str(path), ["file not found; give the path of the cell's TOML configuration"])
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CellConfigError(str(path), [f"not valid TOML ({exc}); fix the syntax at that line"]) from exc
    return parse_cell_config(data, source=str(path))


def format_cell_toml(values: dict[str, dict[str, Any]]) -> str:
    """Write a cell configuration as TOML (flat tables of strings, numbers, booleans and number lists)."""
    lines: list[str] = []
    for section in SECTIONS:
        table = values.get(section)
        if not table:
            continue
        lines.append(f"[{section}]")
        for key, value in table.items():
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, int | float):
        return repr(float(value)) if isinstance(value, float) else str(value)
    if isinstance(value, list | tuple | np.ndarray):
        return "[" + ", ".join(_toml_value(v.item() if isinstance(v, np.generic) else v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")
