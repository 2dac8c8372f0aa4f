"""Program compensation at production scale: `hil compensate MODEL PROGRAM.script -o OUT.script` timed on a long
URScript program, as a cell engineer runs it (a fresh process: interpreter start, imports, parsing, the loop,
the rewrite).

Run:  PYTHONPATH=. python benchmarks/program_compensation.py [--waypoints 10000] [--case realistic]

Model: benchmarks/compensation.py's calibrated UR10 (`--case`). Program: what PolyScope writes when it saves a
program as script, `--waypoints` waypoints along a smooth joint path through the workspace (a
`Waypoint_n_p` / `Waypoint_n_q` pair each, moved to by `movej(get_inverse_kin(..., qnear=...))`, every
other one by `movel` to the pose variable), the TCP at the model's SMR point. The poses are the nominal
arm's at the path's joints: what offline programming puts in a program. The compensated program is checked
by the model itself: each written joint list's predicted SMR pose against the program's pose.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from compensation import CASES, TOOL, calibrated_ur10  # benchmarks/compensation.py (same directory)

from hil.compensation.program import smr_targets
from hil.compensation.target_update import pose_errors
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import make_transform, transform_to_pose

# The path's joints: each joint sweeps about its working pose with a few incommensurate periods over the
# program (UR10 workspace in front of the base, elbow up, wrist clear of its singularity).
PATH_CENTRE_RAD = np.array([0.3, -1.6, 1.7, -1.7, -1.57, 0.0])
PATH_SWING_RAD = np.array([1.2, 0.45, 0.5, 0.6, 0.5, 1.5])
PATH_PERIODS = np.array([3.0, 5.0, 7.0, 4.0, 6.0, 2.0])


def path_joints(n: int) -> np.ndarray:
    """(n, 6) joints along a smooth closed path: consecutive waypoints a few millidegrees to a degree apart."""
    s = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
    return PATH_CENTRE_RAD + PATH_SWING_RAD * np.sin(2 * np.pi * PATH_PERIODS * s + np.arange(6))


def literal(v: np.ndarray) -> str:
    return "p[" + ", ".join(f"{x:.9f}" for x in v) + "]"


def program_text(poses: np.ndarray, q: np.ndarray) -> str:
    """A PolyScope-style saved program moving through the TCP poses (UR pose vectors, base frame)."""
    lines = [
        "def Program():",
        "  set_standard_analog_input_domain(0, 1)",
        f"  set_tcp({literal([*TOOL, 0, 0, 0])})",
    ]
    for k in range(len(poses)):
        joints = "[" + ", ".join(f"{v:.9f}" for v in q[k]) + "]"
        lines += [f"  global Waypoint_{k + 1}_p={literal(poses[k])}", f"  global Waypoint_{k + 1}_q={joints}"]
    lines.append('  $ 1 "Robot Program"')
    for k in range(len(poses)):
        lines.append(f'  $ {k + 2} "Waypoint_{k + 1}"')
        if k % 2:
            lines.append(f"  movel(Waypoint_{k + 1}_p, a=1.2, v=0.25)")
        else:
            lines.append(
                f"  movej(get_inverse_kin(Waypoint_{k + 1}_p, qnear=Waypoint_{k + 1}_q), a=1.39, v=1.04)"
            )
    return "\n".join([*lines, "end"]) + "\n"


def written_joints(text: str, n: int) -> np.ndarray:
    """The joint lists the compensated program moves to, in motion order (n, 6)."""
    found = re.findall(r"move[jl]\(\[([^\]]*)\]", text)
    if len(found) != n:
        raise SystemExit(f"the compensated program moves to {len(found)} joint lists, not {n}")
    return np.array([[float(v) for v in row.split(",")] for row in found])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--waypoints", type=int, default=10000)
    ap.add_argument("--case", default="realistic", choices=CASES)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = calibrated_ur10(args.seed, args.case)
    q = path_joints(args.waypoints)
    T_base_flange = forward_kinematics(model.nominal, q)
    poses = transform_to_pose(T_base_flange @ make_transform(np.eye(3), TOOL))
    with tempfile.TemporaryDirectory() as tmp:
        model_path, program, out = (
            Path(tmp, "model.json"),
            Path(tmp, "program.script"),
            Path(tmp, "out.script"),
        )
        model.save(model_path)
        program.write_text(program_text(poses, q))
        cmd = [sys.executable, "-m", "hil", "compensate", str(model_path), str(program), "-o", str(out)]
        t0 = time.perf_counter()
        run = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if run.returncode != 0:
            raise SystemExit(f"hil compensate failed ({run.returncode}):\n{run.stdout}\n{run.stderr}")
        q_out = written_joints(out.read_text(), args.waypoints)
        size_mb = program.stat().st_size / 1e6
    dp, dr = pose_errors(model.predict_poses(q_out), smr_targets(model, T_base_flange, TOOL))
    before, _ = pose_errors(model.predict_poses(q), smr_targets(model, T_base_flange, TOOL))
    print(
        f"hil compensate, {args.case} model, {args.waypoints} waypoints ({size_mb:.1f} MB of URScript): "
        f"{wall:.2f} s wall in a fresh process ({args.waypoints / wall:,.0f} waypoints/s)"
    )
    print(
        f"predicted SMR error at the program's own joints: mean {np.mean(before) * 1e3:.3f} mm, max "
        f"{np.max(before) * 1e3:.3f} mm; at the compensated joints: mean {np.mean(dp) * 1e6:.2f} um, max "
        f"{np.max(dp) * 1e6:.2f} um, rotation max {np.rad2deg(np.max(dr)) * 1e3:.3f} mdeg"
    )
    print("hil's own summary:", *run.stdout.strip().splitlines()[-3:], sep="\n  ")


if __name__ == "__main__":
    main()
