"""Diagnosis uses every equation the data has: a 6-DoF probe's orientations reveal an effect its positions
cannot show, and the batched screening reproduces the per-candidate refit on those 6-coordinate rows."""

from dataclasses import replace

import numpy as np
import pytest
from calib_data import ur10_joints
from scipy.spatial.transform import Rotation

from hil.analysis.diagnosis.cautions import CalibrationNote
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
from hil.data.dataset import ORIENTATION_COLUMNS, make_dataset
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform

pytestmark = pytest.mark.timeout(180)

ANGLE_NOISE_RAD = np.deg2rad(0.01)  # the probe's stated noise (hil's default)
POSITION_NOISE_M = 15e-6  # the tracker's MPE model at ~2.5 m, 1 sigma
CYCLIC = DiagnosisOptions(families=("cyclic",))  # only the cyclic errors are candidates


def _wrist_cyclic_campaign(n: int = 250, seed: int = 4, angle_noise_rad: float = ANGLE_NOISE_RAD):
    """A UR10 whose joint 6 has a once-per-turn error (0.02 deg) while the SMR sits on the joint-6 axis: the
    error turns the probe but does not move the SMR."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    errors = {nm: rng.normal(0, 3e-4 if nm[0] in "ad" else 5e-4) for nm in nominal.param_names}
    errors |= {"a6": 0.0, "alpha6": 0.0}  # keep the flange's z axis the joint-6 axis
    true = nominal.with_errors(errors)
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    tool = np.array([0.0, 0.0, 0.11])
    R_flange_probe = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    q = ur10_joints(rng, n)
    dq = np.zeros_like(q)
    dq[:, 5] = 0.3e-3 * np.sin(q[:, 5]) + 0.15e-3 * np.cos(q[:, 5])
    T_flange = forward_kinematics(true, q + dq)
    p = (T_flange[:, :3, :3] @ tool + T_flange[:, :3, 3]) @ T[:3, :3].T + T[:3, 3]
    p += rng.normal(0, POSITION_NOISE_M, p.shape)
    R = T[:3, :3] @ T_flange[:, :3, :3] @ R_flange_probe
    R = Rotation.from_rotvec(rng.normal(0, angle_noise_rad, (n, 3))).as_matrix() @ R
    df = make_dataset(q, p, smr=1, R_tracker_probe=R)
    df.attrs["position_noise_m"] = POSITION_NOISE_M
    return df


def _names(report):
    return [(e["name"], e["joint"]) for e in report.effects_added]


def test_an_effect_seen_only_in_the_probe_orientation_is_selected_with_orientations_and_not_without():
    df = _wrist_cyclic_campaign()
    with_rot = run_diagnosis(df, "ur10", options=CYCLIC)
    assert ("cyclic", 6) in _names(with_rot)
    positions = df.drop(columns=list(ORIENTATION_COLUMNS))
    positions.attrs = dict(df.attrs)
    without = run_diagnosis(positions, "ur10", options=CYCLIC)
    assert ("cyclic", 6) not in _names(without)
    # the batched screening on 6-coordinate rows (positions and weighted rotations) is the refit's answer
    slow = run_diagnosis(df, "ur10", options=replace(CYCLIC, screening="refit"))
    assert _names(slow) == _names(with_rot)
    for x, y in zip(with_rot.final_round, slow.final_round, strict=True):
        assert (x.name, x.joint, x.passed) == (y.name, y.joint, y.passed)
        assert x.gain_mm2 == pytest.approx(y.gain_mm2, rel=1e-7, abs=1e-12)


def test_orientations_far_noisier_than_stated_are_left_out_of_the_tests_and_the_verdict_says_so():
    df = _wrist_cyclic_campaign(angle_noise_rad=3 * ANGLE_NOISE_RAD)  # the probe reads 3x worse than stated
    report = run_diagnosis(df, "ur10", options=CYCLIC)
    assert ("cyclic", 6) not in _names(report)
    notes = [c.text for c in report.verdict["cautions"] if isinstance(c, CalibrationNote)]
    assert any("tested on positions only" in t for t in notes)
