"""The dataset contract: clear errors naming the column or row, round trip."""

import numpy as np
import pandas as pd
import pytest

from hil.dataset import DatasetError, load_dataset, make_dataset, validate_dataset, write_dataset


def _frame(n=5):
    rng = np.random.default_rng(1)
    return make_dataset(rng.uniform(-1, 1, (n, 6)), rng.uniform(1, 2, (n, 3)), t_s=np.arange(n) * 4.0, smr=1)


def test_missing_column_is_named():
    df = _frame().drop(columns=["q4_rad"])
    with pytest.raises(DatasetError, match="q4_rad"):
        validate_dataset(df)


def test_bad_value_names_row_and_column():
    df = _frame()
    df["y_mm"] = df["y_mm"].astype(object)
    df.loc[3, "y_mm"] = "oops"
    with pytest.raises(DatasetError, match=r"'y_mm'.*row\(s\) 4"):
        validate_dataset(df)


def test_degrees_are_caught():
    df = _frame()
    df.loc[2, "q2_rad"] = 90.0
    with pytest.raises(DatasetError, match="degrees"):
        validate_dataset(df)


def test_time_must_not_go_backwards():
    df = _frame()
    df.loc[3, "t_s"] = 0.5
    with pytest.raises(DatasetError, match="row 4"):
        validate_dataset(df)


def test_round_trip_and_unitless_column_warning(tmp_path):
    df = _frame()
    df["operator_note"] = "x"
    path = tmp_path / "d.csv"
    with pytest.warns(UserWarning, match="operator_note"):
        write_dataset(df, path)
    with pytest.warns(UserWarning):
        back = load_dataset(path)
    pd.testing.assert_frame_equal(back[_frame().columns], _frame(), check_dtype=False, atol=1e-9)
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "missing.csv")
