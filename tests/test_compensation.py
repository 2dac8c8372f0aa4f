"""Model-based pseudo-target compensation: the model is the truth here, so what is left is the loop's own error.

The remaining error of every answer is re-checked through `CalibratedModel.predict_poses` (the public
`predict` on a dataset frame, orientation through the joint offsets), not the compensation's own predictor.
"""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from calib_data import compliant_ur10, ur10_joints
from scipy.spatial.transform import Rotation

from hil.compensation.model_based import (
    ENSEMBLE,
    STATUSES,
    CompensationOptions,
    PosePredictor,
    PseudoTargetIK,
    TargetConditions,
    compensate,
    compensate_path,
)
from hil.compensation.target_update import GENERATORS, pose_errors, update_pseudo_target
from hil.data.dataset import make_dataset, orientation_columns
from hil.geometry.ik import NewtonOptions, default_home, newton_ik, same_branch_seed, ur_branch_index
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import make_transform, transform_points
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import make_effect
from hil.model.residual_maps import make_map
from tests.cli_in_process import hil_in_process

pytestmark = pytest.mark.timeout(120)
TOOL = np.array([0.03, -0.02, 0.11])
LOOSE_NEWTON = NewtonOptions(max_steps=16, tol_position=1e-8, tol_rotation=1e-7)  # the loop's tolerances


def ur10_model(seed: int = 0) -> CalibratedModel:
    """A calibrated UR10: geometric errors, a tracker 2 m away and gravity compliance on joints 2 and 3."""
    return compliant_ur10(seed, {1: TOOL}, TOOL, n_poses=200)


@pytest.fixture(scope="module")
def model():
    return ur10_model()


def reachable_targets(model: CalibratedModel, n: int, seed: int) -> np.ndarray:
    return model.predict_poses(ur10_joints(np.random.default_rng(seed), n))


@pytest.mark.parametrize("ik_model", ["kinematic", "nominal"])
def test_true_model_leaves_under_a_micrometre(model, ik_model):
    T_target = reachable_targets(model, 300, seed=1)
    for targets in (T_target[:, :3, 3], T_target):
        res = compensate(model, targets, CompensationOptions(threshold_m=1e-7, ik_model=ik_model))
        assert np.all(res.status == "ok"), res.summary()
        reached = model.predict_poses(res.q)
        dp, dr = pose_errors(reached, T_target)
        assert dp.max() < 1e-6
        assert np.mean(res.initial_error_m) > 2e-4  # there was something to compensate
        np.testing.assert_allclose(res.error_m, dp, atol=1e-9)  # the loop's own measure agrees
        if targets.ndim == 3:
            assert dr.max() < 1e-6
        assert res.iterations.max() <= 10 and np.all(res.iterations >= 1)
        hist = res.history
        assert np.all(np.isfinite(hist[0])) and np.nanmax(hist[1]) < np.nanmax(hist[0])


@pytest.mark.parametrize("generator", GENERATORS)
def test_every_generator_converges(model, generator):
    T_target = reachable_targets(model, 200, seed=2)
    res = compensate(model, T_target, CompensationOptions(generator=generator, threshold_m=1e-6, max_iter=15))
    reached = model.predict_poses(res.q)
    dp, dr = pose_errors(reached, T_target)
    assert dp.max() < 1e-6
    if generator == "fixed":  # keeps the target's orientation: the orientation error is never corrected
        # (a target whose model orientation error is already tiny, where the joints carry little gravity
        # torque, converges as it is)
        assert np.all((res.status == "stalled") | (dr < 1e-5)) and np.mean(res.status == "stalled") > 0.9
        assert np.median(dr) > 1e-4
    else:
        assert np.all(res.status == "ok"), res.summary()
        assert dr.max() < 1e-5


def test_ensemble_is_never_worse_than_the_best_single_generator(model):
    T_target = reachable_targets(model, 200, seed=3)
    kw = {"threshold_m": 1e-12, "max_iter": 1}  # one update: the generators still differ
    singles = np.stack(
        [compensate(model, T_target, CompensationOptions(generator=g, **kw)).cost_m for g in GENERATORS]
    )
    ens = compensate(model, T_target, CompensationOptions(generator=ENSEMBLE, **kw))
    assert np.all(ens.cost_m <= singles.min(axis=0) * (1 + 1e-12))
    assert len(set(ens.generator)) > 1  # different generators win on different targets
    dp, dr = pose_errors(model.predict_poses(ens.q), T_target)
    np.testing.assert_allclose(np.hypot(dp, 0.1 * dr), ens.cost_m, rtol=1e-6, atol=1e-12)


