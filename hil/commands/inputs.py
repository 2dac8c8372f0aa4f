"""Measurement input of the analysis commands: a dataset CSV or a campaign file, read the same way."""

from __future__ import annotations

import sqlite3
import warnings
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from hil.data.campaigns import is_campaign, open_campaign
from hil.data.dataset import load_dataset
from hil.data.store import CampaignError, ResultRecord, campaign_dataset
from hil.runner.procedure import Role
from hil.runner.registry import publisher

TRAINING_STEP = "grid"
VALIDATION_STEP = "validation"
REFERENCE_STEP = "reference"  # the drift monitor's re-measured poses: training rows (evidence for drift)


def read_measurements(
    path: str | Path, step: str | Sequence[str] | None = None, *, require_positions: bool = True
) -> pd.DataFrame:
    """The dataset-contract frame of `path`: a campaign file (the measurements of the procedure that
    publishes the grid, one step or all of them) or a dataset CSV (hil.data.dataset.load_dataset). Raises DatasetError/ValueError on bad input."""
    if is_campaign(path):
        with open_campaign(path, create=False) as store:
            return campaign_dataset(store, grid_procedure(), step)
    return load_dataset(path, require_positions=require_positions)


def record_in_campaign(path: str | Path, result: ResultRecord) -> str | None:
    """Record an analysis' result in the campaign it read (a file or the shared store); the campaign as
    shown when recorded, None when `path` is a dataset CSV (nothing to record in)."""
    if not is_campaign(path):
        return None
    try:
        with open_campaign(path, create=False) as store:
            store.record_result(result)
            return str(store.path)
    except (CampaignError, sqlite3.Error) as exc:  # a read-only file, a lost server: the output files stand
        warnings.warn(f"the campaign {path} did not keep the {result.kind} result: {exc}", stacklevel=2)
        return None


def grid_procedure() -> str:
    """The registered procedure whose measurements the analysis commands read: the one publishing the grid."""
    return publisher(Role.GRID)[0]


def _campaign_steps(path: str | Path) -> set[str]:
    if not is_campaign(path):
        return set()
    with open_campaign(path, create=False) as store:
        counts = store.point_counts()
    return set(counts.loc[counts["procedure"] == grid_procedure(), "step"])


def read_training_and_validation(
    path: str | Path, validate: str | Path | None = None
) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """Training and validation frames. A campaign with both a 'grid' and a 'validation' step trains on
    'grid' (and the drift monitor's 'reference' rows, in measurement order) and validates on 'validation', unless a separate validation file is given; a campaign
    given as the validation file gives its 'validation' step when it has one (else all its points)."""
    steps = _campaign_steps(path)
    both = {TRAINING_STEP, VALIDATION_STEP} <= steps
    training = [TRAINING_STEP, REFERENCE_STEP] if REFERENCE_STEP in steps else TRAINING_STEP
    df = read_measurements(path, training if both else None)
    if validate is not None:
        has_validation = VALIDATION_STEP in _campaign_steps(validate)
        return df, read_measurements(validate, VALIDATION_STEP if has_validation else None)
    return df, (read_measurements(path, VALIDATION_STEP) if both else None)
