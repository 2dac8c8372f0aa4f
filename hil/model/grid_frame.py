"""The frame of a measured grid, recovered from the measured positions alone.

The grid planner turns its box to face the tracker, a campaign from another cell or another program may
use any rotation and a different step per axis, and the runner records no grid frame a foreign campaign
would carry. So the IDW map finds the grid from the points: the most common nearest-neighbour direction
is the first axis, the nearest neighbours square to it give the second, the third completes a right-handed
frame; the lattice offset is the circular mean of every location's phase along each axis; a least-squares
fit over the recognised vertices then refines origin, axes and steps together. Off-grid points (validation
poses, random poses) carry no weight in any step: their directions and phases scatter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

ALIGNED_COS = np.cos(np.deg2rad(5.0))  # neighbour vectors within 5 deg count as one direction
ON_VERTEX = 0.25  # a location within this fraction of a step of a lattice node is that vertex
VOTERS = 1500  # neighbour vectors that vote for the dominant direction


@dataclass(frozen=True)
class GridFrame:
    """A lattice p = origin + R_base_grid @ (steps * k), k integer (3,): its rotation, a node and steps."""

    R_base_grid: np.ndarray  # (3, 3), columns = the grid axes in the base frame
    origin_m: np.ndarray  # (3,) one lattice node, base frame
    steps_m: np.ndarray  # (3,) spacing along each grid axis

    def lattice(self, p_base: np.ndarray) -> np.ndarray:
        """Continuous lattice coordinates (N, 3): integers on the vertices."""
        return ((np.asarray(p_base, float) - self.origin_m) @ self.R_base_grid) / self.steps_m

    def vertices(self, p_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer vertex index (N, 3) of each point and (N,) whether it lies on that vertex."""
        u = self.lattice(p_base)
        k = np.round(u)
        return k.astype(int), np.all(np.abs(u - k) < ON_VERTEX, axis=1)

    def to_dict(self) -> dict:
        return {
            "R_base_grid": self.R_base_grid.tolist(),
            "origin_m": self.origin_m.tolist(),
            "steps_m": self.steps_m.tolist(),
        }


def locations(p_base: np.ndarray, merge_m: float) -> np.ndarray:
    """Distinct locations (M, 3): points closer than `merge_m` (orientations at one vertex) averaged."""
    p = np.asarray(p_base, float)
    pairs = cKDTree(p).query_pairs(merge_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(p), len(p)))
    n, label = connected_components(graph, directed=False)
    sums = np.zeros((n, 3))
    np.add.at(sums, label, p)
    return sums / np.bincount(label, minlength=n)[:, None]


