"""A procedure's motion plan: the poses it will visit, in order, for `--dry-run` and for the envelope check.

`describe()` gives what an engineer checks before pressing start: how many poses, in which order, how long
it should take, and the bounding box the tool points sweep (nominal kinematics).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from hil.geometry.kinematics import forward_kinematics
from hil.runner.cell_config import CellConfig
from hil.runner.envelope import EnvelopeError
from hil.runner.operator import OperatorStep
from hil.runner.planners import sequence_duration_s

NO_SAFE_PATH = "no safe path"  # a pose left out because no move to it from the pose before keeps clear


@dataclass(frozen=True)
class PlannedPose:
    """One pose of a plan: its point id, procedure step, commanded joints and where the SMR sits.

    `smr`: the SMR's number in the record; `p_flange_m`: its nominal centre in the flange frame, where the
    tracker is aimed (None: the nest's, when `location` is a nest); `approach_q_rad`: a pre-position to pass
    through first (a known approach direction); `setup`: the manual steps that put the SMR where this pose
    needs it, asked before the first pose of each new setup; `at_pose`: those asked once the robot stands
    at that first pose (guiding the beam onto the SMR).
    """

    point_id: str
    procedure: str
    step: str
    q_rad: np.ndarray
    location: str
    smr: int = 1
    p_flange_m: np.ndarray | None = None
    approach_q_rad: np.ndarray | None = None
    setup: tuple[OperatorStep, ...] = ()
    at_pose: tuple[OperatorStep, ...] = ()


@dataclass
class Plan:
    procedure: str
    poses: list[PlannedPose]
    config: CellConfig
    operator_steps: int = 0
    dropped: dict[str, int] = field(default_factory=dict)  # reason -> poses left out (unreachable, ...)
    per_point_s: float | None = None  # settle + measurement time per pose (default from the config)
    bounds: str = ""  # an adaptive procedure's plan is its first block: the bounds of what may follow

    def joints(self) -> np.ndarray:
        return np.array([p.q_rad for p in self.poses]).reshape(-1, 6)

    def estimated_duration_s(self) -> float:
        cfg = self.config
        per_point = self.per_point_s
        if per_point is None:
            per_point = cfg.settle_s + cfg.shots_per_point * cfg.meas_time_s + 0.5
        return sequence_duration_s(
            self.joints(),
            cfg.q_home_rad,
            float(cfg.robot_driver.get("joint_speed", 1.05)),
            float(cfg.robot_driver.get("joint_accel", 1.4)),
            per_point,
        )

    def path_check(self) -> tuple[int, list[str]]:
        """Check every move of the plan in order (from home): how many need the detour through home, and
        which poses cannot be reached inside the envelope at all (Envelope.detour tries the ways round)."""
        cfg = self.config
        env, tools, home = cfg.envelope, cfg.nests_flange_m, cfg.q_home_rad
        chain = [home, *(pose.q_rad for pose in self.poses)]
        direct = _clear_chain(cfg, chain)
        detours, impossible = 0, []
        previous = home
        for k, pose in enumerate(self.poses):
            if not _clear(cfg, previous, pose.q_rad, direct[k] if previous is chain[k] else None):
                if env.detour(cfg.nominal, previous, pose.q_rad, tools, home) is None:
                    impossible.append(pose.point_id)
                    continue
                detours += 1
            previous = pose.q_rad
        return detours, impossible

    def without_unsafe_moves(self) -> Plan:
        """This plan less the poses that cannot be reached safely from the pose before (or home): neither
        the direct move nor any detour Envelope.detour finds keeps clear. Each is counted in `dropped` as
        "no safe path", so the dry run says so; the run then moves from the pose before to the next one."""
        cfg = self.config
        env, tools, home = cfg.envelope, cfg.nests_flange_m, cfg.q_home_rad
        legs_of = [
            [*([pose.approach_q_rad] if pose.approach_q_rad is not None else []), pose.q_rad]
            for pose in self.poses
        ]
        chain = [home, *(leg for legs in legs_of for leg in legs)]  # every pose reached: its moves at once
        direct = _clear_chain(cfg, chain)
        kept: list[PlannedPose] = []
        previous, first = home, 0  # chain[first]: where the pose's first leg starts if every pose is kept
        for pose, legs in zip(self.poses, legs_of, strict=True):
            start, safe = previous, True
            for k, leg in enumerate(legs, start=first):
                known = direct[k] if start is chain[k] else None
                if (
                    not _clear(cfg, start, leg, known)
                    and env.detour(cfg.nominal, start, leg, tools, home) is None
                ):
                    safe = False
                    break
                start = leg
            first += len(legs)
            if safe:
                kept.append(pose)
                previous = pose.q_rad
        dropped = dict(self.dropped)
        if len(kept) < len(self.poses):
            dropped[NO_SAFE_PATH] = dropped.get(NO_SAFE_PATH, 0) + len(self.poses) - len(kept)
        return replace(self, poses=kept, dropped=dropped)

    def nearest_bodies(self) -> list[tuple[float, str]]:
        """Per pose, its smallest clearance (metres) and the two bodies it lies between: the arm with itself
        or with the cell, whichever keeps less beyond its margin. Empty when collisions are not checked."""
        cfg = self.config
        bodies = cfg.envelope.bodies
        if bodies is None or not self.poses:
            return []
        found = bodies.clearances(cfg.nominal, self.joints())
        own = found.self_m - bodies.self_margin_m
        cell = found.cell_m - bodies.margin_m
        return [
            (float(found.self_m[k]), found.self_between[k])
            if own[k] <= cell[k]
            else (float(found.cell_m[k]), found.cell_between[k])
            for k in range(len(self.poses))
        ]

    def describe(self, max_rows: int = 20) -> str:
        """A readable summary: counts, duration, bounding box, and the first poses in order."""
        cfg = self.config
        q = self.joints()
        lines = [f"plan of {self.procedure}: {len(self.poses)} poses, {self.operator_steps} operator step(s)"]
        if self.dropped:
            lines.append(
                "  left out: " + ", ".join(f"{n} {reason}" for reason, n in sorted(self.dropped.items()))
            )
        detours, impossible = self.path_check()
        if detours:
            lines.append(
                f"  {detours} move(s) go through a safe intermediate pose: the direct path would leave the envelope"
            )
        if impossible:
            lines.append(f"  NOT REACHABLE inside the envelope: {', '.join(impossible[:10])}")
        minutes = self.estimated_duration_s() / 60.0
        lines.append(f"  estimated duration: {minutes:.1f} min (moves + settle + measurement)")
        if self.bounds:
            lines.append(f"  then: {self.bounds}")
        if len(q):
            T = forward_kinematics(cfg.nominal, q)
            points = np.einsum("nij,kj->nki", T[:, :3, :3], cfg.nests_flange_m) + T[:, None, :3, 3]
            lo, hi = points.reshape(-1, 3).min(axis=0) * 1e3, points.reshape(-1, 3).max(axis=0) * 1e3
            lines.append(
                f"  tool points sweep x {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}..{hi[1]:.0f}, z {lo[2]:.0f}..{hi[2]:.0f} mm (robot base frame)"
            )
            nearest = self.nearest_bodies()
            if nearest:
                k = int(np.argmin([clearance for clearance, _ in nearest]))
                clearance, between = nearest[k]
                lines.append(
                    f"  smallest clearance: {clearance * 1e3:.0f} mm ({between}) at {self.poses[k].point_id}"
                )
            # the joints as the pendant shows them: the controller's, for a robot that couples its joints
            shown = q if cfg.coupling is None else cfg.coupling.to_controller(q)
            which = (
                "joints (deg)" if cfg.coupling is None else "controller joints J1..J6 (deg, the pendant's)"
            )
            header = f"  {'#':>4} {'point':>10} {'step':>12} {'smr at':>8}  {which}"
            lines.append(f"{header:<{len(header) + 41}}  clearance" if nearest else header)
            for k, pose in enumerate(self.poses[:max_rows], start=1):
                deg = " ".join(f"{v:8.2f}" for v in np.rad2deg(shown[k - 1]))
                row = f"  {k:>4} {pose.point_id:>10} {pose.step:>12} {pose.location:>8}  {deg}"
                if nearest:
                    clearance, between = nearest[k - 1]
                    row += f"  {clearance * 1e3:5.0f} mm ({between})"
                lines.append(row)
            if len(self.poses) > max_rows:
                lines.append(f"  ... and {len(self.poses) - max_rows} more")
        return "\n".join(lines)


def _clear_chain(cfg: CellConfig, chain: list[np.ndarray]) -> np.ndarray:
    """Which of the direct moves chain[k] -> chain[k + 1] keep inside the envelope, all checked at once."""
    if len(chain) < 2:
        return np.zeros(0, bool)
    q = np.array(chain, float)
    return cfg.envelope.clear_moves(cfg.nominal, q[:-1], q[1:], cfg.nests_flange_m)


def _clear(cfg: CellConfig, q_from: np.ndarray, q_to: np.ndarray, known: bool | None) -> bool:
    """Whether the direct move keeps inside the envelope: `known` when the chain's check already says,
    else checked now."""
    if known is not None:
        return bool(known)
    try:
        cfg.envelope.check_joint_move(cfg.nominal, q_from, q_to, cfg.nests_flange_m)
    except EnvelopeError:
        return False
    return True
