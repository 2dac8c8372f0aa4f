"""The safety envelope: a box in the robot base frame for the tool points and every wrist point, joint
limits, the interaction limits of a robot whose controller couples its joints (hil.geometry.coupling), and
the collision checks of hil.geometry.collision (the arm with itself, the tracker, the keep-out boxes). Every
commanded motion is checked against it, along its whole path, before the robot moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.collision import CellBodies, Clearances
from hil.geometry.coupling import JointCoupling
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
    """Where the robot may go: an axis-aligned box (base frame, metres), joint limits (radians, on the
    kinematic joints), the interaction limits of `coupling` (linear inequalities on the controller's joints;
    a joint move, linear in either convention, keeps them all along when both ends do) and, when `bodies` is
    given, clear of itself, the tracker and the keep-out boxes by their margins."""

    box_min_m: np.ndarray
    box_max_m: np.ndarray
    joint_min_rad: np.ndarray
    joint_max_rad: np.ndarray
    bodies: CellBodies | None = None
    coupling: JointCoupling | None = None

    def clearances(self, nominal: KinematicModel, q: np.ndarray) -> Clearances | None:
        """Each joint set's smallest clearance to the arm itself and to the cell (None: no body model)."""
        return None if self.bodies is None else self.bodies.clearances(nominal, q)

    def point_violations(self, points_m: np.ndarray) -> np.ndarray:
        """(...,) bool: which points lie outside the box."""
        p = np.asarray(points_m, float)
        return np.any((p < self.box_min_m) | (p > self.box_max_m), axis=-1)

    def joint_violations(self, q: np.ndarray) -> np.ndarray:
        """(N,) bool: which joint sets (kinematic) break a joint limit or an interaction limit."""
        q = np.atleast_2d(q)
        beyond = np.any((q < self.joint_min_rad) | (q > self.joint_max_rad), axis=1)
        if self.coupling is not None and self.coupling.limits and len(q):
            beyond |= ~self.coupling.within_limits(self.coupling.to_controller(q))
        return beyond

    def interaction_problems(self, q: np.ndarray) -> list[str]:
        """The interaction limits one joint set (kinematic) breaks, each named with the controller's value."""
        if self.coupling is None:
            return []
        q_controller = self.coupling.to_controller(np.atleast_2d(q))[0]
        return [
            f"{np.rad2deg(q_controller @ limit.coefficients):.1f} deg breaks the interaction limit "
            f"{limit.describe()}"
            for limit in self.coupling.limits
            if not limit.lower_rad <= q_controller @ limit.coefficients <= limit.upper_rad
        ]

    def outside(self, nominal: KinematicModel, q: np.ndarray, p_flange_tools_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which joint sets put a tool point or a wrist point outside, break a joint limit, or
        come closer than a margin to the arm itself, the tracker or a keep-out box."""
        q = np.atleast_2d(np.asarray(q, float))
        outside = self._outside_box(nominal, q, p_flange_tools_m)
        inside = np.flatnonzero(~outside)
        if self.bodies is not None and inside.size:  # the costly check only where the box leaves it open
            outside[inside] = self.bodies.collides(nominal, q[inside])
        return outside

    def _outside_box(
        self, nominal: KinematicModel, q: np.ndarray, p_flange_tools_m: np.ndarray
    ) -> np.ndarray:
        """(N,) bool: which joint sets put a tool point or a wrist point outside, or break a joint limit."""
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
        self, nominal: KinematicModel, q: np.ndarray, p_flange_tools_m: np.ndarray, collisions: bool = True
    ) -> list[str | None]:
        """Per joint set (N, 6): None if inside, else what is outside (nominal FK with the tool points) and,
        with `collisions`, which bodies come closer than their margin and by how much."""
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
        near = (
            self.bodies.pose_problems(nominal, q)
            if self.bodies is not None and collisions and len(q)
            else [None] * len(q)
        )
        for i in range(len(q)):
            parts: list[str] = [problem] if (problem := near[i]) else []
            if bad_joints[i]:
                joints = np.flatnonzero((q[i] < self.joint_min_rad) | (q[i] > self.joint_max_rad)) + 1
                if joints.size:
                    parts.append(f"joint(s) {', '.join(map(str, joints))} beyond their envelope limits")
                parts += self.interaction_problems(q[i])
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
        bad = np.flatnonzero(self._outside_box(nominal, path, p_flange_tools_m))
        if bad.size:
            i = int(bad[0])
            where = "at the target" if i == samples - 1 else f"{100 * s[i, 0]:.0f} % along the move"
            problem = self.pose_problems(nominal, path[i][None], p_flange_tools_m, collisions=False)[0]
            raise EnvelopeError(
                f"the joint move leaves the safety envelope {where}: {problem}; nothing moved: "
                "plan another path (e.g. through a safe intermediate pose) or widen [envelope]"
            )
        problem = self.path_problems(nominal, q_from[None], q_to[None])[0]
        if problem:
            raise EnvelopeError(
                f"the joint move {problem}; nothing moved: plan another path (e.g. through a safe "
                "intermediate pose) or move the keep-out"
            )

    def clear_moves(
        self, nominal: KinematicModel, q_from: np.ndarray, q_to: np.ndarray, p_flange_tools_m: np.ndarray
    ) -> np.ndarray:
        """(M,) bool: which joint moves (M, n) -> (M, n) `check_joint_move` passes, all checked at once (a
        plan's moves: one pass over every path's samples and one collision check of every path, where move
        by move the same checks cost a thousand small passes)."""
        q_from, q_to = np.atleast_2d(np.asarray(q_from, float)), np.atleast_2d(np.asarray(q_to, float))
        if not len(q_from):
            return np.zeros(0, bool)
        travel = np.max(np.abs(q_to - q_from), axis=1)
        samples = np.maximum(_MIN_SAMPLES, np.ceil(travel / _PATH_STEP_RAD).astype(int) + 1)
        move = np.repeat(np.arange(len(q_from)), samples)
        start = np.repeat(np.cumsum(samples) - samples, samples)
        s = (np.arange(len(move)) - start) * (1.0 / (samples[move] - 1.0))  # as np.linspace(0, 1, samples)
        s[np.cumsum(samples) - 1] = 1.0
        path = q_from[move] + s[:, None] * (q_to[move] - q_from[move])
        outside = np.zeros(len(q_from), bool)
        np.logical_or.at(outside, move, self._outside_box(nominal, path, p_flange_tools_m))
        clear = ~outside
        if self.bodies is not None and clear.any():
            inside = np.flatnonzero(clear)
            clear[inside] = np.isnan(self.bodies.path_collisions(nominal, q_from[inside], q_to[inside]))
        return clear

    def detour(
        self,
        nominal: KinematicModel,
        q_from: np.ndarray,
        q_to: np.ndarray,
        p_flange_tools_m: np.ndarray,
        q_home: np.ndarray,
    ) -> list[np.ndarray] | None:
        """The legs of a safe way from q_from to q_to when the direct move is not, ending with q_to; tried in
        order: through one intermediate pose (the wrist turned first: q_from's arm joints with q_to's wrist;
        the arm moved first; the home pose; the home arm with either wrist), then with the wrist tucked at
        home's for the arm's move (q_from's arm with home's wrist, q_to's arm with home's wrist), then that
        through home. Each leg is checked as `check_joint_move` checks; None when no way is safe."""
        q_from, q_to, home = (np.asarray(v, float) for v in (q_from, q_to, q_home))
        arm = slice(0, min(3, len(q_from)))

        def joined(base: np.ndarray, wrist: np.ndarray) -> np.ndarray:
            q = wrist.copy()
            q[arm] = base[arm]
            return q

        ways: list[list[np.ndarray]] = [
            [joined(base, wrist)]
            for base, wrist in ((q_from, q_to), (q_to, q_from), (home, home), (home, q_to), (home, q_from))
        ]
        tucked_from, tucked_to = joined(q_from, home), joined(q_to, home)
        ways += [[tucked_from, tucked_to], [tucked_from, home, tucked_to]]
        for way in ways:
            if self.outside(nominal, np.array(way), p_flange_tools_m).any():
                continue
            legs = [*way, q_to]
            try:
                for start, end in zip([q_from, *way], legs, strict=True):
                    self.check_joint_move(nominal, start, end, p_flange_tools_m)
            except EnvelopeError:
                continue
            return legs
        return None

    def path_problems(
        self, nominal: KinematicModel, q_from: np.ndarray, q_to: np.ndarray
    ) -> list[str | None]:
        """Per joint move (M, n) -> (M, n): None when its whole path keeps clear of the arm itself, the
        tracker and the keep-out boxes (at least half the margin all along), else where and what meets."""
        q_from, q_to = np.atleast_2d(np.asarray(q_from, float)), np.atleast_2d(np.asarray(q_to, float))
        if self.bodies is None or not len(q_from):
            return [None] * len(q_from)
        first_bad = self.bodies.path_collisions(nominal, q_from, q_to)
        problems: list[str | None] = [None] * len(q_from)
        for k in np.flatnonzero(~np.isnan(first_bad)):
            s = float(first_bad[k])
            q = q_from[k] + s * (q_to[k] - q_from[k])
            found = self.bodies.clearances(nominal, q[None])
            own = found.self_m[0] - 0.5 * self.bodies.self_margin_m
            cell = found.cell_m[0] - 0.5 * self.bodies.margin_m
            between, clearance = (
                (found.self_between[0], found.self_m[0])
                if own <= cell
                else (found.cell_between[0], found.cell_m[0])
            )
            where = "at its start" if s == 0 else "at its target" if s == 1 else f"{100 * s:.0f} % along"
            problems[k] = (
                f"brings {between} within {clearance * 1e3:.0f} mm {where} (a path keeps at least half "
                "the margin)"
            )
        return problems

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
