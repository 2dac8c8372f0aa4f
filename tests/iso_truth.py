"""The simulated cell's truth for the ISO 9283 checks (the sim test and benchmarks/iso9283.py): where the cell
really puts an SMR at given joints, and the true SMR path of a moveL through a path run's flange waypoints."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fakes.cell import SimulatedCell
from hil.runner.cell_config import CellConfig
from hil.runner.planners import plan_joints
from procedures import iso9283


def true_smr_points(sim: SimulatedCell, q: np.ndarray, nest: int = 0) -> np.ndarray:
    """Where the cell really puts the SMR of tool nest `nest` (0-based) at joints q (N, 6) approached from
    below, tracker frame (N, 3), m."""
    truth = sim.ground_truth()
    _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
    T = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
    p_nest = np.asarray(truth["tool_nests_flange_m"][nest])
    return T[:, :3, :3] @ p_nest + T[:, :3, 3] + np.asarray(truth["smr_centering_m"][nest])


def true_path(
    sim: SimulatedCell, config: CellConfig, run: iso9283.PathRun, step_m: float = 0.002
) -> np.ndarray:
    """The true SMR path (N, 3, tracker frame) of a moveL through the run's flange waypoints: every `step_m`
    the controller's joints (nominal IK of the interpolated flange pose) and the cell's truth at them."""
    T = run.T_base_flange
    dense = [T[:1]]
    for a, b in zip(T[:-1], T[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b[:3, 3] - a[:3, 3]) / step_m)))
        f = np.arange(1, n + 1) / n
        seg = np.tile(np.eye(4), (n, 1, 1))
        seg[:, :3, :3] = Slerp([0, 1], Rotation.from_matrix([a[:3, :3], b[:3, :3]]))(f).as_matrix()
        seg[:, :3, 3] = a[:3, 3] + f[:, None] * (b[:3, 3] - a[:3, 3])
        dense.append(seg)
    T_tool = np.concatenate(dense)
    p_nest = config.nests_flange_m[0]
    T_tool[:, :3, 3] += T_tool[:, :3, :3] @ p_nest
    return true_smr_points(sim, plan_joints(config.nominal, T_tool, p_nest, q_near=run.q_start).q)
