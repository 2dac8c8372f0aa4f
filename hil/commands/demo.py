"""`hil demo`: the main job on the simulated cell (grows as the project grows)."""

from __future__ import annotations

import argparse

import numpy as np

from hil.kinematics import forward_kinematics
from hil.robots import get_robot


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the main job on a simulated cell")
    parser.add_argument("--robot", default="ur10", help="robot model (default ur10)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    model = get_robot(args.robot)
    q = np.deg2rad([[0, -90, 90, -90, -90, 0], [30, -60, 80, -110, -90, 20]])
    for T in forward_kinematics(model, q):
        print(np.round(T[:3, 3] * 1000, 3))
    return 0
