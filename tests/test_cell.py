"""The simulated cell: determinism, the size of each physical effect, noise statistics, geometry."""

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fakes.cell import SMR_RADIUS_M, SimCellConfig, SimulatedCell, SmrLocation, random_rotation
from fakes.physics import chain_frames
from hil.geometry.kinematics import forward_kinematics

RNG = np.random.default_rng(7)
Q_RANDOM = RNG.uniform(-2.5, 2.5, (300, 6))


def _perfect_config(**flags) -> SimCellConfig:
    """A cell with no geometric errors and every effect off, unless switched on by `flags`."""
    return SimCellConfig(**{"geometric_errors": False, "compliance": False, **flags})


def test_same_seed_same_cell_and_noise():
    a, b = SimulatedCell(SimCellConfig(seed=3)), SimulatedCell(SimCellConfig(seed=3))
    assert json.dumps(a.ground_truth()) == json.dumps(b.ground_truth())
    ra, rb = a.run_sequence(Q_RANDOM[:20]), b.run_sequence(Q_RANDOM[:20])
    np.testing.assert_array_equal(ra["p_tracker_measured"], rb["p_tracker_measured"])
    c = SimulatedCell(SimCellConfig(seed=4))
    assert not np.allclose(a.T_tracker_base, c.T_tracker_base)


def test_the_tracker_is_turned_by_the_rotation_scipy_draws_for_the_seed_bit_for_bit():
    """The cell draws its tracker's orientation without scipy (a simulated cell imports no scipy.spatial, at
    start-up or when it turns the first commanded pose): the same matrices as Rotation.random for each integer
    seed, so no seed's cell changed."""
    seeds = [0, 1, 7, *np.random.default_rng(2).integers(2**31, size=300).tolist(), 2**31 - 1]
    for seed in seeds:
        np.testing.assert_array_equal(
            random_rotation(seed), Rotation.random(random_state=seed).as_matrix(), err_msg=str(seed)
        )
    loaded = subprocess.run(
        [
            sys.executable, "-c",
            "import sys, fakes.sim, fakes.ur_script_runtime as rt; rt.pose_to_transform([0.1, 0, 0.4, 0, 3.1, 0.2]); "
            "print(sorted(m for m in sys.modules if 'spatial' in m))",
        ],
        capture_output=True, text=True, check=True, timeout=60,
    )  # fmt: skip
    assert loaded.stdout.strip() == "[]"


def test_true_chain_matches_hil_kinematics_when_effects_are_off():
    cell = SimulatedCell(_perfect_config())
    m = cell.nominal.with_errors({"beta2": 0.01, "a3": 1e-3, "alpha4": -0.02})
    frames = chain_frames(Q_RANDOM, m.theta, m.d, m.a, m.alpha, m.beta)
    np.testing.assert_allclose(frames[:, -1], forward_kinematics(m, Q_RANDOM), atol=1e-12)


def test_geometric_errors_give_mm_level_absolute_error():
    cell = SimulatedCell(SimCellConfig(compliance=False))
    r = cell.run_sequence(Q_RANDOM)
    T = cell.T_tracker_base @ forward_kinematics(cell.nominal, r["q_encoder"])
    p_nest = np.array(cell.ground_truth()["tool_nests_flange_m"][0])
    p_nominal = T[:, :3, :3] @ p_nest + T[:, :3, 3]
    err_mm = np.linalg.norm(r["p_tracker_true"] - p_nominal, axis=1) * 1e3
    assert 0.3 < err_mm.mean() < 5.0  # an uncalibrated arm: 1-3 mm typical


@pytest.mark.parametrize(
    ("flag", "low_mm", "high_mm"),
    [("compliance", 0.1, 2.0), ("cyclic", 0.02, 0.5), ("backlash", 0.02, 0.5), ("thermal", 0.01, 0.5)],
)
def test_each_effect_moves_the_truth_by_its_expected_size(flag, low_mm, high_mm):
    base = SimulatedCell(_perfect_config()).run_sequence(Q_RANDOM)
    cfg = _perfect_config()
    setattr(cfg, flag, True)
    shifted = SimulatedCell(cfg).run_sequence(Q_RANDOM)
    mean_mm = np.linalg.norm(shifted["p_tracker_true"] - base["p_tracker_true"], axis=1).mean() * 1e3
    assert low_mm < mean_mm < high_mm, f"{flag}: mean shift {mean_mm:.4f} mm"


