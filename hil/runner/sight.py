"""Which joint configurations a cell can measure: inside its envelope, with the SMR facing its tracker.

A plan made by the analysis (hil.analysis.design.plan) takes this as its `admissible` test; the analysis
knows joint limits only, the cell's envelope and the tracker's place are the runner's knowledge.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hil.geometry.kinematics import forward_kinematics
from hil.runner.cell_config import CellConfig

# The SMR is seen while the line to the tracker stays within its acceptance cone about the tool's axis
# (30 deg half angle); a planned pose keeps a margin for what the nominal model and cell.toml do not know.
SMR_ACCEPTANCE_RAD = float(np.deg2rad(30.0))
MARGIN_RAD = float(np.deg2rad(5.0))


def measurable(config: CellConfig, nest: int = 1) -> Callable[[np.ndarray], np.ndarray]:
    """`ok(q (M, 6)) -> (M,) bool`: whole tool and wrist inside the envelope, the nest's SMR facing the tracker
    within its acceptance cone less `MARGIN_RAD`."""
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    p_nest = np.asarray(config.nests_flange_m[nest - 1], float)

    def ok(q: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        inside = ~config.envelope.outside(config.nominal, q, config.nests_flange_m)
        T = forward_kinematics(config.nominal, q)
        p = np.einsum("nij,j->ni", T[:, :3, :3], p_nest) + T[:, :3, 3]
        to_tracker = config.p_base_tracker_m - p
        cos = np.einsum("ni,ni->n", T[:, :3, 2], to_tracker) / np.linalg.norm(to_tracker, axis=1)
        return inside & (cos >= np.cos(SMR_ACCEPTANCE_RAD - MARGIN_RAD))

    return ok
