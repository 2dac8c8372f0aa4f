"""Cross-validation folds: random (interpolation) and blocks of the measured volume (extrapolation), with the
poses of a single-joint sweep dealt to the folds in turn (interpolation along the swept joint)."""

from __future__ import annotations

import numpy as np


def kfold(n: int, k: int, seed: int) -> list[np.ndarray]:
    """k random folds of n rows (interpolation: every fold's neighbours are in the training folds)."""
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(f) for f in np.array_split(perm, k)]


def spatial_folds(points: np.ndarray, k: int, seed: int, iters: int = 25) -> list[np.ndarray]:
    """k folds that are blocks of the measured volume (k-means on the points), so that held-out errors
    score extrapolation to a region the fit has not seen, as a model is used beyond its grid.

    A grid visited in raster order makes the blocks also blocks of time (a warm-up shows as a drift).
    Fewer distinct points than k give one fold per distinct point.
    """
    rng = np.random.default_rng(seed)
    x = (points - points.mean(axis=0)) / (points.std(axis=0) + 1e-12)
    k = max(1, min(k, len(np.unique(x, axis=0))))
    centres = x[[rng.integers(len(x))]]
    for _ in range(1, k):  # k-means++ seeding: spread the first centres
        d2 = np.min(_squared_distances(x, centres), axis=1)
        if d2.sum() <= 0:  # every point sits on a centre already
            break
        centres = np.vstack([centres, x[rng.choice(len(x), p=d2 / d2.sum())]])
    k = len(centres)
    for _ in range(iters):
        label = np.argmin(_squared_distances(x, centres), axis=1)
        # every cluster's mean at once: its points summed in row order, as a mean over its rows sums them
        sums = np.zeros_like(centres)
        np.add.at(sums, label, x)
        counts = np.bincount(label, minlength=k)
        new = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres)  # empty: stays
        if np.allclose(new, centres):
            break
        centres = new
    folds = [np.flatnonzero(label == c) for c in range(k)]
    return [f for f in folds if len(f) > 0]


def _squared_distances(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Squared distances (N, K) of the points (N, D) to the centres (K, D), summed over the coordinates in
    order: the numbers of the (N, K, D) difference array summed over D, without building it."""
    d = x[:, None, 0] - centres[None, :, 0]
    out = d * d
    for j in range(1, x.shape[1]):
        d = x[:, None, j] - centres[None, :, j]
        out += d * d
    return out


# A joint counts as moved between two consecutive poses when it turned more than this (rad): well above a
# joint reading's jitter, well below any planned step.
SWEEP_STEP_TOL_RAD = 1e-3


def sweep_runs(q: np.ndarray, min_poses: int, tol_rad: float = SWEEP_STEP_TOL_RAD) -> np.ndarray:
    """Which single-joint sweep each pose of `q` (M, n), in motion order, belongs to: (M,) run ids from 0,
    -1 for a pose in none. A sweep is a chain of at least `min_poses` consecutive poses between which one
    and the same joint moved and no other (a pose ending one sweep and starting the next stays in the first)."""
    run = np.full(len(q), -1)
    if len(q) < 2:
        return run
    moved = np.abs(np.diff(q, axis=0)) > tol_rad
    joint = np.where(moved.sum(axis=1) == 1, np.argmax(moved, axis=1), -1)  # step i: pose i -> i + 1
    edges = np.flatnonzero(np.diff(joint) != 0) + 1
    n_runs = 0
    for a, b in zip(np.r_[0, edges], np.r_[edges, len(joint)], strict=True):  # steps a..b-1: one joint
        poses = np.arange(a, b + 1)
        if joint[a] >= 0 and len(poses) >= min_poses:
            free = poses[run[poses] < 0]
            run[free] = n_runs
            n_runs += 1
    return run


def campaign_folds(
    points: np.ndarray, pose: np.ndarray, q: np.ndarray, k: int, seed: int
) -> list[np.ndarray]:
    """k folds of the rows (N,) of a campaign, every row of one pose in one fold: blocks of the measured
    volume (`spatial_folds` on the poses' mean points), except that the poses of each single-joint sweep
    (`sweep_runs`, in the rows' order, at least k poses) are dealt to the folds in turn.

    Why: a sweep samples one joint's error along that joint's angle, over a range nothing else in the
    campaign covers (that is why it was measured). A block of the volume cuts a contiguous arc out of it,
    and predicting that arc asks every model to extrapolate the swept joint's function to angles no other
    row samples: the effects of that joint, the ones the sweep was measured for, then score as losses. Dealt
    in turn, each held-out sweep pose has its sweep neighbours on both sides in the training folds, and the
    grid's blocks still score extrapolation across the workspace.
    `pose` (N,) ids of the rows' poses; `q` (N, n) joints; `points` (N, 3).
    """
    ids, compact = np.unique(pose, return_inverse=True)
    compact = compact.ravel()
    n_pose = len(ids)
    centres = np.zeros((n_pose, points.shape[1]))
    np.add.at(centres, compact, points)
    centres /= np.bincount(compact, minlength=n_pose)[:, None]
    # visits in motion order: a new visit wherever the pose changes from the row before
    change = np.flatnonzero(np.r_[True, compact[1:] != compact[:-1]])
    visit_pose = compact[change]
    visit_run = sweep_runs(q[change], max(k, 2))
    pose_run = np.full(n_pose, -1)
    for v in np.flatnonzero(visit_run >= 0)[::-1]:  # a pose swept more than once: its first sweep
        pose_run[visit_pose[v]] = visit_run[v]
    fold_of = np.full(n_pose, -1)
    grid = np.flatnonzero(pose_run < 0)
    n_folds = k
    if len(grid):
        blocks = spatial_folds(centres[grid], k, seed)
        n_folds = len(blocks)
        for f, block in enumerate(blocks):
            fold_of[grid[block]] = f
    rng = np.random.default_rng([seed, 3])
    for r in range(int(pose_run.max()) + 1):
        seen: list[int] = []  # the sweep's poses in motion order, each once
        for p in visit_pose[visit_run == r]:
            if pose_run[p] == r and p not in seen:
                seen.append(p)
        fold_of[seen] = (np.arange(len(seen)) + rng.integers(n_folds)) % n_folds
    folds = [np.flatnonzero(fold_of[compact] == f) for f in range(n_folds)]
    return [f for f in folds if len(f) > 0]
