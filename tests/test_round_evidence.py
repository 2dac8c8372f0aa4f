"""What a diagnosis judges an effect on, where an active loop's rounds put the evidence: single-joint sweeps
appended to a campaign are dealt to the folds in turn (the effects of the swept joint are not scored on arcs
nothing else samples); a round does not end on a model that a selection starting from the earlier diagnosis'
effects beats on held-out points; rows the current model rejects as outliers count for a candidate whose own
fit accepts them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from sim_campaigns import grid_joints

from fakes.campaign import simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.calibration.folds import campaign_folds, spatial_folds, sweep_runs
from hil.analysis.design.plan import propose
from hil.analysis.diagnosis.cautions import PreviousEffectsKept
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
from hil.geometry.robots import get_robot
from hil.report.text import caution_text

GRAVITY_ONLY = DiagnosisOptions(
    families=("gravity_compliance",)
)  # only the joints' gravity yield is a candidate


def _grid_and_sweep(k_sweep: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """30 scattered poses, then joint 2 swept over most of a turn from the last of them: points (N, 3), joints."""
    rng = np.random.default_rng(4)
    q_grid = rng.uniform(-1.0, 1.0, (30, 6))
    q_sweep = np.tile(q_grid[-1], (k_sweep, 1))
    q_sweep[:, 1] = np.linspace(-2.5, 2.5, k_sweep)
    q = np.vstack([q_grid, q_sweep])
    points = np.column_stack([np.cos(q[:, 0]) * (1 + np.cos(q[:, 1])), np.sin(q[:, 0]), np.sin(q[:, 1])])
    return points, q, np.arange(len(q))


def test_sweep_runs_finds_chains_where_one_joint_moves():
    _, q, _ = _grid_and_sweep()
    run = sweep_runs(q, min_poses=5)
    assert np.all(run[30:] == 0) and np.all(
        run[:29] == -1
    )  # the sweep's first pose follows the last grid pose
    assert run[29] == 0  # ... which only joint 2 separates from it: part of the chain
    assert np.all(sweep_runs(q[:30], min_poses=5) == -1)
    assert np.all(sweep_runs(q, min_poses=20) == -1)  # too short a chain is no sweep


def test_a_sweep_is_dealt_to_the_folds_in_turn_and_the_grid_stays_in_blocks():
    points, q, pose = _grid_and_sweep()
    folds = campaign_folds(points, pose, q, 5, seed=0)
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(q)))
    fold_of = np.empty(len(q), int)
    for f, rows in enumerate(folds):
        fold_of[rows] = f
    swept = np.flatnonzero(sweep_runs(q, 5) >= 0)
    assert np.all(np.diff(fold_of[swept]) % 5 == 1)  # consecutive sweep poses: the next fold each time
    blocks = spatial_folds(points[:29], 5, 0)  # the other poses: blocks of the volume, as before
    assert [len(set(fold_of[b])) for b in blocks] == [1] * len(blocks)
    assert len({int(fold_of[b[0]]) for b in blocks}) == len(blocks)


def test_rows_of_one_pose_share_a_fold_in_a_sweep():
    points, q, pose = _grid_and_sweep()
    twice = np.repeat(np.arange(len(q)), 2)  # two SMRs read at every pose
    folds = campaign_folds(
        points[twice] + 1e-4 * (np.arange(len(twice)) % 2)[:, None], pose[twice], q[twice], 5, 0
    )
    for rows in folds:
        assert all(np.sum(twice[rows] == p) == 2 for p in np.unique(twice[rows]))


@pytest.fixture(scope="module")
def two_on_joint2():
    """Backlash and a cyclic error on joint 2 beside gravity sag (seed 0 of benchmarks/active_loop.py): the
    grid's diagnosis names the cyclic error; the plan sweeps joint 2 (among others) over most of a turn."""
    cell = SimulatedCell(
        SimCellConfig(
            robot="ur10", seed=0, cyclic=True, cyclic_joints=(2,), backlash=True, backlash_joints=(2,)
        )
    )
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=0, keep_singular=False))
    first = run_diagnosis(train, "ur10")
    sigma = float(np.sqrt(np.mean(first.noise.sigma_axis_m**2)))
    plan = propose(train, first.model, first.undecided, 100, sigma, seed=0)
    longer = pd.concat([train, simulate_campaign(cell, plan.q)], ignore_index=True)
    return first, plan, longer


@pytest.fixture(scope="module")
def longer_diagnosed(two_on_joint2):
    """The longer campaign diagnosed afresh, as a loop round without the earlier effects would (shared by the
    tests that compare a round with it)."""
    return run_diagnosis(two_on_joint2[2], "ur10")


TRUE_JOINT2 = {("cyclic", 2), ("backlash", 2), ("gravity_compliance", 2)}


def _named(report) -> set:
    return {(e["name"], e["joint"]) for e in report.effects_added}


