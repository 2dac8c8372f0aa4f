"""Foundation kinematics: FK of hand-checked poses, DH vs beta models, Jacobians vs finite differences,
SE(3) helpers and parameter bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hil.geometry import se3
from hil.geometry.kinematics import (
    BASE_PARAM_NAMES,
    TOOL_PARAM_NAMES,
    chain_axes,
    flange_poses_and_last_origins,
    forward_kinematics,
    geometric_jacobian,
    identification_jacobian,
    link_frames,
    measured_point,
    perturb_base,
    pose_and_jacobian,
    tool_points,
)
from hil.geometry.robots import ROBOT_NAMES, get_robot

UR_NAMES = ("ur5", "ur10", "ur5e", "ur10e")


def random_joints(model, n, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
    return rng.uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi), size=(n, model.n_joints))


# ------------------------------------------------------------------------------------------ FK


def test_ur10_flange_at_zero_joints():
    T = forward_kinematics(get_robot("ur10"), np.zeros(6))[0]
    # q = 0: arm stretched along -x; y = -(d4 + d6), z = d1 - d5; tool z axis along -y.
    np.testing.assert_allclose(T[:3, 3], [-1.1843, -0.256141, 0.0116], atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("name", UR_NAMES)
def test_ur_upright_pose_by_hand(name):
    """q = (0, -pi/2, 0, -pi/2, 0, 0): upper and fore arm point straight up (worked through the DH
    chain by hand): flange at (0, -(d4 + d6), d1 - a2 - a3 + d5), x6 = -x0, y6 = -z0, z6 = -y0."""
    m = get_robot(name)
    d1, a2, a3, d4, d5, d6 = m.d[0], m.a[1], m.a[2], m.d[3], m.d[4], m.d[5]
    T = forward_kinematics(m, [0, -np.pi / 2, 0, -np.pi / 2, 0, 0])[0]
    np.testing.assert_allclose(T[:3, 3], [0.0, -(d4 + d6), d1 - a2 - a3 + d5], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[-1, 0, 0], [0, 0, -1], [0, -1, 0]], atol=1e-12)


def test_first_joint_rotates_whole_arm_about_base_z():
    m = get_robot("ur10")
    T0 = forward_kinematics(m, np.zeros(6))[0]
    T1 = forward_kinematics(m, [np.pi / 2, 0, 0, 0, 0, 0])[0]
    np.testing.assert_allclose(T1[:3, 3], [0.256141, -1.1843, 0.0116], atol=1e-9)
    np.testing.assert_allclose(T1[:3, :3], se3.rot_z(np.pi / 2) @ T0[:3, :3], atol=1e-12)


def test_fk_is_batched_and_rigid():
    m = get_robot("irb2600")
    q = random_joints(m, 50)
    T = forward_kinematics(m, q)
    assert T.shape == (50, 4, 4)
    np.testing.assert_allclose(T[7], forward_kinematics(m, q[7])[0])
    R = T[:, :3, :3]
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_irb2600_zero_pose_by_hand():
    """q = 0: with the theta offsets (0, -90, 0, 0, 180, 0) deg the arm is upright, the forearm points
    forward, and the flange is at x = a1 + d4 + d6, z = d1 + a2 + a3 (the wrist flips z6 to +x)."""
    T = forward_kinematics(get_robot("irb2600"), np.zeros(6))[0]
    np.testing.assert_allclose(T[:3, 3], [0.150 + 0.795 + 0.085, 0.0, 0.445 + 0.700 + 0.115], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_bad_joint_shapes_are_rejected():
    m = get_robot("ur5")
    with pytest.raises(ValueError, match="joints must be"):
        forward_kinematics(m, np.zeros((3, 5)))
    with pytest.raises(ValueError, match="NaN"):
        forward_kinematics(m, [0, 0, np.nan, 0, 0, 0])


# ------------------------------------------------------------------------------------------ DH vs beta


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_dh_and_beta_models_agree_when_beta_is_zero(name):
    dh, mdh = get_robot(name, use_beta=False), get_robot(name, use_beta=True)
    assert dh.param_names != mdh.param_names
    assert any(n.startswith("beta") for n in mdh.param_names)
    assert not any(n.startswith("beta") for n in dh.param_names)
    q = random_joints(dh, 200)
    np.testing.assert_allclose(forward_kinematics(dh, q), forward_kinematics(mdh, q), atol=1e-14)


def test_beta_changes_the_pose():
    m = get_robot("ur10")
    q = random_joints(m, 20)
    moved = tool_points(m.with_errors({"beta2": 1e-3}), q, np.zeros(3)) - tool_points(m, q, np.zeros(3))
    # A 1 mrad tilt of joint 3's axis moves the flange by about 1e-3 * (distance from it) > 0.1 mm.
    assert np.all(np.linalg.norm(moved, axis=1) > 1e-5)


# ------------------------------------------------------------------------------------------ Jacobians


@pytest.mark.parametrize("name", ["ur10", "irb2600"])
@pytest.mark.parametrize("use_beta", [True, False])
def test_identification_jacobian_matches_central_differences(name, use_beta):
    m = get_robot(name, use_beta=use_beta).with_errors({"a2": 1e-3, "alpha4": 2e-3})
    rng = np.random.default_rng(3)
    q = random_joints(m, 6, seed=4)
    T_tracker_base = se3.make_transform(
        Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), [2.0, -1.0, 0.5]
    )
    p_tool = np.array([0.02, -0.03, 0.12])
    p, J = identification_jacobian(m, q, T_tracker_base, p_tool)
    n_kin = len(m.param_names)
    assert J.shape == (6, 3, n_kin + len(BASE_PARAM_NAMES) + len(TOOL_PARAM_NAMES))
    np.testing.assert_allclose(p, measured_point(m, q, T_tracker_base, p_tool), atol=1e-14)

    h = 1e-6
    fd = np.zeros_like(J)
    for k in range(n_kin):
        dv = np.zeros(n_kin)
        dv[k] = h
        plus = measured_point(m.with_params(m.params + dv), q, T_tracker_base, p_tool)
        minus = measured_point(m.with_params(m.params - dv), q, T_tracker_base, p_tool)
        fd[:, :, k] = (plus - minus) / (2 * h)
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = h
        plus = measured_point(m, q, perturb_base(T_tracker_base, delta), p_tool)
        minus = measured_point(m, q, perturb_base(T_tracker_base, -delta), p_tool)
        fd[:, :, n_kin + k] = (plus - minus) / (2 * h)
    for k in range(3):
        dt = np.zeros(3)
        dt[k] = h
        plus = measured_point(m, q, T_tracker_base, p_tool + dt)
        minus = measured_point(m, q, T_tracker_base, p_tool - dt)
        fd[:, :, n_kin + 6 + k] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(J, fd, atol=1e-8)


@pytest.mark.parametrize("name", ["ur5e", "irb2600"])
@pytest.mark.parametrize(
    "n", [5, 60]
)  # small batches take a (4, 4) matmul chain, larger ones the column loop
def test_geometric_jacobian_matches_central_differences(name, n):
    m = get_robot(name).with_errors({"beta2": 2e-3})
    q = random_joints(m, n, seed=7)
    p_tool = np.array([0.01, 0.05, 0.2])
    J = geometric_jacobian(m, q, p_tool)
    assert J.shape == (n, 6, 6)
    h = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        Tp = forward_kinematics(m, q + dq)
        Tm = forward_kinematics(m, q - dq)
        dp = (tool_points(m, q + dq, p_tool) - tool_points(m, q - dq, p_tool)) / (2 * h)
        R_rel = Tp[:, :3, :3] @ np.swapaxes(Tm[:, :3, :3], 1, 2)
        omega = Rotation.from_matrix(R_rel).as_rotvec() / (2 * h)
        np.testing.assert_allclose(J[:, :3, j], dp, atol=1e-8)
        np.testing.assert_allclose(J[:, 3:, j], omega, atol=1e-8)


def test_small_and_large_batches_give_the_same_chain():
    m = get_robot("ur10").with_errors({"beta2": 2e-3, "alpha3": 1e-3, "d4": 1e-4})
    q = random_joints(m, 60, seed=8)
    tool = np.array([0.01, 0.05, 0.2])
    T, J = pose_and_jacobian(m, q, tool)
    _, Z, O = chain_axes(m, q)
    for rows in (slice(0, 1), slice(1, 9), slice(9, 60)):
        T_r, J_r = pose_and_jacobian(m, q[rows], tool)
        _, Z_r, O_r = chain_axes(m, q[rows])
        np.testing.assert_allclose(T_r, T[rows], atol=1e-14)
        np.testing.assert_allclose(J_r, J[rows], atol=1e-14)
        np.testing.assert_allclose(Z_r, Z[:, :, rows], atol=1e-14)
        np.testing.assert_allclose(O_r, O[:, :, rows], atol=1e-14)
    frames = link_frames(m, q)  # the axes are the link frames' z columns and origins
    np.testing.assert_allclose(Z, frames[:, :-1, :3, 2].transpose(1, 2, 0), atol=1e-14)
    np.testing.assert_allclose(O, frames[:, :, :3, 3].transpose(1, 2, 0), atol=1e-14)


# ------------------------------------------------------------------------------------------ SE(3)


def test_fit_rigid_recovers_transform_and_scale():
    rng = np.random.default_rng(11)
    src = rng.normal(size=(20, 3))
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    t = np.array([0.3, -2.0, 1.1])
    T, s = se3.fit_rigid(src, src @ R.T + t)
    np.testing.assert_allclose(T, se3.make_transform(R, t), atol=1e-12)
    assert s == 1.0
    T, s = se3.fit_rigid(src, 1.0003 * src @ R.T + t, with_scale=True)
    assert s == pytest.approx(1.0003, abs=1e-12)
    np.testing.assert_allclose(T, se3.make_transform(R, t), atol=1e-12)


def test_fit_rigid_rejects_degenerate_points():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        se3.fit_rigid(line, line + 1.0)
    with pytest.raises(ValueError):
        se3.fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))


def test_fit_circle_3d_exact_through_three_points():
    rng = np.random.default_rng(5)
    centre = np.array([0.4, -0.2, 1.3])
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    radius = 0.0315
    angles = np.array([0.1, 1.7, 4.0])
    pts = centre + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    c, n, r = se3.fit_circle_3d(pts)
    np.testing.assert_allclose(c, centre, atol=1e-12)
    assert r == pytest.approx(radius, abs=1e-12)
    assert abs(n @ normal) == pytest.approx(1.0, abs=1e-12)


def test_fit_plane_normal_and_centroid():
    rng = np.random.default_rng(6)
    xy = rng.uniform(-1, 1, size=(30, 2))
    R = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    pts = np.column_stack([xy, np.zeros(30)]) @ R.T + [1.0, 2.0, 3.0]
    c, n = se3.fit_plane(pts)
    np.testing.assert_allclose(c, pts.mean(axis=0), atol=1e-12)
    assert abs(n @ R[:, 2]) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="collinear"):
        se3.fit_plane(np.outer(np.arange(4.0), [1.0, 0.0, 0.0]))


def test_pose_vector_round_trip_inverse_and_pose_error():
    rng = np.random.default_rng(8)
    poses = np.column_stack([rng.normal(size=(10, 3)), rng.uniform(-1, 1, size=(10, 3))])
    T = se3.pose_to_transform(poses)
    np.testing.assert_allclose(se3.transform_to_pose(T), poses, atol=1e-12)
    np.testing.assert_allclose(T @ se3.invert(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    step = np.array([1e-3, -2e-3, 3e-3, 1e-4, 0.0, -2e-4])
    T_moved = se3.make_transform(
        Rotation.from_rotvec(step[3:]).as_matrix() @ T[:, :3, :3], T[:, :3, 3] + step[:3]
    )
    np.testing.assert_allclose(se3.pose_error(T, T_moved), np.broadcast_to(step, (10, 6)), atol=1e-12)


@pytest.mark.parametrize("scale", [0.0, 1e-9, 5e-4, 1e-3, 2e-3, 1.0, np.pi, 20.0])
def test_rotation_exp_is_scipys_rotation_of_the_vector_and_inverts_the_log(scale):
    """The exponential the simulated cell turns every commanded pose with: scipy's matrices (to the last
    bit or two, whatever scipy's version), either side of the small-angle series' 1 mrad switch, and
    `rotation_log`'s inverse (up to the 2 pi wrap of a vector longer than pi)."""
    rv = np.random.default_rng(3).normal(size=(400, 3)) * scale
    R = se3.rotation_exp(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), rtol=0, atol=2e-15)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(se3.rotation_exp(se3.rotation_log(R)), R, atol=1e-12)
    short = np.linalg.norm(rv, axis=1) < np.pi - 1e-6  # longer vectors come back wrapped
    np.testing.assert_allclose(se3.rotation_log(R[short]), rv[short], atol=1e-12)
    assert se3.rotation_exp(rv[0]).shape == (3, 3)
    assert se3.rotation_exp(rv.reshape(20, 20, 3)).shape == (20, 20, 3, 3)