def test_a_2000_point_circle_stays_on_one_branch(model):
    angle = np.linspace(0.0, 2.0 * np.pi, 2000, endpoint=False)
    circle_base = np.array([0.7, 0.1, 0.3]) + 0.2 * np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1)
    targets = transform_points(model.T_tracker_base, circle_base)
    res = compensate_path(model, targets, options=CompensationOptions(threshold_m=1e-7))
    assert np.all(res.status == "ok")
    assert not res.branch_jump.any()
    assert len(np.unique(ur_branch_index(model.kinematic, res.q))) == 1
    assert np.abs(np.diff(res.q, axis=0)).max() < 0.01  # neighbours' joints stay close: no flips
    dp, _ = pose_errors(model.predict_poses(res.q), make_transform(np.eye(3), targets))
    assert dp.max() < 1e-6


def test_unreachable_targets_are_marked_not_dropped(model):
    T_target = reachable_targets(model, 5, seed=4)
    far_base = np.array([[3.0, 0.0, 0.5], [1.6 * np.cos(0.3), 1.6 * np.sin(0.3), 0.2]])
    far = transform_points(model.T_tracker_base, far_base)
    points = np.concatenate([T_target[:, :3, 3], far])
    res = compensate(model, points)
    assert list(res.status[:5]) == ["ok"] * 5
    assert res.status[5] == "unreachable"
    assert res.status[6] in ("unreachable", "singular", "no_ik_solution")
    assert np.all(np.isnan(res.q[5:])) and np.all(np.isnan(res.error_m[5:]))
    poses = np.concatenate([T_target, make_transform(np.broadcast_to(np.eye(3), (2, 3, 3)), far)])
    res = compensate(model, poses)
    assert list(res.status) == ["ok"] * 5 + ["unreachable"] * 2


def test_no_answer_is_silently_wrong_near_singularities(model):
    # Wrist (q5 = 0) and stretched-elbow (q3 = 0) postures, and a point just beyond the arm's reach:
    # every target is either below the threshold for real, or marked with what went wrong and the error
    # its joints really leave (NaN joints when no IK answer exists at all).
    q = np.array([[0.3, -1.2, 1.5, -1.0, 0.0, 0.4], [0.2, -0.6, 0.0, -1.0, -1.2, 0.1]])
    T_target = model.predict_poses(q)
    beyond = transform_points(model.T_tracker_base, np.array([[1.45 * np.cos(0.3), 1.45 * np.sin(0.3), 0.2]]))
    for targets in (T_target, np.concatenate([T_target[:, :3, 3], beyond])):
        res = compensate(model, targets, CompensationOptions(threshold_m=1e-7))
        assert set(res.status) <= set(STATUSES)
        poses = (
            make_transform(np.broadcast_to(np.eye(3), (len(targets), 3, 3)), targets)
            if targets.ndim == 2
            else targets
        )
        has_q = np.all(np.isfinite(res.q), axis=1)
        dp, _ = pose_errors(model.predict_poses(res.q[has_q]), poses[has_q])
        np.testing.assert_allclose(res.error_m[has_q], dp, atol=1e-9)
        assert np.all((res.status[has_q] == "ok") == (res.cost_m[has_q] < 1e-7))
        assert np.all(res.status[~has_q] != "ok") and np.all(np.isnan(res.error_m[~has_q]))
    assert res.status[-1] != "ok"  # beyond reach


def test_residual_map_is_compensated_and_its_volume_warns(model):
    rng = np.random.default_rng(5)
    q = ur10_joints(rng, 150)
    p_base = (
        forward_kinematics(model.kinematic, q)[:, :3, :3] @ TOOL
        + forward_kinematics(model.kinematic, q)[:, :3, 3]
    )
    residual = 2e-4 * np.stack([np.sin(3 * p_base[:, 0]), np.cos(2 * p_base[:, 1]), p_base[:, 2]], 1)
    gp = make_map("gp").fit(q, p_base, residual, 5e-6)
    with_map = replace(model, residual_map=gp.to_dict())
    targets = with_map.predict_poses(q[:40])[:, :3, 3]  # inside the volume the map was fitted in
    res = compensate(with_map, targets, CompensationOptions(threshold_m=1e-7))
    assert np.all(res.status == "ok")
    assert np.abs(with_map.predict(make_dataset(res.q, targets, smr=1)) - targets).max() < 1e-6
    outside = transform_points(model.T_tracker_base, np.array([[0.9, 0.0, 0.2]]))
    with pytest.warns(UserWarning, match="outside the calibrated volume"):
        res = compensate(with_map, np.concatenate([targets[:3], outside]))
    assert list(res.outside_volume) == [False, False, False, True]


