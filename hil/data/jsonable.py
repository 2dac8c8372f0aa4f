"""One conversion of nested numpy data to strict JSON (NaN and infinities become null)."""

from __future__ import annotations

from dataclasses import fields, is_dataclass

import numpy as np


def to_jsonable(value: object) -> object:
    """A JSON-ready copy of nested dicts/lists/tuples/arrays/numpy scalars/dataclass instances;
    non-finite floats -> None."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in fields(value)}
    return value
