"""Visit planned joints on the simulated cell and return what the tracker measured, in the dataset contract.

Planning the joints is the planners' job (hil.planners, as the procedures do); visiting them on the
simulated cell, as a real cell would, is the fake's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from fakes.cell import SimulatedCell
from hil.dataset import make_dataset
from hil.ik import solve_ik


def simulate_campaign(
    cell: SimulatedCell, q_cmd: np.ndarray, smr_id: int = 1, seconds_per_point: float = 4.0
) -> pd.DataFrame:
    """Visit q_cmd (N, 6) in order on the cell and return the rows of the dataset contract."""
    r = cell.run_sequence(q_cmd, smr_id=smr_id, seconds_per_point=seconds_per_point)
    loc = cell.smr_location(smr_id)
    return make_dataset(
        r["q_encoder"],
        r["p_tracker_measured"],
        t_s=r["t_s"],
        temperature_c=r["temperature_c"],
        smr=loc.index if loc.kind == "nest" else 0,
    )


# ---- Only for hil/commands/demo.py, which imports grid_joints and random_joints until its rewrite on the
# ---- runner lands; then delete everything below (the planners in hil.planners replace it).

def workspace_box(cell: SimulatedCell) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and axes (3, 3, columns scaled to half-extents) of a reachable box facing the tracker."""
    reach = float(np.sum(np.abs(cell.nominal.a)) + np.sum(np.abs(cell.nominal.d[1:])) * 0.3)
    p_base_tracker = np.linalg.inv(cell.T_tracker_base)[:3, 3]
    towards = p_base_tracker[:2] / np.linalg.norm(p_base_tracker[:2])
    forward = np.array([towards[0], towards[1], 0.0])
    lateral = np.array([-towards[1], towards[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    centre = 0.55 * reach * forward + 0.25 * reach * up
    half = np.array([0.22, 0.32, 0.22]) * reach
    return centre, np.column_stack([forward * half[0], lateral * half[1], up * half[2]])


def _facing_targets(
    cell: SimulatedCell, points_base: np.ndarray, rng: np.random.Generator, tilt_deg: float
) -> np.ndarray:
    """Tool-point poses (N, 4, 4) whose z axis looks at the tracker within `tilt_deg`, rolled randomly."""
    p_base_tracker = np.linalg.inv(cell.T_tracker_base)[:3, 3]
    z = p_base_tracker - points_base
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    helper = np.where(np.abs(z[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=2)
    # Tilt the facing direction by at most `tilt_deg` (so the SMR stays inside its acceptance cone)
    # and roll freely about it: diverse orientations for identification, all visible to the tracker.
    count = len(points_base)
    tilt_axis = rng.normal(0, 1, (count, 2))
    tilt_axis /= np.linalg.norm(tilt_axis, axis=1, keepdims=True)
    tilt_angle = np.deg2rad(tilt_deg) * np.sqrt(rng.uniform(0, 1, count))
    tilt_vec = np.column_stack([tilt_axis * tilt_angle[:, None], np.zeros(count)])
    roll_vec = np.column_stack([np.zeros((count, 2)), rng.uniform(-np.pi / 2, np.pi / 2, count)])
    tilt = Rotation.from_rotvec(tilt_vec).as_matrix() @ Rotation.from_rotvec(roll_vec).as_matrix()
    T = np.zeros((len(points_base), 4, 4))
    T[:, :3, :3] = R @ tilt
    T[:, :3, 3] = points_base
    T[:, 3, 3] = 1.0
    return T


def _joints_for_points(
    cell: SimulatedCell, points_base: np.ndarray, rng: np.random.Generator, smr_nest: int, tilt_deg: float
) -> np.ndarray:
    """Joints (M, 6) reaching those tool points with the SMR facing the tracker; unreachable ones dropped."""
    p_nest = np.array(cell.config.tool_nests_flange_m[smr_nest - 1])  # the drawing, not the truth
    T_flange_tool = np.eye(4)
    T_flange_tool[:3, 3] = p_nest
    targets = _facing_targets(cell, points_base, rng, tilt_deg)
    q_near = np.array(cell.config.q_home_rad)
    result = solve_ik(cell.nominal, targets, q_near=q_near, mode="pose", T_flange_tool=T_flange_tool)
    return result.q[result.success]


def grid_joints(cell: SimulatedCell, step_m: float = 0.2, smr_nest: int = 1, seed: int = 0) -> np.ndarray:
    """Joints for every reachable vertex of a Cartesian grid of `step_m` (0.1-0.2 m) in front of the tracker."""
    if not 0.02 <= step_m <= 0.5:
        raise ValueError(f"grid step {step_m} m is outside 0.02..0.5 m (the papers use 0.1-0.2 m)")
    centre, axes = workspace_box(cell)
    half = np.linalg.norm(axes, axis=0)
    ticks = [np.arange(-h, h + 1e-9, step_m) for h in half]
    ticks = [t - t.mean() for t in ticks]
    grid = np.stack(np.meshgrid(*ticks, indexing="ij"), axis=-1).reshape(-1, 3)
    unit = axes / half
    points = centre + grid @ unit.T
    return _joints_for_points(cell, points, np.random.default_rng(seed), smr_nest, tilt_deg=20.0)


def random_joints(cell: SimulatedCell, count: int, smr_nest: int = 1, seed: int = 1) -> np.ndarray:
    """Joints for `count` random reachable tool points in the same box (held-out poses)."""
    rng = np.random.default_rng(seed)
    centre, axes = workspace_box(cell)
    out = np.zeros((0, 6))
    while len(out) < count:
        u = rng.uniform(-1, 1, (2 * count, 3))
        q = _joints_for_points(cell, centre + u @ axes.T, rng, smr_nest, tilt_deg=20.0)
        out = np.vstack([out, q])
    return out[:count]
