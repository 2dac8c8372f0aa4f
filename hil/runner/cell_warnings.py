"""Settings a cell config accepts but a cell engineer would question before the first motion: a settle time
that multiplies every point, speeds above what a measurement run needs, an envelope box the arm cannot fill,
joint limits wider than the arm can use without folding into itself, a URDF whose base frame had to move
onto joint 1's axis. `hil cell check` prints them; none stops
a run (the envelope and the collision checks do that), each says what to change."""

from __future__ import annotations

import numpy as np

from hil.geometry.collision import clear_range_rad
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.urdf_import import import_urdf
from hil.geometry.urdf_read import is_urdf_spec
from hil.runner.cell_config import DEFAULT_JOINT_SPEED_RAD_S, DEFAULT_LINEAR_SPEED_M_S, CellConfig

SETTLE_PLAUSIBLE_S = (
    5.0  # a UR arm and an SMR settle in well under a second; seconds more wait at every point
)
TYPICAL_GRID_POINTS = 400  # what a 100 mm grid of a UR10's volume measures: the settle time's cost in words
REACH_SAMPLES = 4000  # random joint vectors inside the limits: the arm's reach from the base origin
REACH_SLACK = 1.05  # a box corner this much beyond the sampled reach is beyond the arm
FOLD_SLACK_RAD = np.deg2rad(5.0)  # joint limits within this of where the arm folds are the same limits


def cell_warnings(config: CellConfig, seed: int = 0) -> list[str]:
    """What to question in `config`, one sentence each with the key and the remedy; empty when nothing."""
    return [
        *_settle(config),
        *_speeds(config),
        *_box_beyond_reach(config, seed),
        *_folding_limits(config),
        *_urdf_notes(config),
    ]


def _urdf_notes(config: CellConfig) -> list[str]:
    """What reading the cell's URDF decided (a base frame moved onto joint 1's axis, masses left out): the
    envelope and keep-out boxes are written in the model's base frame."""
    if config.robot_file_text is None or not is_urdf_spec(config.robot_model):
        return []
    notes = import_urdf(config.robot_file_text, config.robot_model).notes
    return [f"robot.model: {note}" for note in notes]


def _settle(config: CellConfig) -> list[str]:
    if config.settle_s <= SETTLE_PLAUSIBLE_S:
        return []
    hours = config.settle_s * TYPICAL_GRID_POINTS / 3600.0
    return [
        f"motion.settle_s = {config.settle_s:g} s: every point waits that long (a {TYPICAL_GRID_POINTS}-point grid "
        f"waits {hours:.1f} h); an arm and an SMR settle in 0.1-2 s: is it milliseconds meant as seconds?"
    ]


def _speeds(config: CellConfig) -> list[str]:
    out = []
    for key, default, unit in (
        ("joint_speed", DEFAULT_JOINT_SPEED_RAD_S, "rad/s"),
        ("linear_speed", DEFAULT_LINEAR_SPEED_M_S, "m/s"),
    ):
        value = float(config.robot_driver.get(key, default))
        if value > 2 * default:
            out.append(
                f"robot.{key} = {value:g} {unit}: more than twice the default {default:g} {unit}; a measurement run "
                "gains little from speed and a new cell should move slowly: lower it"
            )
    return out


def _box_beyond_reach(config: CellConfig, seed: int) -> list[str]:
    """A box face farther from the base origin than the SMR can be: the box does not limit the SMR there."""
    nominal, env = config.nominal, config.envelope
    rng = np.random.default_rng(seed)
    lo = np.maximum(nominal.joint_limits[:, 0], env.joint_min_rad)
    hi = np.minimum(nominal.joint_limits[:, 1], env.joint_max_rad)
    q = rng.uniform(lo, hi, (REACH_SAMPLES, nominal.n_joints))
    flange = forward_kinematics(nominal, q)[:, :3, 3]
    tool = float(np.max(np.linalg.norm(config.nests_flange_m, axis=1)))
    reach = float(np.max(np.linalg.norm(flange, axis=1))) + tool
    farthest = float(np.max(np.abs(np.concatenate([env.box_min_m, env.box_max_m]))))  # the farthest face
    if farthest <= REACH_SLACK * reach:
        return []
    return [
        f"envelope: the box reaches out {farthest * 1e3:.0f} mm from the robot base where the SMR can be at most "
        f"{reach * 1e3:.0f} mm away: it does not bound the arm there; shrink box_min_mm / box_max_mm to the "
        "volume to measure"
    ]


def _folding_limits(config: CellConfig) -> list[str]:
    """Joint limits beyond where the arm, from its home pose, folds into itself (each joint turned alone)."""
    if config.bodies is None:
        return []
    env, nominal, home = config.envelope, config.nominal, np.asarray(config.q_home_rad, float)
    out = []
    remedy = (
        "the collision checks refuse such poses; narrowing the limits says so in the cell config"
        if env.bodies is not None
        else "or turn [envelope] collisions back on"
    )
    for j in range(nominal.n_joints):
        lo, hi = clear_range_rad(config.bodies, nominal, home, j)
        if env.joint_min_rad[j] < lo - FOLD_SLACK_RAD or env.joint_max_rad[j] > hi + FOLD_SLACK_RAD:
            out.append(
                f"envelope: joint {j + 1} may turn {np.rad2deg(env.joint_min_rad[j]):.0f}..{np.rad2deg(env.joint_max_rad[j]):.0f} "
                f"deg, but from the home pose the arm folds into itself outside {np.rad2deg(lo):.0f}..{np.rad2deg(hi):.0f} "
                f"deg: narrow [envelope] joint_min_deg / joint_max_deg ({remedy})"
            )
    return out
