"""`hil run pseudo_target --targets FILE.csv`: orientation columns mean what they mean in every dataset."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from hil.data.dataset import orientation_columns
from procedures.pseudo_target import read_targets_csv


def test_target_orientations_are_read_in_the_dataset_convention(tmp_path):
    R = Rotation.from_euler("xyz", [[10, -20, 30], [0, 45, -90]], degrees=True).as_matrix()
    frame = pd.DataFrame(
        {"x_mm": [500.0, 600.0], "y_mm": [0.0, 100.0], "z_mm": [300.0, 400.0], **orientation_columns(R)}
    )
    frame.to_csv(tmp_path / "targets.csv", index=False)
    T = read_targets_csv(tmp_path / "targets.csv")
    assert np.allclose(T[:, :3, :3], R, atol=1e-12)
    assert np.allclose(T[:, :3, 3], [[0.5, 0.0, 0.3], [0.6, 0.1, 0.4]])


def test_targets_with_part_of_an_orientation_are_refused(tmp_path):
    pd.DataFrame({"x_mm": [1.0], "y_mm": [2.0], "z_mm": [3.0], "rx_deg": [4.0]}).to_csv(
        tmp_path / "t.csv", index=False
    )
    with pytest.raises(ValueError, match="rx_deg, ry_deg, rz_deg"):
        read_targets_csv(tmp_path / "t.csv")
