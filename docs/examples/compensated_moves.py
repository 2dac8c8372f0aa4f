"""A shop-floor script whose moves land where they are meant: the robot driver wrapped with a calibrated model.

    python docs/examples/compensated_moves.py cell.toml model.json [--side-mm 100] [--temperature-c 21.5]

The script opens the robot the cell names (cell.toml: robot.driver, robot.host), wraps it in
`hil.compensation.online.CompensatedRobot` with the model (model.json from `hil diagnose -o`), and moves
the TCP (the model's SMR point in nest 1) through the corners of a square in the base frame's XY plane
around where it stands, keeping its orientation. Each corner is compensated before the robot moves, so the
real arm puts the TCP on the corner, not where the controller's nominal kinematics would. One JSON line per
corner on stdout: the pose asked for (base frame, m) and the joints commanded.

On the simulated cell (`hil sim --write-cell cell.toml`, then `hil run registration`, `hil run grid_sampling`
and `hil diagnose` for the model) it runs as on a real one.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from hil.compensation.online import CompensatedRobot, OnlineOptions
from hil.geometry.kinematics import forward_kinematics
from hil.instruments.plugins import robot_driver
from hil.model.calibrated_model import CalibratedModel
from hil.runner.cell_config import load_cell_config


def square_corners(T_base_tcp: np.ndarray, side_m: float) -> np.ndarray:
    """Four poses (4, 4, 4): the corners of a square of `side_m` centred on the pose, same orientation."""
    half = side_m / 2
    out = np.repeat(T_base_tcp[None], 4, axis=0)
    for k, (dx, dy) in enumerate([(-half, -half), (half, -half), (half, half), (-half, half)]):
        out[k, :3, 3] += (dx, dy, 0.0)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cell", help="cell.toml")
    parser.add_argument("model", help="model.json of the calibrated robot")
    parser.add_argument("--side-mm", type=float, default=100.0, help="side of the square (mm)")
    parser.add_argument("--temperature-c", type=float, default=None, help="cell temperature (degC)")
    args = parser.parse_args(argv)
    config = load_cell_config(args.cell)
    model = CalibratedModel.load(args.model)
    robot = robot_driver(config.robot_driver_name).open(config.robot_mapping())
    try:
        arm = CompensatedRobot(robot, model, OnlineOptions(temperature_c=args.temperature_c))
        T_now = (
            forward_kinematics(model.kinematic, np.asarray(robot.joints(), float)[None])[0] @ arm.T_flange_tcp
        )
        for T in square_corners(T_now, args.side_mm / 1000.0):
            q = arm.move_to(T)
            robot.wait_settled()
            print(json.dumps({"T_base_tcp": T.tolist(), "q_rad": q.tolist()}), flush=True)
    finally:
        robot.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