def test_compliance_makes_a_horizontal_arm_sag():
    cfg = _perfect_config(compliance=True)
    cell = SimulatedCell(cfg)
    q = np.array([0.0, 0.0, 0.0, -np.pi / 2, 0.0, 0.0])  # upper and fore arm horizontal
    cell.set_commanded_joints(q)
    z_true = cell.T_base_flange_true()[2, 3]
    z_nominal = forward_kinematics(cell.nominal, q)[0, 2, 3]
    assert z_true < z_nominal - 1e-4  # sags by more than 0.1 mm
    heavier = SimulatedCell(_perfect_config(compliance=True, payload_kg=10.0))
    heavier.set_commanded_joints(q)
    assert heavier.T_base_flange_true()[2, 3] < z_true


def test_backlash_depends_on_approach_direction():
    cell = SimulatedCell(_perfect_config(backlash=True, repeatability_sigma_rad=0.0))
    q = np.array([0.2, -1.0, 1.2, -1.5, -1.5, 0.0])
    cell.set_commanded_joints(q - 0.1)
    cell.set_commanded_joints(q)
    from_below = cell.true_joints()
    cell.set_commanded_joints(q + 0.1)
    cell.set_commanded_joints(q)
    from_above = cell.true_joints()
    gap = from_below - from_above
    assert np.all(gap[:3] > 0) and np.allclose(gap[3:], 0)


def test_thermal_growth_follows_the_warming_clock():
    cell = SimulatedCell(_perfect_config(thermal=True, repeatability_sigma_rad=0.0))
    q = np.array([0.0, -0.3, 0.3, -1.5, -1.5, 0.0])
    cell.set_commanded_joints(q)
    cold = cell.T_base_flange_true()[:3, 3]
    cell.advance_time(3600.0)
    assert cell.meteo().temperature_c > cell.config.ambient_c + 5
    warm = cell.T_base_flange_true()[:3, 3]
    growth = np.linalg.norm(warm) / np.linalg.norm(cold) - 1
    assert 0.5 * 23e-6 * 5 < growth < 23e-6 * 12


def test_tracker_noise_matches_configured_sigma():
    cell = SimulatedCell(SimCellConfig(seed=1))
    smr = 2  # fixed floor nest: only tracker noise moves its readings
    truth = cell.smr_center_tracker(smr)
    readings = cell.tracker_reading(smr, np.tile(truth, (4000, 1)))
    sigma = cell.tracker_sigma_m(np.linalg.norm(truth))
    std = readings.std(axis=0)
    assert np.all(np.abs(std / sigma - 1) < 0.08), (std, sigma)
    offset = readings.mean(axis=0) - truth
    np.testing.assert_allclose(offset, cell.ground_truth()["smr_centering_m"][smr - 1], atol=4 * sigma / 60)


def test_encoder_and_repeatability_noise():
    """Each motion draws its jitter and encoder noise; a standing arm (the controller's idle tick repeats the
    same command) reads the same encoders and draws nothing."""
    cell = SimulatedCell(SimCellConfig(seed=2, compliance=False))
    q = np.array([0.1, -1.2, 1.3, -1.6, -1.5, 0.3])
    encoders, visits = [], []
    for _ in range(600):
        cell.set_commanded_joints(q + 0.05)
        cell.set_commanded_joints(q + 0.05)  # stands: the next change starts a new motion
        cell.set_commanded_joints(q)
        encoders.append(cell.encoder_joints())
        visits.append(cell.true_joints())
        assert not cell.set_commanded_joints(q)
        np.testing.assert_array_equal(cell.encoder_joints(), encoders[-1])
    np.testing.assert_allclose(np.std(encoders, axis=0), cell.config.encoder_sigma_rad, rtol=0.15)
    np.testing.assert_allclose(np.std(visits, axis=0), cell.config.repeatability_sigma_rad, rtol=0.15)


