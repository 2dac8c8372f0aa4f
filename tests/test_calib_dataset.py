"""The dataset contract: clear errors naming the column or row, round trip."""

import numpy as np
import pandas as pd
import pytest

from hil.data.dataset import (
    DatasetError,
    float_columns,
    joints_rad,
    load_dataset,
    make_dataset,
    validate_dataset,
    write_dataset,
)


def _frame(n=5):
    rng = np.random.default_rng(1)
    return make_dataset(rng.uniform(-1, 1, (n, 6)), rng.uniform(1, 2, (n, 3)), t_s=np.arange(n) * 4.0, smr=1)


def test_missing_column_is_named():
    df = _frame().drop(columns=["q4_rad"])
    with pytest.raises(DatasetError, match="q4_rad"):
        validate_dataset(df)


def test_float_columns_read_as_the_frame_selection_does():
    df = _frame(40)
    df["q2_rad"] = df["q2_rad"].astype(np.float32)  # another dtype is converted as the frame's to_numpy does
    df["point_id"] = [f"p{i}" for i in range(40)]
    cols = [f"q{j}_rad" for j in range(1, 7)]
    np.testing.assert_array_equal(joints_rad(df), df[cols].to_numpy(float))
    assert float_columns(df, []).shape == (40, 0)
    with pytest.raises(KeyError, match=r"\['q7_rad', 'q8_rad'\] not in index"):
        float_columns(df, [*cols, "q7_rad", "q8_rad"])


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


def test_blank_pose_cells_are_refused_with_their_row():
    df = make_dataset(np.zeros((4, 6)) + 0.1, np.arange(12.0).reshape(4, 3) * 100)
    df["pose"] = ["a", None, "b", " "]
    with pytest.raises(DatasetError, match=r"'pose' is blank in data row\(s\) 2, 4"):
        validate_dataset(df)
    df["pose"] = ["a", "a", "b", "c"]
    assert validate_dataset(df)["pose"].tolist() == ["a", "a", "b", "c"]


def _pose_groups_brute_force(q: np.ndarray, tol: float) -> np.ndarray:
    """Connected components of 'every joint within tol', from the full distance matrix."""
    from scipy.sparse.csgraph import connected_components

    near = np.max(np.abs(q[:, None, :] - q[None, :, :]), axis=2) <= tol
    return connected_components(near, directed=False)[1]


def test_pose_ids_group_rows_whose_joints_agree_within_tolerance():
    from hil.data.dataset import SAME_POSE_RAD, pose_ids

    rng = np.random.default_rng(3)
    cols = [f"q{i}_rad" for i in range(1, 7)]
    for _ in range(40):  # clusters of revisits, chains of near rows, rows near cell borders
        n = int(rng.integers(2, 150))
        centres = rng.uniform(-2e-3, 2e-3, (int(rng.integers(1, 12)), 6))
        q = centres[rng.integers(len(centres), size=n)] + rng.normal(0, 10 ** rng.uniform(-6, -3.5), (n, 6))
        ids = pose_ids(pd.DataFrame(q, columns=cols))
        ref = _pose_groups_brute_force(q, SAME_POSE_RAD)
        assert ids[0] == 0 and len(set(zip(ids, ref, strict=True))) == len(set(ref)) == len(set(ids))
    # A chain a-b-c: a and c differ by 1.5 tolerances but b joins them; rows need not be consecutive.
    step = np.zeros((3, 6))
    step[:, 2] = [0.0, 0.75, 1.5]
    q = np.vstack([step * SAME_POSE_RAD, step[:1] + 1.0, step[1:2] * SAME_POSE_RAD])
    assert pose_ids(pd.DataFrame(q[[0, 3, 2, 1]], columns=cols)).tolist() == [0, 1, 0, 0]


def test_pose_ids_of_a_long_log_at_one_pose_stay_small():
    """20 000 rows at one pose (a static drift log): every pair is within tolerance, but memory must not
    grow with the pairs (the pairwise search took 10 GB)."""
    import tracemalloc

    from hil.data.dataset import pose_ids

    rng = np.random.default_rng(0)
    q = np.array([0.1, -1.2, 1.5, -1.8, -1.57, 0.3]) + rng.normal(0, 2e-5, (20000, 6))
    q[-3:] += 0.01  # and three rows at another pose
    df = pd.DataFrame(q, columns=[f"q{i}_rad" for i in range(1, 7)])
    tracemalloc.start()
    try:
        ids = pose_ids(df)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert np.bincount(ids).tolist() == [19997, 3]
    assert peak < 50e6, f"{peak / 1e6:.0f} MB"
