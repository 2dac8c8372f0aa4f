"""The simulated robot cell: the single physical truth behind both fakes.

It keeps apart what the controller believes (nominal model, commanded joints, encoder readings) and
what physically happens (true geometry with hidden errors, gravity compliance, cyclic errors,
backlash, thermal growth, repeatability jitter), and where each SMR sits and what the tracker reads.
Hidden truth is drawn from `seed`. Noise is drawn from the seed and a counter, never from how often the
cell is asked: tracker noise by the index of the reading, repeatability jitter and encoder noise by the index
of the motion (a robot standing still draws nothing, and its encoders read the same). Two clocks: `time_s`,
the timer clock that runs whenever simulated time passes (moves, waits, the protective-stop delay), and
`physics_time_s`, which runs only while something happens (motion, measurement, an explicit
`advance_time`), so idle wall time neither warms the arm nor drifts the meteo. The same seed and the same
calls give the same cell and the same readings, however loaded the machine.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal, TypedDict, cast

import numpy as np

from fakes.physics import chain_frames, gravity_torques
from hil.data.jsonable import to_jsonable
from hil.geometry.coupling import JointCoupling
from hil.geometry.ik import default_home, is_ur_like
from hil.geometry.kinematics import KinematicModel
from hil.geometry.robots import get_robot, robot_coupling
from hil.geometry.se3 import quaternion_matrix

SMR_RADIUS_M = 0.01905  # 1.5" sphere

# Lumped link masses (kg) per joint's link, rounded from the makers' published figures.
LINK_MASSES_KG: dict[str, tuple[float, ...]] = {
    "ur5": (3.7, 8.4, 2.3, 1.2, 1.2, 0.19),
    "ur10": (7.1, 12.7, 4.3, 2.0, 2.0, 0.37),
    "ur5e": (3.8, 8.1, 2.8, 1.4, 1.3, 0.37),
    "ur10e": (7.4, 13.1, 4.0, 2.1, 2.0, 0.62),
    "irb2600": (90.0, 45.0, 35.0, 15.0, 6.0, 1.0),
    # sized, not from a data sheet: FANUC publishes the LR Mate 200iD's total (25 kg) only
    "lrmate200id": (9.0, 6.0, 4.0, 1.5, 1.0, 0.2),
}

# How far each true link mass lies from the table's (1-sigma, as a fraction, clipped at 2 sigma): cables, motors,
# brakes and castings make a real arm's links differ from the maker's published figures, which the robot
# files give the diagnosis; the cell's truth must not be the model's assumption.
LINK_MASS_SIGMA_FRACTION = 0.15
MASS_STREAM = 4  # default_rng([seed, MASS_STREAM]): the true link masses, apart from the other truth draws

# Joint stiffness (N*m/rad): a harmonic-drive arm of this class deflects a few tenths of a mm.
JOINT_STIFFNESS: dict[str, tuple[float, ...]] = {
    "ur5": (1.2e5, 1.2e5, 6.0e4, 1.5e4, 1.5e4, 1.5e4),
    "ur10": (2.0e5, 2.0e5, 1.0e5, 2.5e4, 2.5e4, 2.5e4),
    "ur5e": (1.2e5, 1.2e5, 6.0e4, 1.5e4, 1.5e4, 1.5e4),
    "ur10e": (2.0e5, 2.0e5, 1.0e5, 2.5e4, 2.5e4, 2.5e4),
    "irb2600": (2.0e6, 2.0e6, 1.0e6, 2.0e5, 2.0e5, 2.0e5),
    "lrmate200id": (2.0e5, 2.0e5, 1.0e5, 2.0e4, 2.0e4, 2.0e4),  # sized like the UR10's: none published
}

# The robots whose simulated controller couples its joints (their robot file's [coupling]): the arm and its
# physics stay kinematic, the controller speaks the maker's joints (hil.geometry.coupling)
COUPLED_ROBOTS = ("lrmate200id",)


class EffectFlags(TypedDict, total=False):
    """SimCellConfig flags of the physical effects a cell can switch on beside its hidden geometric errors."""

    compliance: bool
    cyclic: bool
    backlash: bool
    thermal: bool


# Each effect named as the diagnosis names its effect family (hil.model.effects.EFFECT_FAMILIES), with the
# SimCellConfig flag that switches it on: one name per effect across the simulator and the diagnosis.
EFFECT_FLAGS: dict[str, str] = {
    "gravity_compliance": "compliance",
    "cyclic": "cyclic",
    "backlash": "backlash",
    "thermal_expansion": "thermal",
}
CELL_EFFECTS: tuple[str, ...] = tuple(EFFECT_FLAGS)

# Refraction: n - 1 of air falls ~0.93 ppm per K near 20 degC. A tracker that computes n from an air
# temperature below the real one takes n too large and measures distances short: 0.93 ppm per K of
# (real - used) air temperature.
REFRACTION_PER_K = -0.93e-6

# Counter-keyed noise streams: default_rng([seed, stream, index]).
TRACKER_NOISE_STREAM = 6  # index: the tracker reading
JITTER_STREAM = 7  # index: the motion
ENCODER_STREAM = 8  # index: the motion


def parse_effect_flags(text: str) -> EffectFlags:
    """'gravity_compliance,thermal_expansion' (or 'none') -> SimCellConfig flags of every effect."""
    chosen = set() if text.strip().lower() == "none" else {e.strip() for e in text.split(",") if e.strip()}
    unknown = chosen - set(CELL_EFFECTS)
    if unknown:
        raise ValueError(
            f"unknown effect(s) {sorted(unknown)}: choose from {', '.join(CELL_EFFECTS)} or none"
        )
    return cast(EffectFlags, {flag: name in chosen for name, flag in EFFECT_FLAGS.items()})


@dataclass(frozen=True)
class Meteo:
    """Air temperature, pressure and humidity at the tracker."""

    temperature_c: float
    pressure_hpa: float
    humidity_pct: float


@dataclass(frozen=True)
class SmrLocation:
    """Where an SMR sits: a flange hole (1..7), the flange face, a tool nest (1..3) or fixed in the room."""

    kind: Literal["hole", "face", "nest", "fixed"]
    index: int | None = None
    point_m: tuple[float, ...] | None = None  # face: (x, y) on the flange face; fixed: tracker frame (x,y,z)

    def __post_init__(self) -> None:
        if self.kind in ("hole", "nest") and self.index is None:
            raise ValueError(f"SmrLocation kind '{self.kind}' needs an index")
        if self.kind == "face" and (self.point_m is None or len(self.point_m) != 2):
            raise ValueError("SmrLocation kind 'face' needs point_m=(x, y) in the flange frame, metres")
        if self.kind == "fixed" and (self.point_m is None or len(self.point_m) != 3):
            raise ValueError("SmrLocation kind 'fixed' needs point_m=(x, y, z) in the tracker frame, metres")
        if self.kind not in ("hole", "face", "nest", "fixed"):
            raise ValueError(f"unknown SmrLocation kind '{self.kind}': use hole, face, nest or fixed")

    @property
    def number(self) -> int:
        """The hole or nest number (a hole or nest location always has one)."""
        if self.index is None:
            raise ValueError(f"SmrLocation kind '{self.kind}' has no hole or nest number")
        return self.index

    @property
    def point(self) -> tuple[float, ...]:
        """The face point (x, y) or the fixed point (x, y, z), metres (those kinds always have one)."""
        if self.point_m is None:
            raise ValueError(f"SmrLocation kind '{self.kind}' has no point_m")
        return self.point_m


@dataclass
class SimCellConfig:
    """Everything that defines a simulated cell. Defaults: a UR10 with realistic hidden errors and
    gravity compliance, an AT960-class tracker 2.5 m away, a three-nest tool and three SMRs."""

    robot: str = "ur10"
    seed: int = 0
    # The controller stops a move into the arm's own body (its robot file's capsules) with a protective stop,
    # as a real arm does on contact. False leaves the arm free to pass through itself (a test of what the
    # planner alone refuses).
    self_collision_stop: bool = True
    # Hidden geometric errors (1-sigma per parameter kind); scale 0 gives a perfect geometry.
    geometric_errors: bool = True
    error_sigma_angle_rad: float = np.deg2rad(0.03)
    error_sigma_length_m: float = 0.3e-3
    # Gravity joint compliance from link masses (the table's, each off by LINK_MASS_SIGMA_FRACTION drawn from
    # the seed), plus an optional payload at the tool.
    compliance: bool = True
    payload_kg: float = 0.0
    payload_point_flange_m: tuple[float, float, float] = (0.0, 0.0, 0.08)
    # Cyclic joint errors: first and second harmonic of the joint angle (rad amplitudes).
    cyclic: bool = False
    cyclic_joints: tuple[int, ...] = (1, 2, 3)
    cyclic_amplitude_rad: tuple[float, float] = (np.deg2rad(0.006), np.deg2rad(0.003))
    # Backlash: half the gap, the joint rests on the side it approached from.
    backlash: bool = False
    backlash_joints: tuple[int, ...] = (1, 2, 3)
    backlash_half_gap_rad: float = np.deg2rad(0.006)
    # Thermal growth of link lengths with a warm-up drift of the temperature.
    thermal: bool = False
    ambient_c: float = 20.0
    warmup_k: float = 10.0
    warmup_tau_s: float = 1200.0
    expansion_per_k: float = 23e-6  # aluminium
    air_warmup_fraction: float = 1.0  # the hall's air follows this fraction of the arm's warm-up
    # The air temperature the tracker's refraction model uses and reports (a manual setting, a station in the
    # sun); None: its weather station reads the hall's air. Off by dT, its distances are (1 + REFRACTION_PER_K
    # dT) too long: a scale about the tracker.
    tracker_air_c: float | None = None
    # Controller-side noise.
    encoder_sigma_rad: float = 1e-6
    repeatability_sigma_rad: float = 4e-6
    # Tracker.
    tracker_distance_m: float = 2.5
    tracker_mpe_const_m: float = 15e-6
    tracker_mpe_per_m: float = 6e-6
    tracker_mpe_sigmas: float = 2.0  # the MPE is this many sigma
    smr_centering_sigma_m: float = 2.5e-6
    pressure_hpa: float = 1013.25
    humidity_pct: float = 45.0
    # Flange calibration holes and the tool.
    hole_circle_radius_m: float = 0.0315
    hole_diameter_m: float = 0.0066
    hole7_radius_m: float = 0.045
    hole_position_sigma_m: float = 5e-6
    tool_nests_flange_m: tuple[tuple[float, float, float], ...] = (
        (0.030, -0.020, 0.110),
        (-0.060, 0.040, 0.090),
        (0.050, 0.070, 0.080),
    )
    tool_nest_error_sigma_m: float = 0.1e-3  # true nest positions differ from the drawing
    q_home_rad: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    smr_count: int = 3

    def __post_init__(self) -> None:
        if self.robot.lower() not in LINK_MASSES_KG:
            raise ValueError(f"unknown robot '{self.robot}'; choose one of {', '.join(LINK_MASSES_KG)}")
        if not 0.5 <= self.tracker_distance_m <= 40.0:
            raise ValueError("tracker_distance_m must lie between 0.5 and 40 m")
        if self.smr_count < 1:
            raise ValueError("smr_count must be at least 1")


class SimulatedCell:
    """One robot, one tracker, a flange with calibration holes, a tool with SMR nests, and SMRs."""

    def __init__(self, config: SimCellConfig | None = None) -> None:
        self.config = config or SimCellConfig()
        cfg = self.config
        self.robot_name = cfg.robot.lower()
        self.nominal: KinematicModel = get_robot(self.robot_name)
        # what the controller's joint readings are (None: the kinematic joints, as a UR reports them)
        self.coupling: JointCoupling | None = robot_coupling(self.robot_name)
        truth_rng = np.random.default_rng([cfg.seed, 1])
        self._noise_rng = np.random.default_rng([cfg.seed, 2])
        self._true_model = self._draw_true_model(truth_rng)
        self._masses = _true_link_masses(np.array(LINK_MASSES_KG[self.robot_name]), cfg.seed)
        self._stiffness = np.array(JOINT_STIFFNESS[self.robot_name])
        n = self.nominal.n_joints
        self._cyclic_phase = truth_rng.uniform(0, 2 * np.pi, (n, 2))
        self._cyclic_amp = np.zeros((n, 2))
        for j in cfg.cyclic_joints:
            self._cyclic_amp[j - 1] = np.array(cfg.cyclic_amplitude_rad) * truth_rng.uniform(0.7, 1.3, 2)
        self._backlash = np.zeros(n)
        for j in cfg.backlash_joints:
            self._backlash[j - 1] = cfg.backlash_half_gap_rad * truth_rng.uniform(0.7, 1.3)
        self.T_tracker_base = self._draw_tracker_pose(truth_rng)
        self._holes_flange = self._draw_holes(truth_rng)
        self._nests_flange = np.array(cfg.tool_nests_flange_m) + truth_rng.normal(
            0, cfg.tool_nest_error_sigma_m, (len(cfg.tool_nests_flange_m), 3)
        )
        self._centering = truth_rng.normal(0, cfg.smr_centering_sigma_m, (cfg.smr_count, 3))
        self.smr_ids: list[int] = list(range(1, cfg.smr_count + 1))
        self._smr_locations: dict[int, SmrLocation] = {}
        self.tool_mounted = True  # the cell starts with the tool on the flange, covering the holes
        self._tool_rotation_rad = 0.0  # how far about flange z the tool sits from its drawn position
        self._init_smrs()
        self._time_s = 0.0  # the timer clock
        self._physics_s = 0.0  # the physics clock (thermal growth, meteo drift)
        # a UR's working pose on a UR-like arm, else the nominal model's home (hil's default home for it)
        start = np.array(cfg.q_home_rad, dtype=float)
        self._q_cmd = start if is_ur_like(self.nominal) else default_home(self.nominal)
        self._approach = np.ones(n)  # last motion direction per joint
        self._jitter = np.zeros(n)
        self._physics_cache: tuple[tuple, tuple[np.ndarray, np.ndarray]] | None = None
        self._encoder_noise = np.zeros(n)
        self._standing = True
        # the array set_commanded_joints last tested, and the commanded joints it was tested against
        self._taken: tuple[object, np.ndarray | None] = (None, None)
        self.motions = 0  # motions started (a change of the commanded joints after standing still)
        self.readings = 0  # tracker readings taken (measure_smr)

    # ----- hidden truth -------------------------------------------------------------------------
    def _draw_true_model(self, rng: np.random.Generator) -> KinematicModel:
        cfg = self.config
        if not cfg.geometric_errors:
            return self.nominal
        errors = {}
        for name in self.nominal.param_names:
            kind = name.rstrip("0123456789")
            sigma = cfg.error_sigma_length_m if kind in ("a", "d") else cfg.error_sigma_angle_rad
            errors[name] = float(rng.normal(0, sigma))
        return self.nominal.with_errors(errors)

    def _draw_tracker_pose(self, rng: np.random.Generator) -> np.ndarray:
        azimuth = rng.uniform(0, 2 * np.pi)
        p_base_tracker = self.config.tracker_distance_m * np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        p_base_tracker[2] = rng.uniform(-0.3, 0.3)
        R_base_tracker = random_rotation(int(rng.integers(2**31)))
        T_base_tracker = np.eye(4)
        T_base_tracker[:3, :3] = R_base_tracker
        T_base_tracker[:3, 3] = p_base_tracker
        return np.linalg.inv(T_base_tracker)

    def _draw_holes(self, rng: np.random.Generator) -> np.ndarray:
        """Seated-SMR centres (7, 3) in the flange frame: holes 1-6 at 60 deg, hole 7 on +x."""
        cfg = self.config
        k = np.arange(1, 7)
        angles = np.deg2rad((k - 3.5) * 60.0)  # holes 3 and 4 at -30 and +30 deg around +x
        radii = np.full(6, cfg.hole_circle_radius_m)
        angles = np.append(angles, 0.0)
        radii = np.append(radii, cfg.hole7_radius_m)
        xy = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
        xy += rng.normal(0, cfg.hole_position_sigma_m, xy.shape)
        seat_height = np.sqrt(SMR_RADIUS_M**2 - (cfg.hole_diameter_m / 2) ** 2)
        return np.column_stack([xy, np.full(7, seat_height)])

    def _init_smrs(self) -> None:
        # SMR 1 on the tool, the others in floor nests beside the robot.
        self._smr_locations[1] = SmrLocation("nest", index=1)
        for smr_id in self.smr_ids[1:]:
            angle = 0.6 * smr_id
            p_base = np.array([0.6 * np.cos(angle), 0.6 * np.sin(angle), -0.05])
            p_tracker = self.T_tracker_base[:3, :3] @ p_base + self.T_tracker_base[:3, 3]
            self._smr_locations[smr_id] = SmrLocation("fixed", point_m=tuple(p_tracker))

    # ----- clock --------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        """Simulated seconds since the cell started (the timer clock)."""
        return self._time_s

    @property
    def physics_time_s(self) -> float:
        """Simulated seconds of activity (motion, measurement, explicit waits): the clock of the physics."""
        return self._physics_s

    def move_tracker(self, seed: int) -> None:
        """Set the tracker up elsewhere (a new placement drawn from `seed`), as between two campaigns;
        the robot, its hidden errors and the room's fixed SMRs stay where they are."""
        fixed_base = {
            i: np.linalg.inv(self.T_tracker_base) @ np.append(np.asarray(loc.point_m, float), 1.0)
            for i, loc in self._smr_locations.items()
            if loc.kind == "fixed"
        }
        self.T_tracker_base = self._draw_tracker_pose(np.random.default_rng([seed, 3]))
        for i, p_base in fixed_base.items():
            self._smr_locations[i] = SmrLocation("fixed", point_m=tuple((self.T_tracker_base @ p_base)[:3]))

    def advance_time(self, dt_s: float) -> None:
        """Let dt_s (>= 0) pass on both clocks: the arm warms, the meteo drifts."""
        self.advance_timer(dt_s)
        self._physics_s += float(dt_s)

    def advance_timer(self, dt_s: float) -> None:
        """Let dt_s (>= 0) pass on the timer clock only (an idle tick: nothing physical happens)."""
        if dt_s < 0:
            raise ValueError("time cannot run backwards")
        self._time_s += float(dt_s)

    def advance_physics(self, dt_s: float) -> None:
        """Let dt_s (>= 0) of activity pass on the physics clock (a motion tick, a measurement)."""
        if dt_s < 0:
            raise ValueError("time cannot run backwards")
        self._physics_s += float(dt_s)

    def structure_temperature_c(self, time_s: np.ndarray | float | None = None) -> np.ndarray | float:
        """Temperature of the arm at the given physics time(s) (default: now)."""
        t = self._physics_s if time_s is None else np.asarray(time_s, dtype=float)
        cfg = self.config
        if not cfg.thermal:
            return cfg.ambient_c + 0.0 * t
        return cfg.ambient_c + cfg.warmup_k * (1.0 - np.exp(-t / cfg.warmup_tau_s))

    def hall_air_c(self, time_s: np.ndarray | float | None = None) -> np.ndarray | float:
        """The hall's real air temperature at the given physics time(s) (default: now)."""
        cfg = self.config
        arm_c = self.structure_temperature_c(time_s)
        return cfg.ambient_c + cfg.air_warmup_fraction * (np.asarray(arm_c) - cfg.ambient_c)

    def station_air_c(self, time_s: np.ndarray | float | None = None) -> np.ndarray:
        """The air temperature the tracker's weather station reads at the given physics time(s) (default: now):
        the hall's air, or the fixed `tracker_air_c` of a stuck station or a hand entry."""
        hall = np.asarray(self.hall_air_c(time_s), float)
        fixed = self.config.tracker_air_c
        return hall if fixed is None else np.full(hall.shape, float(fixed))

    def tracker_scale(
        self, time_s: np.ndarray | float | None = None, air_c: float | None = None
    ) -> np.ndarray | float:
        """How much too long the tracker measures distances: its refraction computed from `air_c` (the meteo
        a client entered by hand), else from `tracker_air_c`; 0 with a station that reads the hall's air."""
        used = self.config.tracker_air_c if air_c is None else air_c
        if used is None:
            return 0.0 * np.asarray(self.structure_temperature_c(time_s))
        return REFRACTION_PER_K * (np.asarray(self.hall_air_c(time_s)) - used)

    def meteo(self) -> Meteo:
        """Meteo at the tracker now (pressure and humidity drift slightly with time)."""
        cfg = self.config
        t = self._physics_s
        return Meteo(
            temperature_c=float(self.station_air_c()),
            pressure_hpa=float(cfg.pressure_hpa + 0.5 * np.sin(2 * np.pi * t / 7200.0)),
            humidity_pct=float(cfg.humidity_pct + 2.0 * np.sin(2 * np.pi * t / 5400.0)),
        )

    # ----- robot --------------------------------------------------------------------------------
    @property
    def commanded_q(self) -> np.ndarray:
        """Joints last commanded (what the controller believes it holds)."""
        return self._q_cmd.copy()

    def set_commanded_joints(self, q: np.ndarray) -> bool:
        """The controller commands joints q (6,); whether they changed. A change after standing still starts
        a motion, which draws its repeatability jitter and encoder noise from the seed and the motion's index."""
        given = q
        if given is self._taken[0] and self._q_cmd is self._taken[1]:
            # the very array last tested, against the same commanded joints: no step, as the full test below
            # would find again (the controller replaces its commanded joints, never writes into them), without
            # its six numpy calls in every cycle of an arm standing still
            self._standing = True
            return False
        q = np.asarray(q, dtype=float).reshape(-1)
        # the arrays' own all/any: called every controller cycle, np.all/np.any's dispatch cost more than the test
        if q.shape != self._q_cmd.shape or not np.isfinite(q).all():
            raise ValueError(f"commanded joints must be {self._q_cmd.shape[0]} finite values, got {q}")
        step = q - self._q_cmd
        moved = np.abs(step) > 1e-12
        if not moved.any():
            self._standing = True
            self._taken = (given, self._q_cmd)
            return False
        self._approach[moved] = np.sign(step[moved])
        if self._standing:
            self._standing = False
            self.motions += 1
            cfg, key = self.config, (self.config.seed, self.motions)
            self._jitter = _keyed(JITTER_STREAM, key).normal(0, cfg.repeatability_sigma_rad, q.shape)
            self._encoder_noise = _keyed(ENCODER_STREAM, key).normal(0, cfg.encoder_sigma_rad, q.shape)
        self._q_cmd = q
        self._taken = (given, q)
        return True

    def encoder_joints(self) -> np.ndarray:
        """What the motor encoders report: commanded joints plus the encoder noise of the current motion."""
        return self._q_cmd + self._encoder_noise

    def true_joint_offsets(
        self, q_cmd: np.ndarray, approach: np.ndarray, time_s: np.ndarray | float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Output-side joint deviations (N, n) and the true frames (N, n+1, 4, 4) at those joints.

        Batch form of the physics: backlash and cyclic errors from the command and its approach
        direction, then gravity deflection computed on the thermally grown true geometry.
        """
        cfg = self.config
        q_cmd = np.atleast_2d(q_cmd)
        offsets = np.zeros_like(q_cmd)
        if cfg.backlash:
            offsets += self._backlash * np.atleast_2d(approach)
        if cfg.cyclic:
            ph = self._cyclic_phase
            offsets += self._cyclic_amp[:, 0] * np.sin(q_cmd + ph[:, 0])
            offsets += self._cyclic_amp[:, 1] * np.sin(2 * q_cmd + ph[:, 1])
        geometry = self._true_geometry(np.atleast_1d(time_s))
        frames = chain_frames(q_cmd + offsets, *geometry)
        if cfg.compliance:
            tau = gravity_torques(frames, self._masses, cfg.payload_kg, np.array(cfg.payload_point_flange_m))
            offsets = offsets + tau / self._stiffness
            frames = chain_frames(q_cmd + offsets, *geometry)
        return offsets, frames

    def _true_geometry(self, time_s: np.ndarray) -> tuple[np.ndarray, ...]:
        m = self._true_model
        growth: np.ndarray | float = 1.0
        if self.config.thermal:
            dT = np.asarray(self.structure_temperature_c(time_s)) - self.config.ambient_c
            growth = (1.0 + self.config.expansion_per_k * dT)[:, None]
        return m.theta, m.d * growth, m.a * growth, m.alpha, m.beta

    def _physics_now(self) -> tuple[np.ndarray, np.ndarray]:
        """`true_joint_offsets` of the arm as it stands now, kept until the command, the approach or the physics
        clock changes (the tracker asks for it at its own rate, mostly while the arm stands still)."""
        q = self._q_cmd + self._jitter
        key = (q.tobytes(), self._approach.tobytes(), self._physics_s)
        if self._physics_cache is None or self._physics_cache[0] != key:
            self._physics_cache = (key, self.true_joint_offsets(q, self._approach, self._physics_s))
        return self._physics_cache[1]

    def true_joints(self) -> np.ndarray:
        """Output-side joints physically reached now."""
        offsets, _ = self._physics_now()
        return self._q_cmd + self._jitter + offsets[0]

    def T_base_flange_true(self) -> np.ndarray:
        """Where the flange physically is now (4, 4), base frame."""
        _, frames = self._physics_now()
        return frames[0, -1] @ self.nominal.T_last_flange

    # ----- the tool on the flange -----------------------------------------------------------------
    def unmount_tool(self) -> None:
        """The operator's hands: take the tool off the flange (bare flange: holes and face reachable). An SMR in
        a tool nest is taken out first and put down in the room where it was."""
        self._put_down("nest")
        self.tool_mounted = False

    def mount_tool(self, rotation_rad: float = 0.0) -> None:
        """The operator's hands: put the tool on the flange, turned `rotation_rad` about flange z from its drawn
        position (0: on its dowel; a bolt circle of six lets it go on 60 deg off). An SMR in a hole or on the
        face is taken off first (the tool covers them) and put down in the room where it was."""
        if not np.isfinite(rotation_rad):
            raise ValueError("the tool's rotation must be a finite angle (radians)")
        self._put_down("hole", "face")
        self.tool_mounted = True
        self._tool_rotation_rad = float(rotation_rad)

    def _put_down(self, *kinds: str) -> None:
        """SMRs at these kinds of location go off the robot: fixed in the room where they are now."""
        for smr_id, loc in list(self._smr_locations.items()):
            if loc.kind in kinds:
                self._smr_locations[smr_id] = SmrLocation(
                    "fixed", point_m=tuple(self.smr_center_tracker(smr_id))
                )

    def _tool_nests_flange(self) -> np.ndarray:
        """True nest centres (K, 3) in the flange frame, as the tool is mounted now."""
        c, s = np.cos(self._tool_rotation_rad), np.sin(self._tool_rotation_rad)
        return self._nests_flange @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T

    # ----- SMRs and the tracker -----------------------------------------------------------------
    def place_smr(self, smr_id: int, location: SmrLocation) -> None:
        """The operator's hands: put SMR `smr_id` at `location` (holes and face on the bare flange, nests on
        the mounted tool)."""
        if smr_id not in self.smr_ids:
            raise ValueError(f"no SMR {smr_id}; the cell has SMRs {self.smr_ids}")
        if location.kind in ("hole", "face") and self.tool_mounted:
            raise ValueError(
                "the tool covers the flange holes and face: take the tool off first (unmount_tool)"
            )
        if location.kind == "nest" and not self.tool_mounted:
            raise ValueError("no tool on the flange: mount the tool before seating an SMR in a tool nest")
        if location.kind == "hole" and not 1 <= location.number <= 7:
            raise ValueError(f"flange holes are numbered 1..7, got {location.index}")
        if location.kind == "nest" and not 1 <= location.number <= len(self._nests_flange):
            raise ValueError(f"tool nests are numbered 1..{len(self._nests_flange)}, got {location.index}")
        self._smr_locations[smr_id] = location

    def smr_location(self, smr_id: int) -> SmrLocation:
        """Current location of an SMR."""
        return self._smr_locations[smr_id]

    def smr_point_flange(self, location: SmrLocation) -> np.ndarray | None:
        """True SMR centre in the flange frame for an on-robot location, None for a fixed one."""
        if location.kind == "hole":
            return self._holes_flange[location.number - 1].copy()
        if location.kind == "nest":
            return self._tool_nests_flange()[location.number - 1]
        if location.kind == "face":
            x, y = location.point
            return np.array([x, y, SMR_RADIUS_M])
        return None

    def smr_center_tracker(self, smr_id: int) -> np.ndarray:
        """True SMR centre (3,) in the tracker frame, metres."""
        loc = self._smr_locations[smr_id]
        p_flange = self.smr_point_flange(loc)
        if p_flange is None:
            return np.array(loc.point_m, dtype=float)
        T = self.T_tracker_base @ self.T_base_flange_true()
        return T[:3, :3] @ p_flange + T[:3, 3]

    def smr_facing_angle_rad(self, smr_id: int) -> float:
        """Angle between the SMR's opening axis (flange +z on the robot) and the line to the tracker."""
        loc = self._smr_locations[smr_id]
        if loc.kind == "fixed":
            return 0.0
        T = self.T_tracker_base @ self.T_base_flange_true()
        p = self.smr_center_tracker(smr_id)
        to_tracker = -p / np.linalg.norm(p)
        return float(np.arccos(np.clip(T[:3, 2] @ to_tracker, -1.0, 1.0)))

    def tracker_sigma_m(self, distance_m: np.ndarray | float) -> np.ndarray:
        """Per-axis 1-sigma tracker noise at a distance: the MPE divided by `tracker_mpe_sigmas`."""
        cfg = self.config
        return (
            cfg.tracker_mpe_const_m + cfg.tracker_mpe_per_m * np.asarray(distance_m)
        ) / cfg.tracker_mpe_sigmas

    def tracker_reading(
        self, smr_id: int, p_tracker: np.ndarray, time_s: np.ndarray | None = None
    ) -> np.ndarray:
        """Noisy tracker readings (N, 3) of SMR `smr_id` whose true centres are p_tracker (N, 3), at physics
        times `time_s` (N,) (default: now; the tracker's scale follows the air)."""
        p = np.atleast_2d(p_tracker)
        p = p * (1.0 + np.broadcast_to(self.tracker_scale(time_s), (len(p),)))[:, None]
        sigma = self.tracker_sigma_m(np.linalg.norm(p, axis=1))[:, None]
        return p + self._centering[smr_id - 1] + sigma * self._noise_rng.standard_normal(p.shape)

    def measure_smr(self, smr_id: int, air_c: float | None = None) -> np.ndarray:
        """One tracker reading (3,) of an SMR, tracker frame, metres; its noise drawn from the seed and the
        reading's index; `air_c`: the air temperature the tracker's refraction uses (`tracker_scale`)."""
        p = self.smr_center_tracker(smr_id) * (1.0 + float(self.tracker_scale(air_c=air_c)))
        self.readings += 1
        noise = _keyed(TRACKER_NOISE_STREAM, (self.config.seed, self.readings)).standard_normal(3)
        return p + self._centering[smr_id - 1] + self.tracker_sigma_m(float(np.linalg.norm(p))) * noise

    # ----- batch campaigns ----------------------------------------------------------------------
    def run_sequence(
        self, q_cmd: np.ndarray, smr_id: int = 1, seconds_per_point: float = 4.0
    ) -> dict[str, np.ndarray]:
        """Visit joint sets q_cmd (N, 6) in order, measure SMR `smr_id` after each; batch physics.

        Returns arrays: q_encoder (N,6), p_tracker_measured (N,3), p_tracker_true (N,3), t_s (N,),
        temperature_c (N,), q_true (N,6), T_base_flange_true (N,4,4) (where the flange physically was: other
        nests and a 6-DoF probe read at the same poses). Leaves the cell at the last pose, its clock moved on.
        """
        q_cmd = self.nominal.check_joints(q_cmd)
        loc = self._smr_locations[smr_id]
        p_flange = self.smr_point_flange(loc)
        if p_flange is None:
            raise ValueError(f"SMR {smr_id} is fixed in the room; put it on the robot to sample poses")
        N, n = q_cmd.shape
        previous = np.vstack([self._q_cmd, q_cmd[:-1]])
        step = q_cmd - previous
        # Direction memory: a joint that does not move keeps the side of its last move (forward fill).
        signs = np.vstack([self._approach, np.sign(step)])
        moved = np.vstack([np.ones(n, bool), np.abs(step) > 1e-12])
        last_move_row = np.maximum.accumulate(np.where(moved, np.arange(N + 1)[:, None], 0), axis=0)
        approach = np.take_along_axis(signs, last_move_row, axis=0)[1:]
        t_s = self._physics_s + seconds_per_point * np.arange(1, N + 1)
        jitter = self._noise_rng.normal(0, self.config.repeatability_sigma_rad, q_cmd.shape)
        offsets, frames = self.true_joint_offsets(q_cmd + jitter, approach, t_s)
        T_flange = frames[:, -1] @ self.nominal.T_last_flange
        p_base = T_flange[:, :3, :3] @ p_flange + T_flange[:, :3, 3]
        p_true = p_base @ self.T_tracker_base[:3, :3].T + self.T_tracker_base[:3, 3]
        p_meas = self.tracker_reading(smr_id, p_true, t_s)
        q_enc = q_cmd + self._noise_rng.normal(0, self.config.encoder_sigma_rad, q_cmd.shape)
        self._q_cmd = q_cmd[-1].copy()
        self._approach = approach[-1].copy()
        self._jitter = jitter[-1].copy()
        self._time_s += float(t_s[-1]) - self._physics_s
        self._physics_s = float(t_s[-1])
        return {
            "q_encoder": q_enc,
            "q_true": q_cmd + jitter + offsets,
            "p_tracker_measured": p_meas,
            "p_tracker_true": p_true,
            "t_s": t_s,
            "temperature_c": np.asarray(self.structure_temperature_c(t_s)) + 0.0 * t_s,
            "T_base_flange_true": T_flange,
        }

    # ----- ground truth -------------------------------------------------------------------------
    def ground_truth(self) -> dict:
        """The hidden truth as a JSON-serialisable dict (for tests and the control channel)."""
        nominal = self.nominal
        names = nominal.param_names
        return {
            "robot": self.robot_name,
            "seed": self.config.seed,
            "config": to_jsonable(asdict(self.config)),
            "parameter_names": names,
            "parameter_errors": dict(
                zip(names, (self._true_model.params - nominal.params).tolist(), strict=True)
            ),
            "T_tracker_base": self.T_tracker_base.tolist(),
            "holes_flange_m": self._holes_flange.tolist(),
            "tool_nests_flange_m": self._nests_flange.tolist(),
            "smr_centering_m": self._centering.tolist(),
            "joint_stiffness_nm_per_rad": self._stiffness.tolist(),
            "link_masses_kg": self._masses.tolist(),
            "cyclic_amplitude_rad": self._cyclic_amp.tolist() if self.config.cyclic else None,
            "cyclic_phase_rad": self._cyclic_phase.tolist() if self.config.cyclic else None,
            "backlash_half_gap_rad": self._backlash.tolist() if self.config.backlash else None,
            "time_s": self._time_s,
            "physics_time_s": self._physics_s,
            "commanded_q": self._q_cmd.tolist(),
            "smr_locations": {str(k): to_jsonable(asdict(v)) for k, v in self._smr_locations.items()},
            "tool_mounted": self.tool_mounted,
            "tool_rotation_rad": self._tool_rotation_rad,
        }


