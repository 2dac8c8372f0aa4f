"""The arm's body as capsules, and the distance maths that tells how close two bodies come.

A capsule is a segment with a radius: every point within `radius_m` of the segment. Each capsule is fixed
in one link frame (`frame`: 0 the base, i the link joint i moves, the frames of hil.geometry.kinematics);
its ends are given in that frame. A robot file declares its capsules (`[[capsule]]`, from the maker's
drawings) or one `body_radius_mm` from which a body is laid along the DH table's links (`body_from_dh`).

The clearance of two capsules is the distance between their segments less both radii: negative when they
overlap. Everything is vectorised over poses: the segments of N poses come out of one batch FK
(`link_frames`), and the distances of every pair of every pose in a few numpy operations.

Which pairs can meet: two capsules on the same link never move apart, and two links joined at a joint
touch by construction, so pairs whose links are joined through less length of intermediate links than
their radii plus the self margin are not checked (`self_pairs`): a spherical wrist's three links, a
link and the next one. Every other pair is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hil.geometry.kinematics import KinematicModel, link_frames

_TINY = 1e-12
RIGID_SAMPLES = 16  # random poses over which a pair of capsules must keep one distance to count as rigid


@dataclass(frozen=True)
class ArmBody:
    """Capsules fixed in link frames: names (C,), frame (C,) int, ends a_m, b_m (C, 3) in that frame, and
    radius_m (C,). `source` says where the figures come from (a drawing, or how they were sized)."""

    names: tuple[str, ...]
    frame: np.ndarray
    a_m: np.ndarray
    b_m: np.ndarray
    radius_m: np.ndarray
    source: str = ""
    _pairs: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        count = len(self.names)
        shapes = (np.shape(self.frame), np.shape(self.a_m), np.shape(self.b_m), np.shape(self.radius_m))
        if shapes != ((count,), (count, 3), (count, 3), (count,)):
            raise ValueError(f"a body of {count} capsules needs frame (C,), ends (C, 3), radius (C,)")
        if np.any(np.asarray(self.radius_m) <= 0):
            raise ValueError("every capsule needs a positive radius")

    def with_capsules(self, names, frame, a_m, b_m, radius_m) -> ArmBody:
        """This body with more capsules (e.g. the tool on the flange)."""
        return ArmBody(
            self.names + tuple(names),
            np.concatenate([self.frame, np.asarray(frame, int)]),
            np.concatenate([self.a_m, np.asarray(a_m, float).reshape(-1, 3)]),
            np.concatenate([self.b_m, np.asarray(b_m, float).reshape(-1, 3)]),
            np.concatenate([self.radius_m, np.asarray(radius_m, float)]),
            self.source,
        )

    def self_pairs(self, model: KinematicModel, margin_m: float) -> np.ndarray:
        """(P, 2) capsule indices whose links can meet: links at least two apart, joined through more
        intermediate link length (sum of |a| and |d| of the links between) than the two radii and the
        margin; pairs joined more tightly touch by construction and are left out."""
        key = (model.name, round(margin_m, 9))
        if key not in self._pairs:
            lengths = np.abs(np.asarray(model.a, float)) + np.abs(np.asarray(model.d, float))
            between = np.concatenate([[0.0], np.cumsum(lengths)])  # between[k]: links 1..k
            i, j = np.triu_indices(len(self.names), k=1)
            fi, fj = np.minimum(self.frame[i], self.frame[j]), np.maximum(self.frame[i], self.frame[j])
            # links fi+1 .. fj-1 lie between the two: their lengths are between[fj-1] - between[fi]
            joined = between[np.maximum(fj - 1, fi)] - between[fi]
            keep = (fj - fi >= 2) & (joined > self.radius_m[i] + self.radius_m[j] + margin_m)
            keep[keep] = ~self._rigid(model, i[keep], j[keep])
            self._pairs[key] = np.column_stack([i[keep], j[keep]])
        return self._pairs[key]

    def _rigid(self, model: KinematicModel, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(P,) which pairs keep one distance in every pose (to a micrometre over RIGID_SAMPLES random joint
        sets within the limits): two wrist housings about the axis between them, which no joint brings
        nearer. Such a pair can neither collide nor tell two poses apart, so it is not checked."""
        lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
        q = np.random.default_rng(0).uniform(
            np.maximum(lo, -np.pi), np.minimum(hi, np.pi), (RIGID_SAMPLES, len(lo))
        )
        a, b = self.segments(link_frames(model, q))
        distance = segment_distance(a[:, i], b[:, i], a[:, j], b[:, j])  # (RIGID_SAMPLES, P)
        return np.ptp(distance, axis=0) < 1e-6

    def segments(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Capsule ends in the base frame, (N, C, 3) each, from link frames (N, n+1, 4, 4)."""
        T = frames[:, self.frame, :3, :]  # (N, C, 3, 4)
        x, y, z, origin = T[..., 0], T[..., 1], T[..., 2], T[..., 3]
        # R @ p + o written out per column: an einsum over (N, C, 3, 3) took 16x as long
        a = x * self.a_m[:, 0, None] + y * self.a_m[:, 1, None] + z * self.a_m[:, 2, None] + origin
        b = x * self.b_m[:, 0, None] + y * self.b_m[:, 1, None] + z * self.b_m[:, 2, None] + origin
        return a, b

    def displacement_bound_m(self, model: KinematicModel) -> np.ndarray:
        """(C, n) R[c, j]: no point of capsule c's segment lies farther than R[c, j] from joint j's axis in
        any pose (triangle inequality along the chain; 0 for a joint that does not move it). A joint move
        of dq moves capsule c's segment points by at most sum_j |dq_j| R[c, j] (the path check's bound)."""
        lengths = np.abs(np.asarray(model.a, float)) + np.abs(np.asarray(model.d, float))
        reach_in_frame = np.maximum(np.linalg.norm(self.a_m, axis=1), np.linalg.norm(self.b_m, axis=1))
        n = model.n_joints
        bound = np.zeros((len(self.names), n))
        for j in range(n):  # joint j+1's axis passes through frame j's origin
            moved = self.frame >= j + 1
            if moved.any():
                chain = np.cumsum(lengths[j:])[self.frame[moved] - j - 1]
                bound[moved, j] = chain + reach_in_frame[moved]
        return bound


def body_from_dh(model: KinematicModel, radius_m: float, source: str) -> ArmBody:
    """A body laid along the DH table: per joint i, a capsule along its d (from frame i-1's origin along its
    z axis) and one along its a (to frame i's origin), each of `radius_m`, in frame i; zero lengths left out.
    For arms whose maker gives no body dimensions: it follows the kinematic lines, not the casting."""
    names, frames, ends_a, ends_b = [], [], [], []
    for i in range(model.n_joints):
        a, d, alpha = float(model.a[i]), float(model.d[i]), float(model.alpha[i])
        start = np.array([-a, -d * np.sin(alpha), -d * np.cos(alpha)])  # frame i-1's origin, in frame i
        corner = np.array([-a, 0.0, 0.0])  # after d, before a
        for what, p, q in (("d", start, corner), ("a", corner, np.zeros(3))):
            if np.linalg.norm(q - p) > 1e-6:
                names.append(f"link {i + 1} ({what})")
                frames.append(i + 1)
                ends_a.append(p)
                ends_b.append(q)
    count = len(names)
    return ArmBody(
        tuple(names),
        np.array(frames, int),
        np.array(ends_a).reshape(count, 3),
        np.array(ends_b).reshape(count, 3),
        np.full(count, float(radius_m)),
        source,
    )


def segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Shortest distance (...) between segments p0-p1 and q0-q1 (..., 3), exact, parallel and degenerate
    (point) segments included: the closest parameters are clamped to the segments in turn."""
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    uu, vv, uv, uw, vw = _dot(u, u), _dot(v, v), _dot(u, v), _dot(u, w), _dot(v, w)
    denom = uu * vv - uv * uv
    uu_safe, vv_safe = np.maximum(uu, _TINY), np.maximum(vv, _TINY)
    # the unconstrained closest point on p's line, clamped (parallel lines: any s, take 0)
    s = np.where(
        denom > _TINY * np.maximum(uu * vv, _TINY), (uv * vw - vv * uw) / np.maximum(denom, _TINY), 0.0
    )
    s = np.clip(s, 0.0, 1.0)
    t = (uv * s + vw) / vv_safe  # the closest point on q's line to p(s)
    t_clamped = np.clip(t, 0.0, 1.0)
    # where t was clamped, p's parameter is found again for that end of q
    s = np.where(t != t_clamped, np.clip((uv * t_clamped - uw) / uu_safe, 0.0, 1.0), s)
    s = np.where(uu > _TINY, s, 0.0)
    t = np.where(vv > _TINY, t_clamped, 0.0)
    gap = w + s[..., None] * u - t[..., None] * v
    return np.sqrt(_dot(gap, gap))


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u . v over the last axis (3) of broadcasting arrays: the three products summed in order, without
    einsum's general broadcasting loop (several times slower on these shapes)."""
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def point_box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance (...) from points (..., 3) to an axis-aligned box [lo, hi] (0 inside)."""
    outside = np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)
    return np.sqrt(np.einsum("...i,...i", outside, outside))


_CORNER_SIGNS = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
# the 12 edges of a box as pairs of corners that differ in one coordinate
_EDGES = np.array(
    [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(_CORNER_SIGNS[i] != _CORNER_SIGNS[j]) == 1]
)


def segment_box_distance(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Shortest distance (...) between segments a-b (..., 3) and an axis-aligned box [lo, hi], exact: 0 when
    the segment enters the box (slab test), else the smallest of its ends' distances to the box and its
    distances to the box's 12 edges (the closest box point lies on an edge, or the segment's closest point
    is one of its ends)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(d) > _TINY, d, np.inf)
        t1, t2 = (lo - a) * inv, (hi - a) * inv
    parallel = np.abs(d) <= _TINY
    inside_slab = (a >= lo) & (a <= hi)
    t_near = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    t_far = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = np.max(t_near, axis=-1), np.min(t_far, axis=-1)
    crosses = (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)
    corners = lo + _CORNER_SIGNS * (hi - lo)
    e0, e1 = corners[_EDGES[:, 0]], corners[_EDGES[:, 1]]  # (12, 3)
    to_edges = segment_distance(a[..., None, :], b[..., None, :], e0, e1).min(axis=-1)
    ends = np.minimum(point_box_distance(a, lo, hi), point_box_distance(b, lo, hi))
    return np.where(crosses, 0.0, np.minimum(to_edges, ends))
