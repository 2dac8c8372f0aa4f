"""`hil demo`: the main job on the simulated cell (grows as the project grows)."""

from __future__ import annotations

import argparse

import numpy as np

from fakes.cell import CellConfig, SimulatedCell
from hil.kinematics import forward_kinematics


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the main job on a simulated cell")
    parser.add_argument("--robot", default="ur10", help="robot model (default ur10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cell = SimulatedCell(CellConfig(robot=args.robot, seed=args.seed))
    poses_deg = np.array(
        [
            [0, -90, 90, -90, -90, 0],
            [30, -60, 80, -110, -90, 20],
            [-45, -100, 110, -80, -80, 45],
            [90, -45, 60, -120, -90, -30],
        ]
    )
    print(f"simulated {cell.robot_name} (seed {args.seed}): nominal vs physical flange position, mm")
    print(
        f"{'pose':>4} {'x_nom':>9} {'y_nom':>9} {'z_nom':>9}   {'x_true':>9} {'y_true':>9} {'z_true':>9}  {'err':>6}"
    )
    for k, q in enumerate(np.deg2rad(poses_deg), start=1):
        cell.set_commanded_joints(q)
        cell.advance_time(4.0)
        p_nominal = forward_kinematics(cell.nominal, cell.encoder_joints())[0, :3, 3] * 1e3
        p_true = cell.T_base_flange_true()[:3, 3] * 1e3
        err = np.linalg.norm(p_true - p_nominal)
        print(
            f"{k:>4} {p_nominal[0]:9.3f} {p_nominal[1]:9.3f} {p_nominal[2]:9.3f}   "
            f"{p_true[0]:9.3f} {p_true[1]:9.3f} {p_true[2]:9.3f}  {err:6.3f}"
        )
    return 0