def _true_link_masses(table_kg: np.ndarray, seed: int) -> np.ndarray:
    """The cell's true link masses: the table's, each off by a seeded LINK_MASS_SIGMA_FRACTION (clipped at 2
    sigma, so no link weighs near nothing), from its own stream so no other truth draw changes with it."""
    z = np.clip(np.random.default_rng([seed, MASS_STREAM]).standard_normal(len(table_kg)), -2.0, 2.0)
    return table_kg * (1.0 + LINK_MASS_SIGMA_FRACTION * z)


def _keyed(stream: int, key: tuple[int, int]) -> np.random.Generator:
    """The generator of one draw: seed, stream and counter, independent of every other draw."""
    seed, index = key
    return np.random.default_rng([seed, stream, index])


def random_rotation(seed: int) -> np.ndarray:
    """A uniformly distributed rotation matrix: four standard normal draws of the legacy generator seeded with
    `seed`, taken as a quaternion (x, y, z, w) and normalised. The draw scipy's `Rotation.random` makes for
    an integer seed, written out so that a cell starts without importing scipy.spatial (half of its import
    time): the same matrix bit for bit, so every seed's cell stays the cell it was (tests/test_cell.py)."""
    x, y, z, w = np.random.RandomState(seed).normal(size=4)
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    return quaternion_matrix(x / norm, y / norm, z / norm, w / norm)