def test_a_chain_asked_again_comes_from_the_memo_and_is_never_stale():
    """A fit's Jacobian and prediction ask for the same chain one after the other: the second is served from
    `_chain`'s memo, equal to a fresh computation; joints changed in place or another geometry are computed
    anew; what leaves the module is the caller's own copy."""
    from hil.geometry.kinematics import _chain, _chain_loop, _ChainOut

    m = get_robot("ur10")
    q = random_joints(m, 100, seed=11)
    n = m.n_joints
    Z, O, X, Y = (
        np.empty((n, 3, 100)),
        np.empty((n + 1, 3, 100)),
        np.empty((n, 3, 100)),
        np.empty((n, 3, 100)),
    )
    R, p = _chain(m, q, None, (Z, O), (X, Y))
    R_again, p_again = _chain(m, q.copy(), None)
    assert R_again is R and p_again is p and not R.flags.writeable  # served, read-only
    fresh = [np.empty_like(a) for a in (Z, O, X, Y)]
    R_fresh, p_fresh = _chain_loop(m, q, _ChainOut(axes=(fresh[0], fresh[1]), mids=(fresh[2], fresh[3])))
    np.testing.assert_array_equal(R, R_fresh)
    np.testing.assert_array_equal(p, p_fresh)
    for filled, computed in zip((Z, O, X, Y), fresh, strict=True):
        np.testing.assert_array_equal(filled, computed)
    q[3, 1] += 0.2  # the same array, changed in place
    R_moved, _ = _chain(m, q, None)
    assert R_moved is not R
    np.testing.assert_array_equal(R_moved, _chain_loop(m, q, _ChainOut())[0])
    other = m.with_errors({"a2": 1e-4})
    np.testing.assert_array_equal(_chain(other, q, None)[1], _chain_loop(other, q, _ChainOut())[1])
    T, origins = flange_poses_and_last_origins(m, q)
    origins += 1.0  # the caller's own
    np.testing.assert_array_equal(flange_poses_and_last_origins(m, q)[1], _chain_loop(m, q, _ChainOut())[1])


