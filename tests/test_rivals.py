"""An added effect refitted against its rivals (hil.analysis.diagnosis.rivals) and effects tested as a group: the wrong
joint is replaced when the data says so, and left as an open question when it cannot."""

from __future__ import annotations

import numpy as np
import pytest
from calib_data import ur10_joints

from hil.analysis.calibration.solve import Problem, calibrate, identify
from hil.analysis.diagnosis.rivals import compare_with_rivals, rivals_in_round
from hil.analysis.diagnosis.screening import Candidate, Screen
from hil.data.dataset import joints_rad, make_dataset
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import CalibratedModel, initial_model
from hil.model.effects import EffectContext, make_effect

GRAVITY_2, GRAVITY_3 = ("gravity_compliance", 2), ("gravity_compliance", 3)


def _campaign(n: int, noise_m: float, sag: dict[tuple[str, int], float], seed: int = 0):
    """A UR10 (nominal geometry, tracker 2 m away) whose only error is joint compliance under gravity on the
    joints in `sag` (coefficients in rad per N m), measured at n random poses."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    q = ur10_joints(rng, n)
    T = make_transform(np.eye(3), [2.0, 0.3, -0.2])
    tool = np.array([0.0, 0.0, 0.1])
    ctx = EffectContext(q, p_flange_tool=np.tile(tool, (n, 1)))
    effects = []
    for key, k in sag.items():
        eff = make_effect(*key)
        assert eff.prepare(ctx, nominal)
        eff.params = np.full(len(eff.params), k)
        effects.append(eff)
    truth = CalibratedModel("ur10", nominal, nominal, T, {1: tool}, effects)
    p = truth.predict_ctx(ctx) + rng.normal(0, noise_m, (n, 3))
    return make_dataset(q, p, smr=1)


def _fitted_with(df, key):
    model = initial_model("ur10", df)
    eff = make_effect(*key)
    ctx = EffectContext.from_frame(df, joints_rad(df))
    assert eff.prepare(ctx, model.nominal)
    result = calibrate(df, model.with_effect(eff), "ridge")
    prob = Problem.from_frame(result.model, df)
    return result.model, prob, ctx


def _compare(df, chosen, rival):
    model, prob, ctx = _fitted_with(df, chosen)
    partitions = [prob.spatial_folds(5, r) for r in range(2)]
    sigma2 = float(np.var(prob.residuals(model)))
    tests, models = compare_with_rivals(model, 0, [rival], prob, ctx, partitions, sigma2, 1e-3)
    assert len(tests) == 1
    return tests[0], models


def test_the_wrong_joint_is_replaced_when_the_data_separates_them():
    df = _campaign(300, 15e-6, {GRAVITY_2: 2e-5})
    test, models = _compare(df, GRAVITY_3, GRAVITY_2)
    assert test.verdict == "replace" and test.p_rival_better < 1e-3
    assert GRAVITY_2 in models and models[GRAVITY_2].effects[-1].family == "gravity_compliance"


def test_the_right_joint_is_kept():
    df = _campaign(300, 15e-6, {GRAVITY_2: 2e-5})
    test, _ = _compare(df, GRAVITY_2, GRAVITY_3)
    assert test.verdict == "kept" and test.p_chosen_better < 0.01


def test_a_campaign_that_cannot_separate_them_leaves_the_question_open():
    df = _campaign(30, 150e-6, {GRAVITY_2: 2e-6})  # a small sag under large noise, few poses
    test, _ = _compare(df, GRAVITY_3, GRAVITY_2)
    assert test.verdict == "undecided" and test.p_chosen_better >= 0.01


def test_rivals_of_a_round_are_the_candidates_with_a_share_of_the_winners_gain():
    def cand(name, joint, gain, passed=False, note=""):
        return Candidate(
            name=name,
            joint=joint,
            n_params=2,
            cv_rms_mm=0.1,
            gain_mm2=gain,
            p_cv=0.5,
            p_chi2=0.5,
            passed=passed,
            note=note,
        )

    round_ = [
        cand("cyclic", 3, 0.007, passed=True),
        cand("cyclic", 2, 0.0028),  # did not pass, but 40 % of the winner's gain: a rival
        cand("backlash", 2, 0.001),  # 14 %: not
        cand("joint_scale", 2, 0.005, note="collinear with the geometric parameters"),
    ]
    assert rivals_in_round(round_, ("cyclic", 3)) == [("cyclic", 2)]
    assert rivals_in_round(round_, ("thermal_expansion", None)) == []


def test_two_effects_tested_together_pass_as_a_group_and_say_so():
    df = _campaign(200, 15e-6, {GRAVITY_2: 2e-5, GRAVITY_3: 2e-5})
    model = initial_model("ur10", df)
    model = calibrate(df, model, "ridge").model
    prob = Problem.from_frame(model, df)
    ctx = EffectContext.from_frame(df, joints_rad(df))
    free = identify(model, prob).keep_mask
    partitions = [prob.spatial_folds(5, 0)]
    screen = Screen(model, prob, free, partitions, (15e-6) ** 2, 1e-3, 2)
    pair = [make_effect(*key) for key in (GRAVITY_2, GRAVITY_3)]
    assert all(e.prepare(ctx, model.nominal) for e in pair)
    cand, fitted = screen.test(pair[1], pair[0])
    assert cand.passed and fitted is not None
    assert [(e.family, e.joint) for e in fitted.effects] == [GRAVITY_2, GRAVITY_3]
    assert "tested together with gravity_compliance (joint 2)" in cand.note
    assert cand.n_params == len(pair[0].params) + len(pair[1].params)


@pytest.mark.parametrize("share", [0.0, 1.0])
def test_a_group_of_one_is_the_plain_test(share):
    """`Screen.test(eff)` with nothing beside it is the single-candidate test (no note, its own errors kept)."""
    df = _campaign(120, 15e-6, {GRAVITY_2: 2e-5 * share})
    model = calibrate(df, initial_model("ur10", df), "ridge").model
    prob = Problem.from_frame(model, df)
    ctx = EffectContext.from_frame(df, joints_rad(df))
    screen = Screen(
        model, prob, identify(model, prob).keep_mask, [prob.spatial_folds(5, 0)], 2.25e-10, 1e-3, 1
    )
    eff = make_effect(*GRAVITY_2)
    assert eff.prepare(ctx, model.nominal)
    cand, _ = screen.test(eff)
    assert "together" not in cand.note and GRAVITY_2 in screen.heldout_errors
    assert cand.passed == (share > 0)
