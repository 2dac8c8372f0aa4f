"""The drift monitor's evidence: how far each reference pose (re-measured at intervals during a grid, step
`reference`, see procedures/grid_sampling) has moved since its first visit, against time and temperature.

A reference pose is the same commanded joints each round, so its reading moves only with what changes in the
cell: the arm's growth as it warms, the tracker's scale as the air changes, a stand or floor that drifts.
Growth and the tracker's scale grow with the temperature, a drift with time; plotted against both, the
report shows which one the cell has. Rows of one pose and one SMR nest are compared with each other.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from hil.data.dataset import points_m, pose_ids, smr_ids

REFERENCE_STEP = "reference"


def reference_drift(df: pd.DataFrame) -> dict | None:
    """Per reference pose and nest measured at least twice: each visit's displacement (mm, tracker frame)
    from its first visit, with its time (s) and temperature (degC) where recorded; None when the campaign has
    no reference rows (no `step_id` column, or the drift monitor was off)."""
    if "step_id" not in df.columns:
        return None
    ref = df[df["step_id"].astype(str) == REFERENCE_STEP]
    if len(ref) < 2:
        return None
    pose, smr, p = pose_ids(ref), smr_ids(ref), points_m(ref)
    t = ref["t_s"].to_numpy(float) if "t_s" in ref.columns else np.full(len(ref), np.nan)
    temp = (
        ref["temperature_c"].to_numpy(float) if "temperature_c" in ref.columns else np.full(len(ref), np.nan)
    )
    series = []
    for key in sorted(set(zip(pose.tolist(), smr.tolist(), strict=True))):
        rows = np.flatnonzero((pose == key[0]) & (smr == key[1]))
        if len(rows) < 2:
            continue
        d = (p[rows] - p[rows[0]]) * 1000.0
        series.append(
            {
                "pose": int(key[0]) + 1,
                "smr": int(key[1]),
                "t_s": t[rows].tolist(),
                "temperature_c": temp[rows].tolist(),
                "drift_mm": d.tolist(),
                "norm_mm": np.linalg.norm(d, axis=1).tolist(),
            }
        )
    if not series:
        return None
    worst = max(series, key=lambda s: max(s["norm_mm"]))
    return {
        "poses": series,
        "visits": int(sum(len(s["norm_mm"]) for s in series)),
        "max_mm": float(max(worst["norm_mm"])),
        "span_s": float(np.nanmax(t) - np.nanmin(t)) if np.isfinite(t).any() else None,
        "span_k": float(np.nanmax(temp) - np.nanmin(temp)) if np.isfinite(temp).any() else None,
    }


def drift_text(drift: dict | None) -> str | None:
    """One line for the terminal: how many reference poses, how far the worst moved, over what time and
    temperature (None without a drift monitor)."""
    if not drift:
        return None
    over = []
    if drift["span_s"] is not None:
        over.append(f"{drift['span_s'] / 60:.0f} min")
    if drift["span_k"] is not None:
        over.append(f"{drift['span_k']:.2f} K")
    return (
        f"Drift monitor: {len(drift['poses'])} reference pose(s), {drift['visits']} visits; the farthest moved "
        f"{drift['max_mm']:.4f} mm from its first visit"
        + (f" over {' and '.join(over)}" if over else "")
        + "."
    )