# ------------------------------------------------------------------------------------------ parameters


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_with_params_round_trip(name):
    m = get_robot(name)
    p = m.params
    assert len(p) == len(m.param_names) == 4 * m.n_joints
    rng = np.random.default_rng(1)
    p2 = p + rng.normal(scale=1e-3, size=p.shape)
    m2 = m.with_params(p2)
    np.testing.assert_array_equal(m2.params, p2)
    np.testing.assert_array_equal(m.params, p)  # the original is untouched
    np.testing.assert_array_equal(m2.with_params(p).params, p)


def test_with_errors_adds_to_named_parameters():
    m = get_robot("ur10")
    m2 = m.with_errors({"a2": 2e-4, "beta3": -1e-4, "theta6": 1e-3})
    names = m.param_names
    diff = m2.params - m.params
    assert diff[names.index("a2")] == pytest.approx(2e-4)
    assert diff[names.index("beta3")] == pytest.approx(-1e-4)
    assert diff[names.index("theta6")] == pytest.approx(1e-3)
    assert np.count_nonzero(diff) == 3
    assert m2.a[1] == pytest.approx(m.a[1] + 2e-4)


def test_unknown_parameter_names_and_bad_lengths_are_errors():
    m = get_robot("ur10")
    with pytest.raises(KeyError, match="d2"):
        m.with_errors({"d2": 1e-4})  # d2 is replaced by beta2 on the beta model
    with pytest.raises(KeyError):
        m.with_errors({"beta1": 1e-4})
    with pytest.raises(ValueError, match="parameter values"):
        m.with_params(np.zeros(3))
    with pytest.raises(ValueError, match="unknown robot"):
        get_robot("kr6")


