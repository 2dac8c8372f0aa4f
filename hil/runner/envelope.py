"""The safety envelope: a box in the robot base frame for the tool points and every wrist point, plus
joint limits. Every commanded motion is checked against it, along its whole path, before the robot moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.kinematics import KinematicModel, forward_kinematics, link_frames
from hil.runner.planners import wrist_points

# Samples per joint move when checking its path: moveJ interpolates linearly in joint space, so the
# tool sweeps a smooth curve; 1 degree of the largest joint travel per sample, at least 8.
_PATH_STEP_RAD = np.deg2rad(1.0)
_MIN_SAMPLES = 8


class EnvelopeError(ValueError):
    """A commanded pose or path leaves the configured envelope; nothing moved."""


@dataclass(frozen=True)
class Envelope:
    """Where the robot may go: an axis-aligned box (base frame, metres) and joint limits (radians)."""

    box_min_m: np.ndarray
    box_max_m: np.ndarray
    joint_min_rad: np.ndarray
    joint_max_rad: np.ndarray

    def point_violations(self, points_m: np.ndarray) -> np.ndarray:
        """(...,) bool: which points lie outside the box."""
        p = np.asarray(points_m, float)
        return np.any((p < self.box_min_m) | (p > self.box_max_m), axis=-1)

    def joint_violations(self, q: np.ndarray) -> np.ndarray:
        """(N,) bool: which joint sets break a joint limit."""
        q = np.atleast_2d(q)
        return np.any((q < self.joint_min_rad) | (q > self.joint_max_rad), axis=1)

    def outside(self, nominal: KinematicModel, q: np.ndarray, p_flange_tools_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which joint sets put a tool point or a wrist point outside, or break a joint limit."""
        q = np.atleast_2d(np.asarray(q, float))
        tools = np.atleast_2d(np.asarray(p_flange_tools_m, float))
        frames = link_frames(nominal, q)  # one chain for the wrist points and the flange
        T = frames[:, -1] @ nominal.T_last_flange
        tool_points = np.einsum("nij,kj->nki", T[:, :3, :3], tools) + T[:, None, :3, 3]
        wrist = np.concatenate([frames[:, 4:7, :3, 3], T[:, None, :3, 3]], axis=1)
        return (
            self.joint_violations(q)
            | self.point_violations(tool_points).any(axis=1)
            | self.point_violations(wrist).any(axis=1)
        )

    def pose_problems(
        self, nominal: KinematicModel, q: np.ndarray, p_flange_tools_m: np.ndarray
    ) -> list[str | None]:
        """Per joint set (N, 6): None if inside, else what is outside (nominal FK with the tool points)."""
        q = np.atleast_2d(np.asarray(q, float))
        tools = np.atleast_2d(np.asarray(p_flange_tools_m, float))
        T = forward_kinematics(nominal, q)
        tool_points = np.einsum("nij,kj->nki", T[:, :3, :3], tools) + T[:, None, :3, 3]
        wrist = wrist_points(nominal, q)
        bad_joints = self.joint_violations(q)
        bad_tool = self.point_violations(tool_points)  # (N, K)
        bad_wrist = self.point_violations(wrist)  # (N, 4)
        problems: list[str | None] = []
        wrist_names = ("wrist 1", "wrist 2", "wrist 3", "flange")
        for i in range(len(q)):
            parts = []
            if bad_joints[i]:
                joints = np.flatnonzero((q[i] < self.joint_min_rad) | (q[i] > self.joint_max_rad)) + 1
                parts.append(f"joint(s) {', '.join(map(str, joints))} beyond their envelope limits")
            for k in np.flatnonzero(bad_tool[i]):
                p = tool_points[i, k] * 1e3
                parts.append(f"tool point {k + 1} at ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f}) mm outside the box")
            for k in np.flatnonzero(bad_wrist[i]):
                p = wrist[i, k] * 1e3
                parts.append(f"{wrist_names[k]} at ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f}) mm outside the box")
            problems.append("; ".join(parts) if parts else None)
        return problems

    def check_poses(
        self,
        nominal: KinematicModel,
        q: np.ndarray,
        p_flange_tools_m: np.ndarray,
        labels: list[str] | None = None,
    ) -> None:
        """Raise EnvelopeError naming every joint set (N, 6) that leaves the envelope."""
        q = np.atleast_2d(np.asarray(q, float))
        flagged = np.flatnonzero(self.outside(nominal, q, p_flange_tools_m))
        if flagged.size:
            problems = self.pose_problems(nominal, q[flagged], p_flange_tools_m)
            bad = list(zip(flagged, problems, strict=True))
            names = labels or [f"pose {i + 1}" for i in range(len(q))]
            lines = [f"{names[i]}: {p}" for i, p in bad[:5]]
            more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
            raise EnvelopeError(
                f"{len(bad)} commanded pose(s) leave the safety envelope{more}: "
                + " | ".join(lines)
                + "; nothing moved: shrink the sampling box or widen [envelope] in the cell config"
            )

    def check_joint_move(
        self, nominal: KinematicModel, q_from: np.ndarray, q_to: np.ndarray, p_flange_tools_m: np.ndarray
    ) -> None:
        """Check the whole path of a joint move (moveJ interpolates linearly in joint space)."""
        q_from, q_to = np.asarray(q_from, float), np.asarray(q_to, float)
        travel = float(np.max(np.abs(q_to - q_from)))
        samples = max(_MIN_SAMPLES, int(np.ceil(travel / _PATH_STEP_RAD)) + 1)
        s = np.linspace(0.0, 1.0, samples)[:, None]
        path = q_from + s * (q_to - q_from)
        bad = np.flatnonzero(self.outside(nominal, path, p_flange_tools_m))
        if bad.size:
            i = int(bad[0])
            where = "at the target" if i == samples - 1 else f"{100 * s[i, 0]:.0f} % along the move"
            problem = self.pose_problems(nominal, path[i][None], p_flange_tools_m)[0]
            raise EnvelopeError(
                f"the joint move leaves the safety envelope {where}: {problem}; nothing moved: "
                "plan another path (e.g. through a safe intermediate pose) or widen [envelope]"
            )

    def check_linear_move(
        self, T_base_flange_from: np.ndarray, T_base_flange_to: np.ndarray, p_flange_tools_m: np.ndarray
    ) -> None:
        """Check a straight-line flange move: the tool points and the flange along the whole segment."""
        from scipy.spatial.transform import Rotation, Slerp

        A, B = np.asarray(T_base_flange_from, float), np.asarray(T_base_flange_to, float)
        length = float(np.linalg.norm(B[:3, 3] - A[:3, 3]))
        samples = max(_MIN_SAMPLES, int(np.ceil(length / 0.005)) + 1)
        s = np.linspace(0.0, 1.0, samples)
        rotations = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))(s).as_matrix()
        origins = A[:3, 3] + s[:, None] * (B[:3, 3] - A[:3, 3])
        tools = np.atleast_2d(np.asarray(p_flange_tools_m, float))
        points = np.concatenate(
            [origins[:, None, :], np.einsum("nij,kj->nki", rotations, tools) + origins[:, None, :]], axis=1
        )
        bad = np.flatnonzero(np.any(self.point_violations(points), axis=1))
        if bad.size:
            p = origins[bad[0]] * 1e3
            raise EnvelopeError(
                f"the linear move leaves the safety envelope {100 * s[bad[0]]:.0f} % along the segment "
                f"(flange near ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f}) mm); nothing moved"
            )
