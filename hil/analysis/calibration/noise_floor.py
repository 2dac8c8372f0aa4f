"""How well could a perfect model predict these measurements? The measurement noise floor.

Two estimates, the better one wins:
- repeated poses (rows of one SMR whose reported joints agree within `repeat_tol_rad`, at least 5 groups): the
  pooled scatter of their measured positions;
- otherwise the tracker's noise model at each point's distance (MPE = a + b * distance, taken as
  `mpe_sigmas` sigma per axis; defaults: AT901/AT960 class, 15 um + 6 um/m, MPE = 2 sigma), divided by
  the square root of the shots averaged per point when the data says (`shots_count`, as a campaign
  export has it), combined with a robot repeatability the user states (default 0).
The floor is quoted as the RMS of the 3-D error a perfect model would leave, in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from hil.data.dataset import joints_rad, points_m, smr_ids

# The tracker's noise model (AT901 / AT960 class): MPE = 15 um + 6 um/m of distance, taken as 2 sigma per axis.
TRACKER_MPE_M: tuple[float, float] = (15e-6, 6e-6)
TRACKER_MPE_SIGMAS = 2.0


def tracker_sigma_m(
    distance_m, mpe_m: tuple[float, float] = TRACKER_MPE_M, sigmas: float = TRACKER_MPE_SIGMAS
):
    """Per-axis 1-sigma of one tracker shot at `distance_m` (m, scalar or array) by the MPE = a + b * d model."""
    return (mpe_m[0] + mpe_m[1] * np.asarray(distance_m, float)) / sigmas


@dataclass
class NoiseFloor:
    floor_mm: float  # RMS 3-D error of a perfect model
    sigma_axis_m: np.ndarray  # (N,) per-axis 1-sigma per row
    method: str

    def to_dict(self) -> dict:
        return {"noise_floor_mm": self.floor_mm, "method": self.method}


def estimate_noise_floor(
    df: pd.DataFrame,
    mpe_const_m: float = TRACKER_MPE_M[0],
    mpe_per_m: float = TRACKER_MPE_M[1],
    mpe_sigmas: float = TRACKER_MPE_SIGMAS,
    repeatability_m: float = 0.0,
    repeat_tol_rad: float = 2e-5,
) -> NoiseFloor:
    """Noise floor of a dataset (see module docstring)."""
    p = points_m(df)
    dist = np.linalg.norm(p, axis=1)
    sigma_tracker = tracker_sigma_m(dist, (mpe_const_m, mpe_per_m), mpe_sigmas)
    shots = df["shots_count"].to_numpy(float) if "shots_count" in df.columns else np.ones(len(p))
    sigma_tracker = sigma_tracker / np.sqrt(np.clip(shots, 1.0, None))  # each row averages its shots
    rep_axis = repeatability_m / np.sqrt(3.0)
    sigma = np.sqrt(sigma_tracker**2 + rep_axis**2)
    method = (
        f"tracker noise model {mpe_const_m * 1e6:.0f} um + {mpe_per_m * 1e6:.0f} um/m as {mpe_sigmas:g} sigma "
        f"at the measured distances ({dist.min():.2f}-{dist.max():.2f} m)"
        + (f", averaged over {np.median(shots):g} shots per point" if np.any(shots > 1) else "")
        + (f", plus robot repeatability {repeatability_m * 1e3:g} mm" if repeatability_m else "")
    )
    groups = _repeat_groups(joints_rad(df), repeat_tol_rad, smr_ids(df))
    if len(groups) >= 5:
        ss, dof = 0.0, 0
        for g in groups:
            ss += float(np.sum((p[g] - p[g].mean(axis=0)) ** 2))
            dof += 3 * (len(g) - 1)
        s_axis = np.sqrt(ss / dof)
        if s_axis > np.sqrt(np.mean(sigma**2)):
            sigma = np.full(len(p), s_axis)
            method = f"scatter of {len(groups)} repeated poses (pooled, {dof} degrees of freedom)"
    floor = float(np.sqrt(3.0 * np.mean(sigma**2)) * 1000.0)
    return NoiseFloor(floor, sigma, method)


def _repeat_groups(q: np.ndarray, tol: float, smr: np.ndarray | None = None) -> list[np.ndarray]:
    """Index groups (size >= 2) of rows of one SMR whose joints agree within tol (several SMRs read at one
    pose are no repeats: their positions differ by the nest layout)."""
    key = np.round(q / tol).astype(np.int64)
    if smr is not None:
        key = np.column_stack([key, smr])
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return [np.flatnonzero(inverse.ravel() == k) for k in np.flatnonzero(counts >= 2)]