def _dominant_direction(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The most common direction (sign ignored) among `vectors` (K, 3) and the mask of its members."""
    if len(vectors) == 0:
        return None
    length = np.linalg.norm(vectors, axis=1)
    unit = vectors / length[:, None]
    # Votes among at most VOTERS vectors (memory grows with their square; a big campaign has thousands).
    voters = unit[np.random.default_rng(0).permutation(len(unit))[:VOTERS]]
    votes = np.abs(voters @ voters.T) > ALIGNED_COS
    best_direction = voters[int(np.argmax(votes.sum(axis=1)))]
    members = np.abs(unit @ best_direction) > ALIGNED_COS
    aligned = unit[members] * np.sign(unit[members] @ best_direction)[:, None]
    direction = aligned.mean(axis=0)
    return direction / np.linalg.norm(direction), members


class _Neighbours:
    """Vectors from every location to its nearest others (queried once), and the shortest of a kind."""

    def __init__(self, loc: np.ndarray, k: int = 27) -> None:
        dist, idx = cKDTree(loc).query(loc, k=min(k, len(loc)))
        self.vec = loc[idx[:, 1:]] - loc[:, None, :]
        self.d = dist[:, 1:]
        self.unit = self.vec / np.maximum(self.d, 1e-12)[..., None]

    def nearest(self, keep=None) -> np.ndarray:
        """Per location, the shortest vector to another location whose direction `keep(unit)` accepts."""
        ok = self.d > 0 if keep is None else (self.d > 0) & keep(self.unit)
        d = np.where(ok, self.d, np.inf)
        j = np.argmin(d, axis=1)
        rows = np.flatnonzero(np.isfinite(d[np.arange(len(d)), j]))
        return self.vec[rows, j[rows]]


def estimate_grid_frame(p_base: np.ndarray, step_m: float | None = None, merge_m: float = 5e-3) -> GridFrame:
    """The grid the points were measured on: any rotation, a step per axis (or `step_m` on all three)."""
    loc = locations(p_base, merge_m)
    if len(loc) < 2:
        return GridFrame(np.eye(3), loc[0] if len(loc) else np.zeros(3), np.full(3, step_m or 0.1))
    nb = _Neighbours(loc)
    first = _dominant_direction(nb.nearest())
    assert first is not None  # two distinct locations give one vector at least
    a1 = first[0]
    a2 = _axis_perpendicular(nb, a1)
    a3 = np.cross(a1, a2)
    R = np.column_stack([a1, a2, a3])
    steps = np.array([_step_along(nb, a) for a in R.T])
    if step_m is not None:
        steps = np.full(3, float(step_m))
    # Lattice offset, in steps, from the location nearest the middle: far from it a step's small error
    # would add up to a wrong phase (a model's base frame may lie metres from the grid).
    anchor = loc[np.argmin(np.linalg.norm(loc - loc.mean(axis=0), axis=1))]
    u = ((loc - anchor) @ R) / steps
    phase = np.angle(np.exp(2j * np.pi * u).mean(axis=0)) / (2 * np.pi)
    frame = GridFrame(R, anchor + R @ (phase * steps), steps)
    for tolerance in (ON_VERTEX, 0.05):  # then only vertices close to the lattice: off-grid points drop out
        frame = _refine(frame, loc, step_m is not None, tolerance)
    return frame


def _axis_perpendicular(nb: _Neighbours, a1: np.ndarray) -> np.ndarray:
    """The second grid axis: the most common nearest-neighbour direction square to the first."""
    sin_tol = np.sqrt(1.0 - ALIGNED_COS**2)
    found = _dominant_direction(nb.nearest(lambda u: np.abs(u @ a1) < sin_tol))
    if found is None:  # a single row or column of points: any axis square to the first
        helper = np.eye(3)[int(np.argmin(np.abs(a1)))]
        a2 = helper - (helper @ a1) * a1
    else:
        a2 = found[0] - (found[0] @ a1) * a1
    return a2 / np.linalg.norm(a2)


def _step_along(nb: _Neighbours, axis: np.ndarray) -> float:
    """Median length of the nearest-neighbour vectors along `axis` (one plane of points: the median of all)."""
    vec = nb.nearest(lambda u: np.abs(u @ axis) > ALIGNED_COS)
    if len(vec) == 0:
        vec = nb.nearest()
    return float(np.median(np.linalg.norm(vec, axis=1)))


def _refine(frame: GridFrame, loc: np.ndarray, fixed_step: bool, tolerance: float) -> GridFrame:
    """Least squares p = origin + A k over the locations within `tolerance` steps of a lattice node;
    A -> nearest rotation times steps."""
    u = frame.lattice(loc)
    k = np.round(u)
    on = np.all(np.abs(u - k) < tolerance, axis=1)
    if on.sum() < 4 or np.linalg.matrix_rank(k[on] - k[on].mean(axis=0)) < 3:
        return frame  # a plane or a line of vertices: the estimate cannot be refined in 3-D
    X = np.column_stack([np.ones(on.sum()), k[on]])
    coef = np.linalg.lstsq(X, loc[on], rcond=None)[0]
    origin, A = coef[0], coef[1:].T  # p = origin + A @ k
    steps = frame.steps_m if fixed_step else np.linalg.norm(A, axis=0)
    U, _, Vt = np.linalg.svd(A / np.linalg.norm(A, axis=0))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return frame
    return GridFrame(R, origin, steps)


# Points closer than this are one location (several orientations measured at one grid node).
SAME_LOCATION_M = 5e-3


def location_spacing(points: np.ndarray) -> float:
    """Median distance from each point to the nearest point at another location (m): repeated
    orientations at a grid node do not shrink it."""
    tree = cKDTree(points)
    k = min(len(points), 16)
    dist = tree.query(points, k=k)[0][:, 1:]
    far = np.where(dist > SAME_LOCATION_M, dist, np.inf).min(axis=1)
    far = far[np.isfinite(far)]
    return float(np.median(far)) if far.size else SAME_LOCATION_M
