"""Measurement input of the analysis commands: a dataset CSV or a campaign file, read the same way."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from hil.dataset import load_dataset
from hil.store import CampaignStore, campaign_dataset, is_campaign_file

CAMPAIGN_PROCEDURE = "grid_sampling"  # the procedure whose measurements the analysis commands read
TRAINING_STEP = "grid"
VALIDATION_STEP = "validation"


def read_measurements(
    path: str | Path, step: str | None = None, *, require_positions: bool = True
) -> pd.DataFrame:
    """The dataset-contract frame of `path`: a campaign file (its grid_sampling measurements, one step or
    all of them) or a dataset CSV (hil.dataset.load_dataset). Raises DatasetError/ValueError on bad input."""
    if is_campaign_file(path):
        return campaign_dataset(path, CAMPAIGN_PROCEDURE, step)
    return load_dataset(path, require_positions=require_positions)


def read_training_and_validation(
    path: str | Path, validate: str | Path | None = None
) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """Training and validation frames. A campaign with both a 'grid' and a 'validation' step trains on
    'grid' only and validates on 'validation' unless a separate validation file is given."""
    training_step = None
    validation_step = None
    if is_campaign_file(path):
        with CampaignStore(path, create=False) as store:
            steps = set(store.measurements(CAMPAIGN_PROCEDURE)["step"])
        if {TRAINING_STEP, VALIDATION_STEP} <= steps:
            training_step, validation_step = TRAINING_STEP, VALIDATION_STEP
    df = read_measurements(path, training_step)
    if validate is not None:
        return df, read_measurements(validate)
    return df, (read_measurements(path, validation_step) if validation_step else None)
