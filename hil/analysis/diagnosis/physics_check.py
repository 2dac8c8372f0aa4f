"""Whether a physics term the data do not find still earns its place: a joint's gravity yield from the link
masses that the data carry (most of what is known of it is theirs) but do not find above zero stays in the
model only while it predicts held-out points better than a rigid joint. A cell whose joints do not yield
otherwise keeps a yield fitted to noise and the geometry's leftovers, and predicts worse for it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
from scipy import stats

from hil.analysis.calibration.solve import calibrate
from hil.analysis.diagnosis.baseline import free_mask
from hil.analysis.diagnosis.physics_terms import DATA_LED_SHARE, data_share
from hil.analysis.diagnosis.selection import SelectionPath, cv_positions
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import gravity_physics_term, hold_absent


def unfound_yields(path: SelectionPath, alpha: float) -> dict[int | None, float]:
    """{joint: fitted compliance} of the free gravity physics terms the data carry but do not find above
    zero at the two-sided `alpha` level."""
    z = float(stats.norm.isf(alpha / 2))
    out = {}
    for eff in path.current.model.effects:
        if not gravity_physics_term(eff) or eff.held:
            continue
        std, share = data_share(path.current, path.prob, eff.param_names[0], float(eff.state["prior_std"]))
        c = float(eff.params[0])
        if share >= DATA_LED_SHARE and not c > z * std:
            out[eff.joint] = c
    return out


def heldout_sse(model: CalibratedModel, path: SelectionPath) -> float:
    """Held-out squared position error (m^2) of `model` summed over the path's spatial partitions."""
    free = free_mask(model, path.prob)[0]
    return float(sum(np.sum(cv_positions(model, free, path.prob, folds) ** 2) for folds in path.partitions))


def yields_no_better(df: pd.DataFrame, path: SelectionPath, alpha: float) -> dict[int | None, float]:
    """{joint: fitted compliance} of the unfound yields (`unfound_yields`) when the final model with those
    joints rigid predicts the path's held-out points at least as well; else {} (they help, so they stay, as
    assumed)."""
    unfound = unfound_yields(path, alpha)
    if not unfound:
        return {}
    model = path.current.model
    rigid_start = replace(
        model,
        effects=[
            hold_absent(e, float(e.params[0])) if gravity_physics_term(e) and e.joint in unfound else e
            for e in model.effects
        ],
    )
    rigid = calibrate(df, rigid_start, "ridge").model
    return unfound if heldout_sse(rigid, path) <= heldout_sse(model, path) else {}
