"""Tracker <-> robot-base registration: a Kabsch/Umeyama fit with RANSAC against bad points.

The robot's nominal tool points carry its uncompensated error (about a millimetre on a UR), so the
inlier threshold is millimetres: RANSAC only sets aside gross mistakes (a wrong lock, a bumped SMR).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.se3 import fit_rigid, transform_points


@dataclass(frozen=True)
class RigidFit:
    """T_tracker_base mapping base-frame points onto tracker readings, with per-point residuals."""

    T_tracker_base: np.ndarray
    residuals_m: np.ndarray  # (N,) distance of every point after the fit (outliers included)
    inliers: np.ndarray  # (N,) bool

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m[self.inliers] ** 2)))

    @property
    def max_m(self) -> float:
        return float(np.max(self.residuals_m[self.inliers]))

    def as_result(self, point_ids: list[str]) -> dict:
        """JSON-able step result (mm in the keys)."""
        return {
            "T_tracker_base": self.T_tracker_base.tolist(),
            "rms_mm": self.rms_m * 1e3,
            "max_mm": self.max_m * 1e3,
            "points": len(self.inliers),
            "inliers": int(self.inliers.sum()),
            "outliers": [pid for pid, ok in zip(point_ids, self.inliers, strict=True) if not ok],
            "residuals_mm": (self.residuals_m * 1e3).round(4).tolist(),
        }


def ransac_rigid(
    p_base_m: np.ndarray,
    p_tracker_m: np.ndarray,
    inlier_m: float = 3e-3,
    iterations: int = 200,
    seed: int = 0,
) -> RigidFit:
    """Rigid fit of p_tracker = T p_base on the largest consistent subset of point pairs, refitted on it.

    Minimal samples of 3 pairs are drawn at random; the sample whose fit puts most pairs within `inlier_m`
    wins (ties: smaller RMS). Raises ValueError when fewer than 4 pairs agree: nothing trustworthy to report.
    """
    src, dst = np.asarray(p_base_m, float), np.asarray(p_tracker_m, float)
    n = len(src)
    if n < 4:
        raise ValueError(f"registration needs at least 4 point pairs, got {n}")
    rng = np.random.default_rng(seed)
    best_inliers = np.zeros(n, bool)
    best_rms = np.inf
    for _ in range(iterations):
        sample = rng.choice(n, 3, replace=False)
        try:
            T, _ = fit_rigid(src[sample], dst[sample])
        except ValueError:  # collinear sample
            continue
        d = np.linalg.norm(transform_points(T, src) - dst, axis=1)
        inliers = d < inlier_m
        rms = float(np.sqrt(np.mean(d[inliers] ** 2))) if inliers.any() else np.inf
        if inliers.sum() > best_inliers.sum() or (inliers.sum() == best_inliers.sum() and rms < best_rms):
            best_inliers, best_rms = inliers, rms
    if best_inliers.sum() < 4:
        raise ValueError(
            f"no 4 registration points agree within {inlier_m * 1e3:.1f} mm: check the SMR seat, the beam "
            "lock and tracker.position_base_mm"
        )
    for _ in range(3):  # refit on the consensus set, let it settle
        T, _ = fit_rigid(src[best_inliers], dst[best_inliers])
        d = np.linalg.norm(transform_points(T, src) - dst, axis=1)
        best_inliers = d < inlier_m
    return RigidFit(T, d, best_inliers)