@pytest.mark.parametrize("generator", GENERATORS)
def test_a_perfect_move_makes_the_target_the_next_pseudo_target(generator):
    # When the reached pose equals the pseudo target, every generator asks for the target itself: the
    # update works the same whether the reached poses are predicted or measured.
    rng = np.random.default_rng(7)
    T_pseudo = make_transform(Rotation.random(20, random_state=1).as_matrix(), rng.normal(0, 1, (20, 3)))
    T_target = make_transform(Rotation.random(20, random_state=2).as_matrix(), rng.normal(0, 1, (20, 3)))
    new = update_pseudo_target(generator, T_target, T_pseudo, T_pseudo)
    if generator == "fixed":
        np.testing.assert_allclose(new, T_target, atol=1e-12)
    else:
        np.testing.assert_allclose(new, T_target, atol=1e-9)
    with pytest.raises(ValueError, match="unknown pseudo-target generator"):
        update_pseudo_target("nope", T_target, T_pseudo, T_pseudo)


def test_predictor_matches_the_public_prediction(model):
    q = ur10_joints(np.random.default_rng(8), 50)
    T = PosePredictor(model)(q)
    np.testing.assert_allclose(T, model.predict_poses(q), atol=1e-12)


def test_bad_targets_are_rejected(model):
    with pytest.raises(ValueError, match="points"):
        compensate(model, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        compensate(model, np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="generator"):
        compensate(model, np.zeros((1, 4, 4)) + np.eye(4), CompensationOptions(generator="best"))


_hil = hil_in_process


def orientation_errors(model: CalibratedModel, q: np.ndarray, T_target: np.ndarray) -> np.ndarray:
    """Angle (N,) rad between the flange orientation the model predicts at joints q (its public context and
    geometry, not hil.compensation.model_based's predictor) and the targets' orientations."""
    ctx, _ = model.context(make_dataset(q, np.zeros((len(q), 3)), smr=1))
    R = (
        model.T_tracker_base[:3, :3]
        @ forward_kinematics(model.kinematic, q + model.joint_offsets(ctx))[:, :3, :3]
    )
    return Rotation.from_matrix(np.swapaxes(T_target[:, :3, :3], 1, 2) @ R).magnitude()


def test_cli(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    T_target = reachable_targets(model, 20, seed=9)
    far = transform_points(model.T_tracker_base, np.array([[3.0, 0.0, 0.5]]))
    points = np.concatenate([T_target[:, :3, 3], far]) * 1000.0
    pd.DataFrame(points, columns=["x_mm", "y_mm", "z_mm"]).to_csv(tmp_path / "pts.csv", index=False)
    out = _hil("compensate", "model.json", "pts.csv", "-o", "joints.csv", cwd=tmp_path, capsys=capsys)
    assert out[0] == 0, out[2]
    df = pd.read_csv(tmp_path / "joints.csv")
    assert len(df) == 21
    assert list(df["status"]) == ["ok"] * 20 + ["unreachable"]
    assert df.loc[20, ["q1_rad", "q6_rad"]].isna().all()
    assert (df["error_mm"][:20] < 0.01).all() and (df["iterations"][:20] >= 1).all()
    q = df[[f"q{i}_rad" for i in range(1, 7)]].to_numpy()[:20]
    assert np.abs(model.predict_poses(q)[:, :3, 3] * 1000.0 - points[:20]).max() < 0.01

    # rx/ry/rz_deg as in a dataset: the targeted frame's orientation in the tracker frame, xyz-extrinsic Euler
    poses = pd.DataFrame(points[:20], columns=["x_mm", "y_mm", "z_mm"]).assign(
        **orientation_columns(T_target[:, :3, :3])
    )
    poses.to_csv(tmp_path / "poses.csv", index=False)
    out = _hil(
        "compensate",
        "model.json",
        "poses.csv",
        "-o",
        "j2.csv",
        "--generator",
        "ensemble",
        "--threshold-mm",
        "0.001",
        cwd=tmp_path,
        capsys=capsys,
    )
    assert out[0] == 0, out[2]
    df = pd.read_csv(tmp_path / "j2.csv")
    assert (df["status"] == "ok").all() and (df["error_mm"] < 0.001).all()
    assert (df["rotation_error_deg"] < 1e-3).all()
    q = df[[f"q{i}_rad" for i in range(1, 7)]].to_numpy()
    assert orientation_errors(model, q, T_target).max() < np.deg2rad(1e-3)  # the orientation the file meant

    intrinsic = poses.copy()  # the same targets in the other convention, named by the option
    intrinsic[["rx_deg", "ry_deg", "rz_deg"]] = Rotation.from_matrix(T_target[:, :3, :3]).as_euler(
        "XYZ", True
    )
    intrinsic.to_csv(tmp_path / "intrinsic.csv", index=False)
    args = (
        "intrinsic.csv",
        "-o",
        "j4.csv",
        "--orientation-convention",
        "xyz-intrinsic",
        "--threshold-mm",
        "0.001",
    )
    out = _hil("compensate", "model.json", *args, cwd=tmp_path, capsys=capsys)
    assert out[0] == 0, out[2]
    df = pd.read_csv(tmp_path / "j4.csv")
    q = df[[f"q{i}_rad" for i in range(1, 7)]].to_numpy()
    assert orientation_errors(model, q, T_target).max() < np.deg2rad(1e-3)

    poses.drop(columns="rz_deg").to_csv(tmp_path / "bad.csv", index=False)
    out = _hil("compensate", "model.json", "bad.csv", "-o", "j3.csv", cwd=tmp_path, capsys=capsys)
    assert out[0] == 2 and "rx_deg, ry_deg, rz_deg" in out[2]
    out = _hil("compensate", "model.json", "missing.csv", "-o", "j3.csv", cwd=tmp_path, capsys=capsys)
    assert out[0] == 2 and "hil compensate: " in out[2] and "what to do: " in out[2]


def test_the_update_and_ik_steps_work_on_poses_from_elsewhere(model):
    # The measured loop's building blocks: reached poses come from outside (here a second model with
    # other effects plays the measured cell), the update and the seeded IK do the rest.
    cell = ur10_model(seed=11)
    cell = replace(cell, T_tracker_base=model.T_tracker_base, tools=model.tools)
    T_target = reachable_targets(model, 50, seed=12)
    ik = PseudoTargetIK(model)
    seed, _ = same_branch_seed(model.kinematic, ik.to_flange(T_target), default_home(model.kinematic))
    q, reason = ik.solve(T_target, seed)
    assert np.all(reason == "ok")
    T_p = T_target.copy()
    errors = []
    for _ in range(6):
        T_reached = cell.predict_poses(q)
        errors.append(pose_errors(T_reached, T_target)[0].max())
        T_p = update_pseudo_target("quaternion", T_target, T_reached, T_p)
        q, reason = ik.solve(T_p, q)
        assert np.all(reason == "ok")
    assert errors[0] > 1e-3 and errors[-1] < 1e-7


@pytest.mark.parametrize("mode", ["pose", "position"])
def test_newton_rows_ended_by_the_convergence_bound_are_converged(model, mode):
    """Rows that Newton ends by its second-order bound, without evaluating them again, are within the
    tolerance when evaluated, and their reported error bounds the true one."""
    kin = model.kinematic
    rng = np.random.default_rng(21)
    q_true = ur10_joints(rng, 400)
    T = forward_kinematics(kin, q_true)
    target = T if mode == "pose" else T[:, :3, :3] @ TOOL + T[:, :3, 3]
    tool = None if mode == "pose" else TOOL
    for noise in (1e-2, 1e-3):
        seed = q_true + rng.normal(0.0, noise, q_true.shape)
        res = newton_ik(kin, target, seed, mode, tool, LOOSE_NEWTON)
        assert res.converged.all()
        ended_by_bound = np.isnan(res.pose[:, 0, 0])
        assert 0 < ended_by_bound.sum() < len(seed)  # both ways of ending occur
        T_q = forward_kinematics(kin, res.q)
        if mode == "pose":
            dp = np.linalg.norm(T_q[:, :3, 3] - T[:, :3, 3], axis=1)
            dr = pose_errors(T_q, T)[1]
            assert np.all(dr <= res.rotation_error + 1e-15) and dr.max() < 1e-7
        else:
            dp = np.linalg.norm(T_q[:, :3, :3] @ TOOL + T_q[:, :3, 3] - target, axis=1)
        assert np.all(dp <= res.error + 1e-15) and dp.max() < 1e-8
        evaluated = ~ended_by_bound
        np.testing.assert_allclose(res.pose[evaluated], T_q[evaluated], atol=1e-14)


def test_newton_warm_start_is_the_cold_start_without_its_first_evaluation(model):
    kin = model.kinematic
    q = ur10_joints(np.random.default_rng(22), 300)
    T = forward_kinematics(kin, q)
    first = newton_ik(kin, T, q + 1e-3, options=LOOSE_NEWTON)
    moved = T.copy()
    moved[:, :3, 3] += 2e-4  # the next pseudo targets, a little away
    cold = newton_ik(kin, moved, first.q, options=LOOSE_NEWTON)
    warm = newton_ik(kin, moved, first.q, options=LOOSE_NEWTON, start=(first.pose, first.jacobian))
    assert np.isnan(first.pose[:, 0, 0]).any()  # rows without a pose at the seed are evaluated then
    np.testing.assert_allclose(warm.q, cold.q, atol=1e-13)
    assert np.array_equal(warm.converged, cold.converged) and np.array_equal(warm.steps, cold.steps)


def test_large_batches_run_in_blocks_with_the_same_answer(model, monkeypatch):
    """compensate splits large batches into blocks; per-target drivers (backlash approach signs) and
    seeds follow their targets, the result is the one of a single batch."""
    backlash = make_effect("backlash", 2)
    backlash.params = np.array([3e-4])
    with_backlash = model.with_effect(backlash)
    rng = np.random.default_rng(23)
    q = ur10_joints(rng, 45)
    approach = rng.choice([-1.0, 1.0], size=q.shape)
    T_target = model.predict_poses(q)
    for generator in ("yin", ENSEMBLE):
        kw = {
            "options": CompensationOptions(generator=generator),
            "conditions": TargetConditions(approach=approach),
            "q_seed": q + 0.01,
        }
        monkeypatch.setattr("hil.compensation.model_based.BLOCK_TARGETS", 2048)
        whole = compensate(with_backlash, T_target, **kw)
        monkeypatch.setattr("hil.compensation.model_based.BLOCK_TARGETS", 16)
        blocks = compensate(with_backlash, T_target, **kw)
        assert np.all(whole.status == "ok") and np.array_equal(blocks.status, whole.status)
        for name in ("q", "error_m", "rotation_error_rad", "cost_m", "history", "initial_error_m"):
            np.testing.assert_allclose(
                getattr(blocks, name), getattr(whole, name), atol=1e-12, equal_nan=True
            )
        if generator == "yin":  # (an ensemble's near-ties between generators may fall either way)
            assert np.array_equal(blocks.iterations, whole.iterations)


def test_update_ik_left_by_newton_is_searched_once_for_all_blocks_and_resumes(model, monkeypatch):
    """An update whose IK Newton leaves waits until every block's loop has run; then one solve_ik (LM from
    the previous joints) searches all such rows at once, and those it solves go on from the iteration they
    stopped in. With Newton cut to one step nearly every update goes that way, in rounds; the answers are
    those of the full Newton within the IK's tolerance, checked through the public prediction."""
    from hil.compensation import model_based

    T_target = reachable_targets(model, 90, seed=31)
    options = CompensationOptions(threshold_m=1e-7)
    full = compensate(model, T_target, options)
    calls = []
    fallback = model_based.PseudoTargetIK._fallback

    def spy(self, target, q_seed, ik_options):
        if ik_options == model_based.UPDATE_FALLBACK:
            calls.append(len(target))
        return fallback(self, target, q_seed, ik_options)

    monkeypatch.setattr(model_based.PseudoTargetIK, "_fallback", spy)
    monkeypatch.setattr(model_based, "NEWTON_STEPS", 1)
    monkeypatch.setattr(model_based, "BLOCK_TARGETS", 30)  # three blocks, one search per round
    cut = compensate(model, T_target, options)
    assert np.all(full.status == "ok") and np.all(cut.status == "ok"), cut.summary()
    assert sum(calls) >= len(T_target) and len(calls) <= cut.iterations.max(), calls
    np.testing.assert_allclose(cut.q, full.q, atol=1e-6)
    dp, dr = pose_errors(model.predict_poses(cut.q), T_target)
    assert np.all(np.hypot(dp, 0.1 * dr) < 1e-7)
