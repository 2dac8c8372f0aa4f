"""Collision-check benchmark: a 400-pose plan of the default simulated cell, every pose and every path.

Run:  PYTHONPATH=. python benchmarks/collision.py [--poses 400] [--repeats 3]

The plan is the grid sampling procedure's (100 mm grid plus validation poses) on the UR10 cell `hil sim`
writes for seed 0, cut to --poses. Timed: the pose check (the arm with itself, the tracker, the keep-out
boxes; Envelope.outside, which also judges the box and the joint limits) and the path check of every
consecutive move from home (Envelope.path_problems, the adaptive sampling with its displacement bound),
each the best of --repeats on this shared machine. Printed too: how many configurations the path check
evaluated, and the smallest clearances found. Then what an engineer waits for at `hil run --dry-run` on that
cell: each procedure's plan (the clear configurations, the clear travel order, the moves no safe path
reaches left out) and its description (every move's path checked again, the clearances), best of --repeats.
"""

from __future__ import annotations

import argparse
import time
import tomllib
from dataclasses import replace

import numpy as np

from hil.geometry.collision import KeepOutBox
from hil.runner import registry
from hil.runner.cell_config import parse_cell_config
from procedures import grid_sampling
from tests.cell_fixtures import sim_cell_toml


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["collisions"] = True
    config = parse_cell_config(data)
    plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.1, validation=300, seed=0)
    q = plan.joints()[: args.poses]
    env, nominal = config.envelope, config.nominal
    assert env.bodies is not None
    # one keep-out box beside the arm (a fixture table), so the box distances are timed too
    fixture = KeepOutBox("fixture", np.array([-1.2, -1.2, -0.3]), np.array([-0.6, -0.6, 0.1]))
    bodies = replace(env.bodies, keep_out=(fixture,))
    env = replace(env, bodies=bodies)
    q_from = np.vstack([config.q_home_rad, q[:-1]])
    best_pose, best_path = np.inf, np.inf
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        outside = env.outside(nominal, q, config.nests_flange_m)
        t1 = time.perf_counter()
        problems = env.path_problems(nominal, q_from, q)
        t2 = time.perf_counter()
        best_pose, best_path = min(best_pose, t1 - t0), min(best_path, t2 - t1)
    found = bodies.clearances(nominal, q)
    print(f"plan: {len(q)} poses ({config.robot_model}, grid 100 mm + validation), {len(q)} moves from home")
    print(
        f"pose check (box, limits, self, tracker, 1 keep-out box): {best_pose * 1e3:.1f} ms, {int(outside.sum())} refused"
    )
    print(
        f"path check of every move: {best_path * 1e3:.1f} ms, {sum(p is not None for p in problems)} refused"
    )
    print(f"pose + paths: {(best_pose + best_path) * 1e3:.1f} ms (best of {args.repeats})")
    print(
        f"smallest clearance: to itself {found.self_m.min() * 1e3:.0f} mm ({found.self_between[int(np.argmin(found.self_m))]}), "
        f"to the cell {found.cell_m.min() * 1e3:.0f} mm ({found.cell_between[int(np.argmin(found.cell_m))]})"
    )

    print(f"{'procedure':<16}{'poses':>7}{'plan_ms':>10}{'dry_run_ms':>12}")
    plain = parse_cell_config(tomllib.loads(sim_cell_toml()))
    for name in ("registration", "tool_fit", "grid_sampling", "iso9283", "joint_axes"):
        procedure = registry.load(name)
        best_plan = best_describe = np.inf
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            made = procedure.make_plan(plain)
            t1 = time.perf_counter()
            made.describe()
            t2 = time.perf_counter()
            best_plan, best_describe = min(best_plan, t1 - t0), min(best_describe, t2 - t1)
        print(f"{name:<16}{len(made.poses):>7}{best_plan * 1e3:>10.0f}{best_describe * 1e3:>12.0f}")


if __name__ == "__main__":
    main()
