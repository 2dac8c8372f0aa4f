"""Collisions before anything moves: the arm with itself, with the tracker and with the cell's keep-out boxes.

`CellBodies` holds the arm's capsules with the tool's (hil.geometry.body), the tracker's keep-out (a
vertical capsule through its position: its head and its stand) and the boxes the cell config declares.
A pose is clear when every pair of the arm's own capsules that can meet keeps `self_margin_m` and every
moving capsule keeps `margin_m` from the tracker and the boxes (the base, which stands where it stands,
is left out of the cell checks).

A joint move is checked along its whole path without a fixed step. Along a moveJ (s from 0 to 1) no point
of a capsule's segment moves faster than D = sum_j |dq_j| R_j per unit s (R_j: its farthest point from
joint j's axis, `ArmBody.displacement_bound_m`), so its clearance to the cell changes by at most L = D per
unit s; the clearance of two links changes only through the joints between them, by at most L = the outer
one's D over those joints (the joints before both move them together). Between two samples s0 < s1 with
clearances c0, c1 each clearance therefore stays at least (c0 + c1 - L (s1 - s0)) / 2. The path is sampled from
its two ends and halved wherever that bound falls below half the margin, until it holds everywhere: the
whole path then keeps half the margin (the capsule radii are inside the clearances), so a collision between
two clear samples cannot slip through, whatever the arm's speed (the bound is geometric, not timed). A
sample closer than half the margin refuses the move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.body import ArmBody, segment_box_distance, segment_distance
from hil.geometry.kinematics import KinematicModel, link_frames

_MAX_HALVINGS = 40
_BLOCK_POSES = 1024  # poses checked at once (see CellBodies._arrays)
PATH_MARGIN_SHARE = 0.5  # the share of each margin a path keeps all along (poses keep all of it)  # 2**-40 of a move: far below a micrometre of travel


@dataclass(frozen=True)
class KeepOutBox:
    """A region the arm must not enter: an axis-aligned box in the robot base frame (metres)."""

    name: str
    min_m: np.ndarray
    max_m: np.ndarray


@dataclass(frozen=True)
class Clearances:
    """Per pose (N,): the smallest clearance of the arm to itself and to the cell (metres; +inf when nothing
    is checked), and which two bodies it is between."""

    self_m: np.ndarray
    self_between: list[str]
    cell_m: np.ndarray
    cell_between: list[str]


@dataclass(frozen=True)
class CellBodies:
    """The arm (with its tool), the tracker's keep-out and the keep-out boxes, with the margins to keep."""

    body: ArmBody
    tracker_a_m: np.ndarray | None = None  # the tracker keep-out capsule's ends (base frame)
    tracker_b_m: np.ndarray | None = None
    tracker_radius_m: float = 0.0
    keep_out: tuple[KeepOutBox, ...] = ()
    margin_m: float = 0.05
    self_margin_m: float = 0.01

    def _arrays(self, model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Self clearances (N, P), cell clearances (N, Cm, 1 + K) (tracker, then each box) and the moving
        capsules' indices (Cm,). In blocks of `_BLOCK_POSES`: the per-pair work arrays of a whole plan's
        candidates (tens of thousands of poses) outgrow the processor's cache, and block by block the same
        check ran 7x faster (80 000 random poses: 2.2 s -> 0.3 s)."""
        pairs = self.body.self_pairs(model, self.self_margin_m)
        moving = np.flatnonzero(self.body.frame >= 1)
        own = np.empty((len(q), len(pairs)))
        cell = np.empty((len(q), len(moving), 1 + len(self.keep_out)))  # every block fills its rows
        for start in range(0, len(q), _BLOCK_POSES):
            block = slice(start, start + _BLOCK_POSES)
            own[block], cell[block] = self._block_arrays(model, q[block], pairs, moving)
        return own, cell, moving

    def _block_arrays(
        self, model: KinematicModel, q: np.ndarray, pairs: np.ndarray, moving: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """`_arrays` of one block of poses."""
        frames = link_frames(model, q)
        a, b = self.body.segments(frames)
        radius = self.body.radius_m
        i, j = pairs[:, 0], pairs[:, 1]
        own = segment_distance(a[:, i], b[:, i], a[:, j], b[:, j]) - radius[i] - radius[j]
        am, bm, rm = a[:, moving], b[:, moving], radius[moving]
        cell = np.full((len(q), len(moving), 1 + len(self.keep_out)), np.inf)
        if self.tracker_a_m is not None and self.tracker_b_m is not None:
            cell[..., 0] = (
                segment_distance(am, bm, self.tracker_a_m, self.tracker_b_m) - rm - self.tracker_radius_m
            )
        for k, box in enumerate(self.keep_out, start=1):
            cell[..., k] = segment_box_distance(am, bm, box.min_m, box.max_m) - rm
        return own, cell

    def clearances(self, model: KinematicModel, q: np.ndarray) -> Clearances:
        """The smallest clearances of joint sets q (N, n), each with the two bodies it lies between."""
        q = np.atleast_2d(np.asarray(q, float))
        own, cell, moving = self._arrays(model, q)
        pairs = self.body.self_pairs(model, self.self_margin_m)
        names = self.body.names
        others = ("the tracker",) + tuple(f"keep-out box {box.name!r}" for box in self.keep_out)
        self_m = own.min(axis=1) if own.shape[1] else np.full(len(q), np.inf)
        self_between = []
        for row in own:
            if not len(row):
                self_between.append("")
                continue
            i, j = pairs[int(np.argmin(row))]
            self_between.append(f"{names[i]} and {names[j]}")
        flat = cell.reshape(len(q), -1)
        cell_m = flat.min(axis=1) if flat.shape[1] else np.full(len(q), np.inf)
        cell_between = []
        for row in flat:
            if not len(row) or not np.isfinite(row.min()):
                cell_between.append("")
                continue
            c, k = divmod(int(np.argmin(row)), cell.shape[2])
            cell_between.append(f"{names[moving[c]]} and {others[k]}")
        return Clearances(self_m, self_between, cell_m, cell_between)

    def collides(self, model: KinematicModel, q: np.ndarray) -> np.ndarray:
        """(N,) bool: which joint sets come closer than a margin to the arm itself or to the cell."""
        q = np.atleast_2d(np.asarray(q, float))
        own, cell, _ = self._arrays(model, q)
        near_self = (own < self.self_margin_m).any(axis=1)
        near_cell = (cell < self.margin_m).reshape(len(q), -1).any(axis=1)
        return np.asarray(near_self | near_cell, bool)

    def pair_count(self, model: KinematicModel) -> int:
        """How many clearances `pair_slack_m` gives per joint set."""
        moving = int(np.sum(self.body.frame >= 1))
        return len(self.body.self_pairs(model, self.self_margin_m)) + moving * (1 + len(self.keep_out))

    def pair_slack_m(self, model: KinematicModel, q: np.ndarray) -> np.ndarray:
        """(N, Q) how far each checked pair of each joint set keeps beyond its margin (negative: too close):
        the self pairs less the self margin, then each moving capsule against the tracker and each box less
        the cell margin (+inf for what is not there)."""
        q = np.atleast_2d(np.asarray(q, float))
        own, cell, _ = self._arrays(model, q)
        return np.concatenate([own - self.self_margin_m, cell.reshape(len(q), -1) - self.margin_m], axis=1)

    def pose_problems(self, model: KinematicModel, q: np.ndarray) -> list[str | None]:
        """Per joint set: None when clear, else the bodies that come too close and their clearance."""
        found = self.clearances(model, q)
        problems: list[str | None] = []
        for k in range(len(found.self_m)):
            parts = []
            if found.self_m[k] < self.self_margin_m:
                parts.append(_too_close(found.self_between[k], found.self_m[k], self.self_margin_m))
            if found.cell_m[k] < self.margin_m:
                parts.append(_too_close(found.cell_between[k], found.cell_m[k], self.margin_m))
            problems.append("; ".join(parts) if parts else None)
        return problems

    def _slack(self, model: KinematicModel, q: np.ndarray) -> np.ndarray:
        """(N, Q) every checked clearance less half its margin: the self pairs, then each moving capsule
        against the tracker and each box."""
        own, cell, _ = self._arrays(model, q)
        return np.concatenate(
            [
                own - PATH_MARGIN_SHARE * self.self_margin_m,
                cell.reshape(len(q), -1) - PATH_MARGIN_SHARE * self.margin_m,
            ],
            axis=1,
        )

    def _rates(self, model: KinematicModel, dq: np.ndarray) -> np.ndarray:
        """(M, Q) how fast each clearance of `_slack` can change per unit of each move dq (M, n): for a self
        pair, the farther-out capsule's motion by the joints between the two links (the joints before
        both move them together); for the cell, the capsule's motion by every joint before it."""
        R = self.body.displacement_bound_m(model)  # (C, n)
        pairs = self.body.self_pairs(model, self.self_margin_m)
        frame = self.body.frame
        inner = np.minimum(frame[pairs[:, 0]], frame[pairs[:, 1]])
        outer_capsule = np.where(frame[pairs[:, 0]] >= frame[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
        joints = np.arange(1, model.n_joints + 1)
        between = joints[None, :] > inner[:, None]  # (P, n): joint k moves the outer link, not the inner
        own = np.abs(dq) @ (R[outer_capsule] * between).T
        moving = np.flatnonzero(frame >= 1)
        cell = np.repeat(np.abs(dq) @ R[moving].T, 1 + len(self.keep_out), axis=1)
        return np.concatenate([own, cell], axis=1)

    def path_collisions(self, model: KinematicModel, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
        """For joint moves (M, n) from q_from to q_to (moveJ, straight in joint space): the fraction of
        the way (M,) at which a move first comes closer than half a margin, NaN for a move that keeps it
        all along (see the module docstring for why the samples suffice)."""
        q_from, q_to = np.atleast_2d(np.asarray(q_from, float)), np.atleast_2d(np.asarray(q_to, float))
        rate = self._rates(model, q_to - q_from)  # (M, Q) per unit of the move
        first_bad = np.full(len(q_from), np.nan)
        m = len(q_from)
        ends = self._slack(model, np.concatenate([q_from, q_to]))
        move = np.arange(m)
        s0, s1 = np.zeros(m), np.ones(m)
        slack0, slack1 = ends[:m], ends[m:]
        _mark(first_bad, move, s0, (slack0 < 0).any(axis=1))
        _mark(first_bad, move, s1, (slack1 < 0).any(axis=1))
        for _ in range(_MAX_HALVINGS):
            width = (s1 - s0)[:, None]
            open_ = np.isnan(first_bad[move]) & (slack0 + slack1 < rate[move] * width).any(axis=1)
            if not open_.any():
                return first_bad
            move, s0, s1, slack0, slack1 = move[open_], s0[open_], s1[open_], slack0[open_], slack1[open_]
            mid = 0.5 * (s0 + s1)
            q_mid = q_from[move] + mid[:, None] * (q_to[move] - q_from[move])
            slack_mid = self._slack(model, q_mid)
            _mark(first_bad, move, mid, (slack_mid < 0).any(axis=1))
            move = np.concatenate([move, move])
            s0, s1 = np.concatenate([s0, mid]), np.concatenate([mid, s1])
            slack0, slack1 = np.concatenate([slack0, slack_mid]), np.concatenate([slack_mid, slack1])
        unresolved = np.unique(move[np.isnan(first_bad[move])])
        first_bad[unresolved] = 0.5  # never certified: refused rather than passed
        return first_bad


def clear_range_rad(
    bodies: CellBodies,
    model: KinematicModel,
    q_ref: np.ndarray,
    joint: int,
    step_rad: float = np.deg2rad(1.0),
) -> tuple[float, float]:
    """The range of joint `joint` (0-based) about q_ref, the other joints held at q_ref, over which the arm
    keeps its self margin: where it would fold into itself on either side (within the model's limits, to
    `step_rad`; the range ends one step short of the first sample that is not clear)."""
    lo, hi = model.joint_limits[joint]
    start = float(q_ref[joint])
    ends = []
    for end in (lo, hi):
        angles = np.arange(start, end, step_rad if end > start else -step_rad)
        q = np.tile(np.asarray(q_ref, float), (len(angles), 1))
        q[:, joint] = angles
        own, _, _ = bodies._arrays(model, q) if len(q) else (np.zeros((0, 0)), None, None)
        bad = np.flatnonzero((own < bodies.self_margin_m).any(axis=1)) if own.size else np.array([], int)
        ends.append(float(end) if not bad.size else float(angles[max(bad[0] - 1, 0)]))
    return ends[0], ends[1]


def _mark(first_bad: np.ndarray, move: np.ndarray, s: np.ndarray, bad: np.ndarray | np.bool_) -> None:
    """Record, per move, the smallest fraction at which it was found too close."""
    bad = np.asarray(bad, bool)
    for k, value in zip(move[bad], s[bad], strict=True):
        if np.isnan(first_bad[k]) or value < first_bad[k]:
            first_bad[k] = value


def _too_close(between: str, clearance_m: float, margin_m: float) -> str:
    if clearance_m < 0:
        return f"{between} collide ({-clearance_m * 1e3:.0f} mm overlap; margin {margin_m * 1e3:.0f} mm)"
    return f"{between} {clearance_m * 1e3:.0f} mm apart, inside the {margin_m * 1e3:.0f} mm margin"