def test_true_effects_stay_named_after_single_joint_sweeps(two_on_joint2, longer_diagnosed):
    first, plan, longer = two_on_joint2
    # on the grid alone joint 2's errors are not told apart: beside its gravity yield (physics from the UR10's
    # link masses) neither the cyclic error nor the backlash is named, and its scale is an open question
    assert not _named(first) >= TRUE_JOINT2
    assert any(getattr(q, "effect", None) == {"name": "joint_scale", "joint": 2} for q in first.undecided)
    assert "sweep_j2" in plan.purpose
    # sweeps held out as arcs scored every effect as a loss: nothing at all was named on the longer campaign
    assert _named(longer_diagnosed) >= {("backlash", 2), ("gravity_compliance", 2)}
    # as a round of the loop: the earlier effects are kept when dropping them predicts held-out points worse
    loop = run_diagnosis(longer, "ur10", previous_effects=first.effects_added)
    assert _named(loop) >= TRUE_JOINT2


def test_a_round_keeps_the_earlier_effects_a_selection_without_them_predicts_worse(two_on_joint2):
    """A selection that cannot re-admit the earlier effects (only gravity sag is offered here) does not end the
    round on the worse model: the selection that starts from them predicts held-out points better."""
    _, _, longer = two_on_joint2
    earlier = [{"name": n, "joint": j} for n, j in sorted(TRUE_JOINT2)]
    alone = run_diagnosis(longer, "ur10", options=GRAVITY_ONLY)
    assert not _named(alone) >= TRUE_JOINT2
    kept = run_diagnosis(longer, "ur10", options=GRAVITY_ONLY, previous_effects=earlier)
    assert _named(kept) >= TRUE_JOINT2
    said = [c for c in kept.verdict["cautions"] if isinstance(c, PreviousEffectsKept)]
    assert len(said) == 1 and said[0].heldout_rms_kept_mm < said[0].heldout_rms_mm
    assert "it was kept" in caution_text(said[0])
    assert kept.stages[-1]["rms_mm"] < alone.stages[-1]["rms_mm"]


def test_an_earlier_effect_that_does_not_predict_better_is_not_kept(two_on_joint2, longer_diagnosed):
    _, _, longer = two_on_joint2
    fresh = longer_diagnosed
    spurious = {"name": "joint_scale", "joint": 5}
    again = run_diagnosis(longer, "ur10", previous_effects=[*fresh.effects_added, spurious])
    assert _named(again) == _named(fresh)
    assert not [c for c in again.verdict["cautions"] if isinstance(c, PreviousEffectsKept)]


def test_rows_the_current_model_rejects_count_for_the_effect_that_explains_them():
    """Gravity sag and a once-per-turn error of joint 1 (seed 0 of the benchmark's gravity_cyclic1): the model
    with gravity alone rejects the grid's rows where joint 1's error shows most; judged on its inliers only,
    the cyclic term lost its held-out test (p 0.014), and the loop ended at 1.71x the true model's
    validation error. Judged on the rows either model accepts, it is named in the first diagnosis.
    The robot file without its link masses: the gravity yield is then a candidate, and this grid's model with
    it alone rejects those rows (with the masses the yield is physics from the start and the cyclic term
    misses its held-out test by a hair, p 0.001; the loop's next round names it)."""
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=0, cyclic=True, cyclic_joints=(1,)))
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=0, keep_singular=False))
    report = run_diagnosis(train, replace(get_robot("ur10"), link_masses_kg=None))
    assert {("cyclic", 1), ("gravity_compliance", 2)} <= _named(report)
    step = next(s for s in report.steps if s.effect == {"name": "cyclic", "joint": 1})
    judged = next(c for c in step.candidates if (c.name, c.joint) == ("cyclic", 1))
    assert judged.rows_reclaimed > 0 and judged.passed


def test_an_effect_whose_rows_the_model_rejects_is_judged_though_the_inliers_hide_it():
    """Two errors of joint 2 (seed 3 of the benchmark's two_on_joint2): after the first round's sweeps the
    model without the once-per-turn term rejects the joint-2 sweep rows that show it, and on its inliers the
    full-fit test does not find it (p 0.04 .. 0.5), so it was never judged on the rows its own fit accepts
    and the loop never named it. Its linearised fit on every row takes those rows back: it is re-judged on
    them, and named."""
    cell = SimulatedCell(
        SimCellConfig(
            robot="ur10", seed=3, cyclic=True, cyclic_joints=(2,), backlash=True, backlash_joints=(2,)
        )
    )
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=3, keep_singular=False))
    first = run_diagnosis(train, "ur10")
    assert ("cyclic", 2) not in _named(first)
    sigma = float(np.sqrt(np.mean(first.noise.sigma_axis_m**2)))
    plan = propose(train, first.model, first.undecided, 100, sigma, seed=3)
    assert "sweep_j2" in plan.purpose
    longer = pd.concat([train, simulate_campaign(cell, plan.q)], ignore_index=True)
    again = run_diagnosis(longer, "ur10", previous_effects=first.effects_added)
    assert ("cyclic", 2) in _named(again)
    step = next(s for s in again.steps if s.effect == {"name": "cyclic", "joint": 2})
    judged = next(c for c in step.candidates if (c.name, c.joint) == ("cyclic", 2))
    assert judged.rows_reclaimed > 0 and judged.passed