def test_within_limits():
    m = get_robot("irb2600")
    q = np.zeros((2, 6))
    q[1, 1] = np.deg2rad(160)  # joint 2 upper limit is 155 deg
    np.testing.assert_array_equal(m.within_limits(q), [True, False])


def test_the_growth_direction_is_the_derivative_of_the_tool_point_when_every_link_length_grows():
    """Thermal growth scales every a and d by (1 + k); the tool and the fixed flange transform stay. The tool
    point's derivative in k is then the last link's origin: checked against a central difference."""
    import dataclasses

    from hil.model.effects import growth_direction

    rng = np.random.default_rng(4)
    flange = se3.make_transform(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [0.01, -0.02, 0.03])
    model = dataclasses.replace(get_robot("ur10"), beta=np.r_[0.0, 1e-3, 0, 0, 0, 0], T_last_flange=flange)
    q = rng.uniform(-3.0, 3.0, (50, 6))
    tool = rng.normal(scale=0.1, size=(50, 3))

    def tool_points_grown(k: float) -> np.ndarray:
        grown = dataclasses.replace(model, a=np.asarray(model.a) * (1 + k), d=np.asarray(model.d) * (1 + k))
        T = forward_kinematics(grown, q)
        return np.einsum("nij,nj->ni", T[:, :3, :3], tool) + T[:, :3, 3]

    h = 1e-4  # the tool point is linear in k: the central difference is exact but for rounding
    numeric = (tool_points_grown(h) - tool_points_grown(-h)) / (2 * h)
    np.testing.assert_allclose(growth_direction(model, q), numeric, atol=1e-10)
