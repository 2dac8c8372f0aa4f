"""Cross-validation folds: random (interpolation) and blocks of the measured volume (extrapolation)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


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
        d2 = np.min(((x[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        if d2.sum() <= 0:  # every point sits on a centre already
            break
        centres = np.vstack([centres, x[rng.choice(len(x), p=d2 / d2.sum())]])
    k = len(centres)
    for _ in range(iters):
        label = np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        new = np.array([x[label == c].mean(axis=0) if np.any(label == c) else centres[c] for c in range(k)])
        if np.allclose(new, centres):
            break
        centres = new
    folds = [np.flatnonzero(label == c) for c in range(k)]
    return [f for f in folds if len(f) > 0]


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
