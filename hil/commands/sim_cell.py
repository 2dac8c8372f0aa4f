"""The cell configuration of a simulated cell, as an engineer would write it for a real one.

From the simulator's ready line and what an engineer can know without a tracker: the robot model and
address, the tracker's URL and roughly where it stands (to 50 mm, as with a tape measure), the tool drawing
(nest positions, flange holes) and a safety box around the arm's reach. Nothing of the hidden truth (the
robot's errors, the true nests) goes in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.geometry.ik import reach_bound
from hil.geometry.robots import get_robot
from hil.runner.cell_config import SMR_RADIUS_MM, format_cell_toml


def sim_cell_values(info: dict, truth: dict, time_scale: float) -> dict[str, dict]:
    """cell.toml sections for the simulated cell announced by `info` (hil sim's ready line)."""
    model = info["robot"]["model"]
    config = truth["config"]
    T_tracker_base = np.asarray(truth["T_tracker_base"], float)
    p_base_tracker_mm = np.linalg.inv(T_tracker_base)[:3, 3] * 1e3
    reach_mm = (reach_bound(get_robot(model)) + 0.15) * 1e3
    # The driver's settle dwell is wall time; the simulated cell runs `time_scale` times faster.
    settle_s = round(1.0 / time_scale, 4)
    return {
        "robot": {"model": model, "host": info["robot"]["host"], "settle_dwell_s": settle_s},
        "tracker": {
            "url": info["tracker"]["url"],
            "meas_time_s": 0.5,
            "shots_per_point": 3,
            "position_base_mm": [float(v) for v in np.round(p_base_tracker_mm / 50.0) * 50.0],
        },
        "tool": {
            "nests_flange_mm": [[round(v * 1e3, 3) for v in nest] for nest in config["tool_nests_flange_m"]],
            "smr_radius_mm": SMR_RADIUS_MM,
            "hole_circle_radius_mm": config["hole_circle_radius_m"] * 1e3,
            "hole7_radius_mm": config["hole7_radius_m"] * 1e3,
            "hole_diameter_mm": config["hole_diameter_m"] * 1e3,
        },
        "envelope": {
            "box_min_mm": [-round(reach_mm), -round(reach_mm), -200.0],
            "box_max_mm": [round(reach_mm), round(reach_mm), round(reach_mm)],
        },
        # the simulated cell needs no first motions at reduced speed (nothing there to hit)
        "motion": {"settle_s": settle_s, "reduced_speed": False},
        "simulator": {"control": info["control"]},
    }


def write_sim_cell(path: str | Path, info: dict, truth: dict, time_scale: float) -> None:
    """Write the cell.toml of a simulated cell (see sim_cell_values)."""
    header = (
        f"# Cell configuration of a simulated cell (hil sim, {info['robot']['model']}, seed {truth.get('seed')}).\n"
        "# Lengths in mm, angles in degrees; `hil cell check` explains every key.\n\n"
    )
    Path(path).write_text(header + format_cell_toml(sim_cell_values(info, truth, time_scale)))