def test_the_same_array_commanded_again_and_again_stands_and_moves_as_fresh_copies_of_it_do():
    """The controller hands the cell the same array every cycle while the arm stands (the cell then skips its
    checks): the cell answers, counts motions and reads its encoders exactly as for a fresh copy every cycle,
    also after a batch of commands and a change back to an array it saw before."""
    q = np.array([0.1, -1.2, 1.3, -1.6, -1.5, 0.3])
    same, fresh = SimulatedCell(SimCellConfig(seed=4)), SimulatedCell(SimCellConfig(seed=4))
    a, b = q + 0.02, q - 0.03
    for step, array in enumerate([a, a, b, b, a, a, a, a + 1e-13, a]):
        if step == 5:
            for cell in (same, fresh):
                cell.run_sequence(np.array([q, q + 0.01]))
        moved = same.set_commanded_joints(array)
        assert moved == fresh.set_commanded_joints(array.copy())
        assert moved == (step in (0, 2, 4, 5))
        assert same.motions == fresh.motions
        np.testing.assert_array_equal(same.encoder_joints(), fresh.encoder_joints())
        np.testing.assert_array_equal(same.commanded_q, fresh.commanded_q)


def test_flange_holes_follow_the_tool_paper_layout():
    cell = SimulatedCell(SimCellConfig(hole_position_sigma_m=0.0))
    holes = np.array(cell.ground_truth()["holes_flange_m"])
    radii = np.linalg.norm(holes[:6, :2], axis=1)
    np.testing.assert_allclose(radii, cell.config.hole_circle_radius_m, atol=1e-12)
    angles = np.degrees(np.arctan2(holes[:6, 1], holes[:6, 0]))
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(angles))), np.radians(60), atol=1e-12)
    bisector = holes[2, :2] / np.linalg.norm(holes[2, :2]) + holes[3, :2] / np.linalg.norm(holes[3, :2])
    hole7_dir = holes[6, :2] / np.linalg.norm(holes[6, :2])
    np.testing.assert_allclose(hole7_dir, bisector / np.linalg.norm(bisector), atol=1e-12)
    # A ball seated in a hole sits lower than one resting on the face.
    assert np.all(holes[:, 2] < SMR_RADIUS_M)


def test_smr_placement_and_errors():
    cell = SimulatedCell()
    with pytest.raises(ValueError, match="tool covers the flange holes"):
        cell.place_smr(1, SmrLocation("face", point_m=(0.02, 0.01)))
    cell.unmount_tool()
    with pytest.raises(ValueError, match="mount the tool before"):
        cell.place_smr(1, SmrLocation("nest", index=1))
    cell.place_smr(1, SmrLocation("face", point_m=(0.02, 0.01)))
    T = cell.T_tracker_base @ cell.T_base_flange_true()
    expected = T[:3, :3] @ np.array([0.02, 0.01, SMR_RADIUS_M]) + T[:3, 3]
    np.testing.assert_allclose(cell.smr_center_tracker(1), expected, atol=1e-12)
    with pytest.raises(ValueError, match="holes are numbered"):
        cell.place_smr(1, SmrLocation("hole", index=9))
    with pytest.raises(ValueError, match="no SMR 7"):
        cell.place_smr(7, SmrLocation("nest", index=1))
    cell.mount_tool()  # the SMR comes off the face first
    assert cell.smr_location(1).kind == "fixed"
    with pytest.raises(ValueError, match="needs an index"):
        SmrLocation("nest")
    with pytest.raises(ValueError, match="fixed in the room"):
        cell.run_sequence(Q_RANDOM[:3], smr_id=2)


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="unknown robot"):
        SimCellConfig(robot="kuka")
    with pytest.raises(ValueError, match="finite"):
        SimulatedCell().set_commanded_joints(np.array([0, 0, np.nan, 0, 0, 0]))


def test_the_tool_comes_off_and_goes_back_on_turned():
    """Mounting the tool 60 deg off its dowel turns every nest about flange z; the SMR in a nest comes off with it."""
    cell = SimulatedCell()
    drawn = cell.smr_point_flange(SmrLocation("nest", index=2))
    cell.unmount_tool()
    assert cell.smr_location(1).kind == "fixed" and not cell.ground_truth()["tool_mounted"]
    cell.mount_tool(np.deg2rad(60.0))
    turned = cell.smr_point_flange(SmrLocation("nest", index=2))
    c, s = np.cos(np.deg2rad(60.0)), np.sin(np.deg2rad(60.0))
    np.testing.assert_allclose(turned, [c * drawn[0] - s * drawn[1], s * drawn[0] + c * drawn[1], drawn[2]])
