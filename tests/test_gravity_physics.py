"""Gravity yield as physics: with the links' masses in the robot file, each joint that carries the arm's weight
has one compliance whose regressor is the gravity torque from those masses, always in the model with a prior
(hil.model.effects.gravity_physics). A scale of a joint must also predict along that joint
(hil.analysis.diagnosis.screening.predicts_along_joint). The simulator's physics is read only to check the torque."""

from dataclasses import replace

import numpy as np
import pytest
from calib_data import ur10_joints
from scipy.spatial.transform import Rotation

from hil.analysis.calibration.solve import Problem, calibrate, identify
from hil.analysis.diagnosis.screening import predicts_along_joint
from hil.data.dataset import make_dataset
from hil.geometry.kinematics import measured_point
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform
from hil.model.effects import (
    GRAVITY_PRIOR_DEFLECTION_RAD,
    EffectContext,
    GravityCompliance,
    candidate_effects,
    effect_from_dict,
    gravity_physics,
    hold_rigid,
    make_effect,
    physical,
    stretched_torque_nm,
    yields_against_gravity,
)

pytestmark = pytest.mark.timeout(120)


def test_torque_from_the_masses_is_the_simulators_torque():
    # Written independently of fakes.physics; both lump each link's mass at the middle of its span.
    from fakes.physics import GRAVITY_BASE, chain_frames, gravity_torques

    robot = get_robot("ur10")
    rng = np.random.default_rng(3)
    q = rng.uniform(-np.pi, np.pi, (40, 6))
    payload = np.array([0.02, -0.01, 0.12])
    ctx = EffectContext(q, payload_kg=np.full(40, 2.5), p_flange_tool=np.tile(payload, (40, 1)))
    frames = chain_frames(q, robot.theta, robot.d, robot.a, robot.alpha, robot.beta)
    truth = gravity_torques(frames, np.array(robot.link_masses_kg), 2.5, payload)
    g_ratio = 9.80665 / -GRAVITY_BASE[2]
    for j in range(2, 7):
        eff = GravityCompliance(joint=j)
        assert eff.prepare(ctx, robot)
        np.testing.assert_allclose(eff.torque(ctx, robot), truth[:, j - 1] * g_ratio, atol=1e-9)
    assert not GravityCompliance(joint=1).prepare(ctx, robot)  # a vertical axis carries no torque


def test_the_joints_that_carry_the_arm_are_physics_with_their_prior():
    robot = get_robot("ur10")
    ctx = EffectContext(
        ur10_joints(np.random.default_rng(0), 60), p_flange_tool=np.tile([0, 0, 0.1], (60, 1))
    )
    terms = gravity_physics(ctx, robot)
    assert [e.joint for e in terms] == [2, 3]  # the wrist carries under 10 % of joint 2's torque
    for e in terms:
        assert physical(e) and e.coefficient_names() == ["compliance"] and e.coefficient_unit() == "rad/(N m)"
        mean, std = e.prior()
        assert mean[0] == 0.0
        assert std[0] == pytest.approx(
            GRAVITY_PRIOR_DEFLECTION_RAD / stretched_torque_nm(robot, e.joint_index)
        )
        again = effect_from_dict(e.to_dict())  # a saved model keeps the torque form and its prior
        np.testing.assert_allclose(again.regressors(ctx, robot), e.regressors(ctx, robot))
        assert physical(again) and again.prior()[1][0] == std[0]
    # 12.7 kg at 0.306 m, 4.27 kg at 0.898 m, ... held out straight: joint 2's bound is about 134 N m
    assert stretched_torque_nm(robot, 1) == pytest.approx(133.5, abs=0.5)
    # The wrist's yield stays a candidate (the same torque form); joints 2 and 3 are not offered again.
    offered = {(e.family, e.joint) for e in candidate_effects(ctx, robot, terms, ("gravity_compliance",))}
    assert offered == {("gravity_compliance", 4), ("gravity_compliance", 5)}
    # Without masses: no physics, and the free form (lever arms) is a candidate on every loaded joint.
    bare = replace(robot, link_masses_kg=None)
    assert gravity_physics(ctx, bare) == []
    free = candidate_effects(ctx, bare, [], ("gravity_compliance",))
    assert {e.joint for e in free} >= {2, 3} and all(e.coefficient_unit() == "rad/m" for e in free)


