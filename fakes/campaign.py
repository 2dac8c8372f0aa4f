"""Visit planned joints on the simulated cell and return what the tracker measured, in the dataset contract.

Planning the joints is the planners' job (hil.planners, as the procedures do); visiting them on the
simulated cell, as a real cell would, is the fake's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fakes.cell import SimulatedCell
from hil.dataset import make_dataset


def simulate_campaign(
    cell: SimulatedCell, q_cmd: np.ndarray, smr_id: int = 1, seconds_per_point: float = 4.0
) -> pd.DataFrame:
    """Visit q_cmd (N, 6) in order on the cell and return the rows of the dataset contract."""
    r = cell.run_sequence(q_cmd, smr_id=smr_id, seconds_per_point=seconds_per_point)
    loc = cell.smr_location(smr_id)
    return make_dataset(
        r["q_encoder"],
        r["p_tracker_measured"],
        t_s=r["t_s"],
        temperature_c=r["temperature_c"],
        smr=loc.index if loc.kind == "nest" else 0,
    )

