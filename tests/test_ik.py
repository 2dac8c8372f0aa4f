"""Inverse kinematics: closed-form UR branches, batched LM round trips, limits, unreachable targets,
position mode, calibrated (erroneous) models and input validation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hil.geometry import ik
from hil.geometry.kinematics import forward_kinematics, tool_points
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform, pose_error

UR_NAMES = ("ur5", "ur10", "ur5e", "ur10e")


def random_joints(model, n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(model.joint_limits[:, 0], model.joint_limits[:, 1], size=(n, model.n_joints))


def pose_errors(model, q, targets, T_flange_tool=None):
    """Independent check: (position error m, rotation error rad) of FK(q) against the targets."""
    T_ft = np.eye(4) if T_flange_tool is None else T_flange_tool
    e = pose_error(forward_kinematics(model, q) @ T_ft, targets)
    return np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)


def assert_honest(result, pos_err, rot_err=None, tol_pos=1e-10, tol_rot=1e-9):
    """success <=> independently computed errors below tolerance; reasons consistent with success."""
    good = pos_err < tol_pos
    if rot_err is not None:
        good &= rot_err < tol_rot
    np.testing.assert_array_equal(result.success, good)
    np.testing.assert_array_equal(result.reason == "ok", result.success)
    assert set(np.unique(result.reason)) <= set(ik.REASONS)


# ------------------------------------------------------------------------------------ analytic UR IK


@pytest.mark.parametrize("name", UR_NAMES)
def test_analytic_branches_reproduce_pose(name):
    m = get_robot(name)
    q_true = random_joints(m, 500, seed=1)
    T = forward_kinematics(m, q_true)
    qb, valid = ik.ur_analytic_ik(m, T)
    assert qb.shape == (500, 8, 6) and valid.shape == (500, 8)
    assert valid.mean() > 0.8  # most random poses have all 8 branches
    assert np.all(valid.sum(axis=1) >= 2)  # the generating configuration is always among them
    assert np.all(np.isnan(qb[~valid]))
    Tb = forward_kinematics(m, np.nan_to_num(qb.reshape(-1, 6))).reshape(500, 8, 4, 4)
    err = np.abs(Tb - T[:, None])[:, :, :3, :].max(axis=(2, 3))
    assert err[valid].max() < 1e-9
    # Branch bits: elbow bit 0 -> q3 >= 0, wrist bit 0 -> q5 >= 0 (q5 = theta offsets are zero on URs).
    branch = np.arange(8)
    q3, q5 = qb[..., 2], qb[..., 4]
    assert np.all(q3[:, branch % 2 == 0][valid[:, branch % 2 == 0]] >= 0)
    assert np.all(q3[:, branch % 2 == 1][valid[:, branch % 2 == 1]] <= 0)
    assert np.all(q5[:, (branch // 2) % 2 == 0][valid[:, (branch // 2) % 2 == 0]] >= 0)


@pytest.mark.parametrize("name", UR_NAMES)
def test_nearest_branch_recovers_generating_joints_across_2pi(name):
    m = get_robot(name)
    q_true = random_joints(m, 300, seed=2)  # +-2 pi: the analytic output in (-pi, pi] must be shifted
    qb, valid = ik.ur_analytic_ik(m, forward_kinematics(m, q_true))
    q, idx, found = ik.select_nearest_branch(m, qb, valid, q_true)
    assert np.all(found)
    assert idx.shape == (300,)
    np.testing.assert_allclose(q, q_true, atol=1e-6)


def test_analytic_unreachable_and_non_ur():
    m = get_robot("ur5")
    far = make_transform(np.eye(3), [2.0, 0.0, 0.3])
    qb, valid = ik.ur_analytic_ik(m, far)
    assert not valid.any() and np.isnan(qb).all()
    with pytest.raises(ValueError, match="not a UR-shaped"):
        ik.ur_analytic_ik(get_robot("irb2600"), far)


def test_nearest_equivalent_respects_limits():
    m = get_robot("ur10")
    m = replace(m, joint_limits=np.array([[-1, 1], [-7, 7], [-7, 7], [-7, 7], [-7, 7], [3.0, 9.0]]))
    q, ok = ik.nearest_equivalent(m, np.array([[0.5, 0.0, 0.0, 0.0, 0.0, -2.0]]), np.zeros(6))
    assert ok[0]
    assert q[0, 5] == pytest.approx(-2.0 + 2 * np.pi)  # only equivalent inside [3, 9]
    _, ok = ik.nearest_equivalent(m, np.array([[2.0, 0, 0, 0, 0, 4.0]]), np.zeros(6))
    assert not ok[0]  # joint 1 at 2 rad has no equivalent in [-1, 1]


# ------------------------------------------------------------------------------------ LM round trips


@pytest.mark.parametrize("name", UR_NAMES)
def test_round_trip_seeded_ur(name):
    m = get_robot(name)
    q_true = random_joints(m, 2000, seed=3)
    T = forward_kinematics(m, q_true)
    res = ik.solve_ik(m, T)
    pos, rot = pose_errors(m, res.q, T)
    assert_honest(res, pos, rot)
    assert res.success.mean() >= 0.999
    assert pos[res.success].max() < 1e-9
    assert np.all(m.within_limits(res.q))
    np.testing.assert_allclose(res.error, pos, atol=1e-15)


def test_round_trip_unseeded_uses_random_restarts():
    m = get_robot("ur10")
    q_true = random_joints(m, 300, seed=4)
    T = forward_kinematics(m, q_true)
    res = ik.solve_ik(m, T, options=ik.IKOptions(use_analytic=False))
    pos, rot = pose_errors(m, res.q, T)
    assert_honest(res, pos, rot)
    assert res.success.mean() >= 0.99
    assert res.attempts.max() > 1  # the home seed alone does not solve every target


def test_seed_and_q_near_choose_the_configuration():
    m = get_robot("ur10e")
    q_true = random_joints(m, 200, seed=5)
    T = forward_kinematics(m, q_true)
    rng = np.random.default_rng(0)
    res = ik.solve_ik(m, T, q_seed=q_true + rng.normal(scale=1e-3, size=q_true.shape))
    assert res.success.all()
    np.testing.assert_allclose(res.q, q_true, atol=1e-7)
    assert np.all(res.attempts == 1)
    # q_near selects the analytic branch nearest to it.
    target = T[:1]
    qb, valid = ik.ur_analytic_ik(m, target)
    for b in np.flatnonzero(valid[0]):
        res = ik.solve_ik(m, target, q_near=qb[0, b])
        np.testing.assert_allclose(res.q[0], qb[0, b], atol=1e-7)


@pytest.mark.parametrize("name", ["ur10", "ur5e"])
def test_models_with_errors_converge_from_nominal_analytic_seed(name):
    nominal = get_robot(name)
    real = nominal.with_errors(
        {"beta2": 2e-3, "beta3": -1.5e-3, "a2": 1e-3, "a3": -5e-4, "theta4": 2e-3, "alpha5": 1e-3, "d6": 5e-4}
    )
    q_true = random_joints(real, 1000, seed=6)
    T = forward_kinematics(real, q_true)
    # The closed form (which ignores beta and alpha errors) alone is off by far more than tolerance...
    qb, valid = ik.ur_analytic_ik(real, T)
    q0, _, found = ik.select_nearest_branch(real, qb, valid, q_true)
    pos0, _ = pose_errors(real, q0[found], T[found])
    assert np.median(pos0) > 1e-4
    # ... and LM from it converges on the erroneous model without random restarts.
    res = ik.solve_ik(real, T, options=ik.IKOptions(restarts=0))
    pos, rot = pose_errors(real, res.q, T)
    assert_honest(res, pos, rot)
    assert res.success.mean() >= 0.999
    assert np.median(res.iterations) >= 2


def test_irb2600_round_trip():
    m = get_robot("irb2600")
    q_true = random_joints(m, 1000, seed=7)
    T = forward_kinematics(m, q_true)
    res = ik.solve_ik(m, T)
    pos, rot = pose_errors(m, res.q, T)
    assert_honest(res, pos, rot)
    assert res.success.mean() >= 0.995
    assert np.all(m.within_limits(res.q))
    assert set(res.reason[~res.success]) <= {"joint_limits", "max_iter", "singular"}


def test_pose_mode_with_tool_frame():
    m = get_robot("ur5")
    T_flange_tool = make_transform(Rotation.from_rotvec([0.2, -0.1, 0.5]).as_matrix(), [0.01, -0.02, 0.18])
    q_true = random_joints(m, 500, seed=8)
    T_base_tool = forward_kinematics(m, q_true) @ T_flange_tool
    res = ik.solve_ik(m, T_base_tool, T_flange_tool=T_flange_tool)
    pos, rot = pose_errors(m, res.q, T_base_tool, T_flange_tool)
    assert_honest(res, pos, rot)
    assert res.success.mean() >= 0.998


@pytest.mark.parametrize("name", ["ur10", "irb2600"])
def test_position_mode_with_tool_point(name):
    m = get_robot(name)
    p_tool = np.array([0.01, 0.02, 0.15])
    q_true = random_joints(m, 1000, seed=9)
    P = tool_points(m, q_true, p_tool)
    res = ik.solve_ik(m, P, mode="position", p_flange_tool=p_tool)
    pos = np.linalg.norm(tool_points(m, res.q, p_tool) - P, axis=1)
    assert_honest(res, pos)
    assert res.success.mean() >= 0.995
    assert np.isnan(res.rotation_error).all()
    # Without the tool offset the same joints miss the points by the tool length.
    res_flange = ik.solve_ik(m, P[:20], mode="position")
    assert np.linalg.norm(tool_points(m, res_flange.q, p_tool) - P[:20], axis=1).min() > 1e-3


# ------------------------------------------------------------------------------------ failures


def test_target_only_reachable_outside_reduced_limits_fails_with_joint_limits():
    full = get_robot("ur10")
    limits = full.joint_limits.copy()
    limits[0] = [-0.5, 0.5]
    tight = replace(full, joint_limits=limits)
    q_true = np.array([[2.0, -1.2, 1.4, -1.8, -1.5, 0.3], [-2.0, -1.0, -1.0, 0.5, 1.2, -0.4]])
    T = forward_kinematics(full, q_true)
    # Precondition: no analytic branch has joint 1 (mod 2 pi) inside [-0.5, 0.5].
    qb, valid = ik.ur_analytic_ik(full, T)
    q1 = np.abs(ik._wrap_pi(qb[..., 0][valid]))
    assert np.all(q1 > 0.6)
    assert ik.solve_ik(full, T).success.all()
    res = ik.solve_ik(tight, T)
    assert not res.success.any()
    assert list(res.reason) == ["joint_limits", "joint_limits"]
    assert np.all(tight.within_limits(res.q))
    assert np.all(res.error > 1e-3)


def test_unreachable_targets_are_failures_not_wrong_joints():
    m = get_robot("ur5")
    rng = np.random.default_rng(10)
    direction = rng.normal(size=(5, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    T_far = make_transform(np.broadcast_to(np.eye(3), (5, 3, 3)), 3.0 * direction)
    res = ik.solve_ik(m, T_far)
    assert not res.success.any()
    assert set(res.reason) == {"unreachable"}
    assert np.all(res.error > 1.0)
    # Beyond the UR5's reach but inside the crude reach bound: the closed form knows, no LM attempt.
    T_edge = make_transform(np.eye(3), [1.0, 0.0, 0.1])
    res = ik.solve_ik(m, T_edge)
    assert not res.success[0] and res.reason[0] == "unreachable" and res.attempts[0] == 0
    assert res.error[0] > 0.05
    # Slightly beyond (1.6 mm, within REACH_SLACK): tried from every seed, then reported as a failure.
    T_stretched = forward_kinematics(m, [0.0, -0.3, 0.0, -1.0, 1.2, 0.0])
    T_stretched[0, :3, 3] *= 1.002
    res = ik.solve_ik(m, T_stretched, options=ik.IKOptions(restarts=2))
    assert not res.success[0] and res.attempts[0] >= 3 and res.error[0] > 1e-3
    assert res.reason[0] in ("singular", "max_iter")
    # Position mode: 3 m away.
    res = ik.solve_ik(get_robot("irb2600"), 3.0 * direction, mode="position")
    assert not res.success.any() and set(res.reason) == {"unreachable"}


def test_iteration_budget_exhausted_is_reported():
    m = get_robot("irb2600")
    q_true = random_joints(m, 50, seed=11)
    T = forward_kinematics(m, q_true)
    res = ik.solve_ik(m, T, options=ik.IKOptions(max_iter=2, restarts=0))
    pos, rot = pose_errors(m, res.q, T)
    assert_honest(res, pos, rot)
    assert (~res.success).sum() > 10
    assert np.all(res.iterations <= 2)


def test_mixed_batch_keeps_targets_apart():
    m = get_robot("ur10")
    q_true = random_joints(m, 4, seed=12)
    T = forward_kinematics(m, q_true)
    T[2, :3, 3] = [4.0, 0.0, 0.0]
    res = ik.solve_ik(m, T)
    np.testing.assert_array_equal(res.success, [True, True, False, True])
    assert res.reason[2] == "unreachable"


# ------------------------------------------------------------------------------------ input validation


def test_bad_inputs_raise_clear_errors():
    m = get_robot("ur10")
    T = forward_kinematics(m, np.zeros((2, 6)))
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        ik.solve_ik(m, np.zeros((2, 3, 3)))
    bad = T.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ik.solve_ik(m, bad)
    skewed = T.copy()
    skewed[0, :3, :3] *= 1.1
    with pytest.raises(ValueError, match="rotation"):
        ik.solve_ik(m, skewed)
    last_row = T.copy()
    last_row[0, 3, 0] = 0.5
    with pytest.raises(ValueError, match="last row"):
        ik.solve_ik(m, last_row)
    with pytest.raises(ValueError, match="positive"):
        ik.solve_ik(m, T, options=ik.IKOptions(tol_position=0.0))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        ik.solve_ik(m, np.zeros((2, 4)), mode="position")
    with pytest.raises(ValueError, match="NaN"):
        ik.solve_ik(m, np.array([[0.1, np.nan, 0.2]]), mode="position")
    with pytest.raises(ValueError, match="mode"):
        ik.solve_ik(m, T, mode="orientation")
    with pytest.raises(ValueError, match="q_seed"):
        ik.solve_ik(m, T, q_seed=np.zeros((3, 6)))
    with pytest.raises(ValueError, match="q_near"):
        ik.solve_ik(m, T, q_near=np.zeros(5))
    with pytest.raises(ValueError, match="either"):
        ik.solve_ik(m, T, T_flange_tool=np.eye(4), p_flange_tool=np.zeros(3))
    with pytest.raises(ValueError, match="p_flange_tool"):
        ik.solve_ik(m, T[:, :3, 3], mode="position", p_flange_tool=np.zeros(2))


def test_single_target_and_empty_batch():
    m = get_robot("ur5e")
    q = np.array([0.3, -1.2, 1.1, -1.4, -1.6, 0.2])
    res = ik.solve_ik(m, forward_kinematics(m, q)[0])
    assert res.q.shape == (1, 6) and res.success[0]
    np.testing.assert_allclose(res.q[0], q, atol=1e-8)  # default home picks the same elbow-up branch
    empty = ik.solve_ik(m, np.zeros((0, 4, 4)))
    assert empty.q.shape == (0, 6) and empty.success.shape == (0,)


def test_project_to_limits_wraps_before_clamping():
    m = get_robot("ur10")  # +-2 pi on every joint
    q = np.array([[6.5, -6.5, 7.0, 0.1, -7.0, 14.0]])
    out = ik.project_to_limits(m, q)
    np.testing.assert_allclose(
        out[0, :5], [6.5 - 2 * np.pi, -6.5 + 2 * np.pi, 7.0 - 2 * np.pi, 0.1, -7.0 + 2 * np.pi]
    )
    assert out[0, 5] == pytest.approx(2 * np.pi)  # 14 - 2 pi is still outside: clamped
    np.testing.assert_allclose(
        forward_kinematics(m, np.r_[out[0, :5], 0.0]),
        forward_kinematics(m, np.r_[q[0, :5], 0.0]),
        atol=1e-12,
    )


def test_ur_seed_is_the_exact_branch_nearest_the_reference():
    m = get_robot("ur5")
    q_true = np.array([[0.4, -1.0, 1.2, -1.7, -1.5, 0.3]])
    T = forward_kinematics(m, q_true)
    np.testing.assert_allclose(ik.ur_seed(m, T, q_near=q_true[0] + 0.2), q_true, atol=1e-9)
    qb, valid = ik.ur_analytic_ik(m, T)
    other = qb[0, np.argmax(np.where(valid[0], np.linalg.norm(qb[0] - q_true, axis=1), -np.inf))]
    seed = ik.ur_seed(m, T, q_near=other)
    assert np.linalg.norm(seed - q_true) > 0.5
    assert pose_errors(m, seed, T)[0][0] < 1e-9


@pytest.mark.parametrize("name", UR_NAMES)
def test_wrist_reach_test_never_rejects_reachable_poses(name):
    m = get_robot(name)
    real = m.with_errors({"a2": 3e-3, "a3": -3e-3, "beta2": 3e-3, "alpha5": 3e-3})
    T = forward_kinematics(real, random_joints(real, 3000, seed=13))
    assert not ik.ur_wrist_out_of_reach(m, T).any()
    T_far = T[:100].copy()
    T_far[:, :3, 3] *= 2.5 / np.linalg.norm(T_far[:, :3, 3], axis=1, keepdims=True)
    assert ik.ur_wrist_out_of_reach(m, T_far).all()
    T_axis = T[:100].copy()
    T_axis[:, :2, 3] = 0.0  # wrist centre near the base axis: closer than d4 to it
    T_axis[:, :3, 3] += m.d[5] * T_axis[:, :3, 2]
    assert ik.ur_wrist_out_of_reach(m, T_axis).all()


def test_solutions_next_to_joint_limits_are_found():
    """Joints 2 and 3 of the IRB2600 within 0.15 rad of their upper limits: steps that would cross a
    limit hold that joint there and move the others (active set), instead of stalling on the clip."""
    m = get_robot("irb2600")
    rng = np.random.default_rng(3)
    lo, hi = m.joint_limits[:, 0], m.joint_limits[:, 1]
    q_true = rng.uniform(lo, hi, size=(300, 6))
    q_true[:, 1:3] = hi[1:3] - rng.uniform(0, 0.15, (300, 2))
    p_tool = np.array([0.0, 0.0, 0.1])
    P = tool_points(m, q_true, p_tool)
    res = ik.solve_ik(m, P, mode="position", p_flange_tool=p_tool, options=ik.IKOptions(restarts=5))
    assert_honest(res, np.linalg.norm(tool_points(m, res.q, p_tool) - P, axis=1))
    assert res.success.mean() >= 0.85  # plain clipping of the step: about 0.45
    assert np.all(m.within_limits(res.q))


def test_branches_along_path_takes_each_rows_reference_where_given():
    """A path solved in one batch with per-row references (a program's qnear, a taught position) picks, row
    for row, the branch the row-by-row walk picks: nearest the reference where given, else the previous."""
    model = get_robot("ur10")
    q = random_joints(model, 40, seed=3)
    T = forward_kinematics(model, q)
    refs = np.full_like(q, np.nan)
    refs[::3] = q[::3] + 0.05  # near the generating joints: their own branch
    start = ik.default_home(model)
    batch = ik.branches_along_path(model, T, start, refs)
    prev, walked = start, []
    for k in range(len(q)):
        ref = refs[k] if np.all(np.isfinite(refs[k])) else prev
        prev = ik.branches_along_path(model, T[k : k + 1], ref)[0]
        walked.append(prev)
    np.testing.assert_array_equal(batch, np.array(walked))
    np.testing.assert_allclose(batch[::3], q[::3], atol=1e-9)
    assert not np.allclose(ik.branches_along_path(model, T, start)[::3], q[::3], atol=1e-6)


def test_newton_first_off_gives_the_same_answers_where_the_callers_newton_failed():
    """newton_first=False skips solve_ik's Newton steps from q_seed; a caller whose own Newton from the same
    seed to a looser tolerance failed loses nothing: LM then starts from the same place. Seeds 0.6 rad off
    leave many of them unconverged after 16 steps; those rows' answers are the same either way."""
    model = get_robot("ur10")
    q = random_joints(model, 60, seed=41)
    T = forward_kinematics(model, q)
    seed = q + np.random.default_rng(42).normal(0.0, 0.6, q.shape)
    loose = ik.NewtonOptions(max_steps=16, tol_position=1e-8, tol_rotation=1e-7)
    failed = ~ik.newton_ik(model, T, seed, options=loose).converged
    assert 5 <= failed.sum() < len(q)
    options = ik.IKOptions(restarts=0, use_analytic=False)
    on = ik.solve_ik(model, T[failed], q_seed=seed[failed], options=options)
    off = ik.solve_ik(model, T[failed], q_seed=seed[failed], options=replace(options, newton_first=False))
    np.testing.assert_array_equal(off.q, on.q)
    np.testing.assert_array_equal(off.reason, on.reason)
    assert on.success.any()  # LM solves some of them: the comparison is not only between failures
