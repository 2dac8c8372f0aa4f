"""`hil cell check` questions what a cell engineer would question before the first motion: a settle time that
multiplies every point, speeds above a measurement run's, a box the arm cannot fill, joint limits wider than
the arm can use without folding into itself; a sensible cell draws none of them."""

from __future__ import annotations

import tomllib

import numpy as np
from cell_fixtures import sim_cell_toml

from hil.runner.cell_config import parse_cell_config
from hil.runner.cell_warnings import cell_warnings


def _config(**sections):
    data = tomllib.loads(sim_cell_toml())
    for section, values in sections.items():
        data.setdefault(section, {}).update(values)
    return parse_cell_config(data)


SENSIBLE = {
    "envelope": {
        "box_min_mm": [-1300, -1300, -200],
        "box_max_mm": [1300, 1300, 1400],
        "joint_min_deg": [-360, -360, -150, -320, -145, -360],
        "joint_max_deg": [360, 360, 150, -10, 170, 360],
    }
}


def test_a_sensible_cell_draws_no_warning():
    assert cell_warnings(_config(**SENSIBLE)) == []


def test_a_settle_time_in_the_wrong_unit_is_questioned():
    (warning,) = cell_warnings(_config(**SENSIBLE, motion={"settle_s": 50}))
    assert "motion.settle_s = 50 s" in warning and "5.6 h" in warning


def test_a_fast_robot_is_questioned():
    (warning,) = cell_warnings(_config(**SENSIBLE, robot={"joint_speed": 3.0}))
    assert warning.startswith("robot.joint_speed = 3 rad/s") and "lower it" in warning


def test_a_box_beyond_the_arm_and_limits_that_fold_it_are_questioned():
    warnings = cell_warnings(_config(envelope={**SENSIBLE["envelope"], "box_max_mm": [3000, 1300, 1400]}))
    assert len(warnings) == 1 and "reaches out 3000 mm" in warnings[0]
    folded = cell_warnings(
        _config(envelope={**SENSIBLE["envelope"], "joint_max_deg": [360, 360, 230, -10, 170, 360]})
    )
    assert len(folded) == 1 and folded[0].startswith("envelope: joint 3 may turn -150..230 deg")
    lo, hi = (float(v) for v in folded[0].split("outside ")[1].split(" deg")[0].split(".."))
    assert lo < -150 and 150 < hi < 230 and np.isfinite(lo)  # the elbow folds between the limits allowed