def test_a_heavy_wrist_carries_its_share_against_the_loaded_joints_not_the_base():
    """The share is of the most loaded joint gravity acts on: a vertical base axis carries no gravity torque
    however far its links reach (an IRB 2600 given its masses: joint 4 carries 16 % of joint 2's, 8 % of the
    base's stretched bound)."""
    robot = replace(get_robot("irb2600"), link_masses_kg=(90.0, 45.0, 35.0, 15.0, 6.0, 1.0))
    rng = np.random.default_rng(0)
    limits = np.asarray(robot.joint_limits)
    q = rng.uniform(
        limits.mean(axis=1) - 0.3 * np.ptp(limits, axis=1),
        limits.mean(axis=1) + 0.3 * np.ptp(limits, axis=1),
        (60, 6),
    )
    ctx = EffectContext(q, p_flange_tool=np.tile([0, 0, 0.1], (60, 1)))
    # the base's stretched bound is no torque: against it the wrist would fall under the share
    assert stretched_torque_nm(robot, 3) < 0.1 * stretched_torque_nm(robot, 0)
    assert [e.joint for e in gravity_physics(ctx, robot)] == [2, 3, 4]


def test_a_negative_compliance_is_held_rigid():
    robot = get_robot("ur10")
    ctx = EffectContext(
        ur10_joints(np.random.default_rng(1), 30), p_flange_tool=np.tile([0, 0, 0.1], (30, 1))
    )
    eff = gravity_physics(ctx, robot)[0]
    eff.params = np.array([-2e-6])
    assert yields_against_gravity(eff) and eff.implausible(ctx, robot).startswith("implausible sign")
    held = hold_rigid(eff, -2e-6)
    assert held.held and held.params[0] == 0.0 and not yields_against_gravity(held)
    eff.params = np.array([1e-5])
    assert not yields_against_gravity(eff) and eff.summary(ctx, robot)["stiffness_knm_per_rad"] == 100.0


def _synthetic(offset, n=250, seed=4):
    """A UR10 (random geometric errors, no gravity) whose joints turn by `offset(q)` (rad) more than read."""
    rng = np.random.default_rng(seed)
    nominal = replace(get_robot("ur10"), link_masses_kg=None)
    true = nominal.with_errors(
        {n: rng.normal(0, 3e-4 if n[0] in "ad" else 5e-4) for n in nominal.param_names}
    )
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    q = ur10_joints(rng, n)
    p = measured_point(true, q + offset(q), T, np.array([0.03, -0.02, 0.11]))
    p += rng.normal(0, 1, p.shape) * (15e-6 + 6e-6 * np.linalg.norm(p, axis=1, keepdims=True)) / 2
    return nominal, make_dataset(q, p)


def _along_joint(offset, joint):
    robot, df = _synthetic(offset)
    fit = calibrate(df, robot, "ridge")
    prob = Problem.from_frame(fit.model, df, orientation=False)
    eff = make_effect("joint_scale", joint)
    assert eff.prepare(prob.ctx, fit.model.nominal)
    return predicts_along_joint(fit.model, prob, identify(fit.model, prob).keep_mask, eff, 4e-10, 1e-3)


def test_a_scale_must_predict_one_half_of_its_joint_from_the_other():
    def scale(q):
        out = np.zeros_like(q)
        out[:, 0] = 5e-4 * q[:, 0]  # joint 1 turns 500 ppm more than read: linear along the whole joint
        return out

    def bend(q):
        out = np.zeros_like(q)
        out[:, 0] = 8e-4 * q[:, 0] ** 2  # curvature: a slope of either sign on either half of the range
        return out

    assert _along_joint(scale, 1) is None
    why = _along_joint(bend, 1)
    assert why is not None and why.startswith("does not extrapolate along joint 1")


def test_the_simulated_cells_masses_are_not_the_files():
    # The cell's truth differs from the published masses the diagnosis is given, per seed and reproducibly.
    from fakes.cell import LINK_MASSES_KG, SimCellConfig, SimulatedCell

    table = np.array(LINK_MASSES_KG["ur10"])
    cells = [SimulatedCell(SimCellConfig(robot="ur10", seed=s)) for s in (0, 0, 1)]
    assert np.array_equal(cells[0]._masses, cells[1]._masses)
    assert not np.allclose(cells[0]._masses, cells[2]._masses)
    for cell in cells:
        ratio = cell._masses / table
        assert np.all(np.abs(ratio - 1) <= 0.3 + 1e-12) and np.std(ratio) > 0.02
