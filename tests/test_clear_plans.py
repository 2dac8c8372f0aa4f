"""Plans that keep clear by default: the planners choose clear configurations and a clear order on the default
simulated cell, and what cannot be reached safely is left out and said so."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hil.geometry.collision import clear_range_rad
from hil.geometry.ik import ur_branch_index
from hil.runner.cell_config import parse_cell_config
from hil.runner.clear_joints import NO_CLEAR, ORDER_CANDIDATES, clear_travel_order, plan_clear_joints
from hil.runner.envelope import EnvelopeError
from hil.runner.plan import NO_SAFE_PATH, Plan, PlannedPose
from hil.runner.planners import facing_poses, plan_joints, workspace_box
from procedures import grid_sampling, iso9283, registration
from tests.cell_fixtures import sim_cell_toml


@pytest.fixture(scope="module")
def config():
    return parse_cell_config(tomllib.loads(sim_cell_toml()))


def _colliding_moves(config, q: np.ndarray) -> list[str]:
    q_from = np.vstack([config.q_home_rad, q[:-1]])
    return [p for p in config.envelope.path_problems(config.nominal, q_from, q) if p]


def test_collisions_are_checked_unless_the_cell_config_turns_them_off(config):
    assert config.envelope.bodies is not None
    data = tomllib.loads(sim_cell_toml())
    data["envelope"]["collisions"] = False
    assert parse_cell_config(data).envelope.bodies is None


def test_the_grid_iso_and_registration_plans_keep_clear_on_every_move_from_home(config):
    grid = grid_sampling.PROCEDURE.make_plan(config)
    assert len(grid.poses) >= 350  # the 100 mm grid and its 50 validation poses, a few left out
    for plan in (grid, iso9283.PROCEDURE.make_plan(config), registration.PROCEDURE.make_plan(config)):
        assert _colliding_moves(config, plan.joints()) == [], plan.procedure
        assert plan.path_check() == (0, [])
        slack = config.bodies.pair_slack_m(config.nominal, plan.joints())
        assert slack.min() >= 0.0


def test_the_nominal_ik_folds_the_elbow_where_the_clear_choice_does_not(config):
    """The ISO cube's P1 (facing the tracker at the sampled volume's centre): nearest home, the nominal IK
    turns the elbow to where reaching it from home passes the fold; the clear choice keeps home's shoulder
    and elbow, inside the elbow's clear range, and keeps every margin."""
    centre = workspace_box(config.nominal, config.p_base_tracker_m).centre_m
    T = facing_poses(
        centre[None], config.p_base_tracker_m, np.random.default_rng(0), tilt_deg=0.0, roll_deg=0.0
    )
    p_nest = config.nests_flange_m[0]
    nominal = plan_joints(config.nominal, T, p_nest, q_near=config.q_home_rad)
    lo, hi = clear_range_rad(config.bodies, config.nominal, config.q_home_rad, 2)
    assert nominal.usable[0] and not lo <= nominal.q[0, 2] <= hi  # the fold the planner must avoid
    clear = plan_clear_joints(
        config.nominal, config.envelope, T, p_nest, config.nests_flange_m, config.q_home_rad
    )
    assert clear.usable[0] and lo <= clear.q[0, 2] <= hi
    home_arm = ur_branch_index(config.nominal, config.q_home_rad[None])[0] & 5
    assert ur_branch_index(config.nominal, clear.q)[0] & 5 == home_arm
    assert _colliding_moves(config, clear.q) == []
    assert config.bodies.pair_slack_m(config.nominal, clear.q).min() >= 0.0


def test_a_pose_without_a_clear_configuration_is_left_out_with_its_reason(config):
    """The tool pointing down beside the base, low: the nominal IK answers it with the tool in the arm's own
    body, and no configuration with home's shoulder and elbow keeps clear."""
    T = np.eye(4)[None].copy()
    T[0, :3, 3] = [0.0, 0.2, 0.2]
    T[0, :3, :3] = np.diag([1.0, -1.0, -1.0])
    p_nest = config.nests_flange_m[0]
    nominal = plan_joints(config.nominal, T, p_nest, q_near=config.q_home_rad)
    assert nominal.usable[0] and config.bodies.collides(config.nominal, nominal.q)[0]
    plan = plan_clear_joints(
        config.nominal, config.envelope, T, p_nest, config.nests_flange_m, config.q_home_rad
    )
    assert not plan.usable[0] and plan.reason[0] == NO_CLEAR


def test_a_pose_no_move_reaches_safely_is_dropped_and_counted(config):
    grid = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0)
    folded = config.q_home_rad.copy()
    folded[2] = np.deg2rad(175.0)  # the forearm folded onto the upper arm: no way there is clear
    bad = PlannedPose("folded", grid.procedure, "grid", folded, "nest1")
    plan = Plan(grid.procedure, [grid.poses[0], bad, *grid.poses[1:3]], config)
    kept = plan.without_unsafe_moves()
    assert [p.point_id for p in kept.poses] == [p.point_id for p in (grid.poses[0], *grid.poses[1:3])]
    assert kept.dropped == {NO_SAFE_PATH: 1}
    assert f"1 {NO_SAFE_PATH}" in kept.describe()


def test_the_dry_run_shows_each_poses_clearance_and_a_refusal_names_pose_bodies_and_clearance(config):
    plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.2, validation=0)
    nearest = plan.nearest_bodies()
    found = config.bodies.clearances(config.nominal, plan.joints())
    assert [c for c, _ in nearest] == pytest.approx(np.minimum(found.self_m, found.cell_m).tolist())
    text = plan.describe(max_rows=3)
    k = int(np.argmin([c for c, _ in nearest]))
    clearance, between = nearest[k]
    assert f"smallest clearance: {clearance * 1e3:.0f} mm ({between}) at {plan.poses[k].point_id}" in text
    rows = [line for line in text.splitlines() if line.strip().startswith(("1 ", "2 ", "3 "))]
    assert [row.endswith(f" mm ({b})") for row, (_, b) in zip(rows, nearest, strict=False)] == [True] * 3
    folded = config.q_home_rad.copy()
    folded[2] = np.deg2rad(175.0)
    with pytest.raises(EnvelopeError) as refused:
        config.envelope.check_poses(config.nominal, folded[None], config.nests_flange_m, ["g1-0999"])
    message = str(refused.value)
    own = config.bodies.clearances(config.nominal, folded[None])
    overlap_mm = -own.self_m[0] * 1e3
    assert overlap_mm > 0
    assert f"g1-0999: {own.self_between[0]} collide ({overlap_mm:.0f} mm overlap; margin 10 mm)" in message


def test_a_move_whose_direct_path_collides_gets_a_detour_whose_every_leg_keeps_clear(config):
    env, tools = config.envelope, config.nests_flange_m
    # clear poses about home with the wrist turned every way: some direct moves between them collide
    turns = np.random.default_rng(3).uniform(-1, 1, (40, 6)) * np.deg2rad([40, 20, 30, 150, 150, 90])
    q = config.q_home_rad + turns
    q = q[~env.outside(config.nominal, q, tools)]
    i, j = np.triu_indices(len(q), k=1)
    problems = env.path_problems(config.nominal, q[i], q[j])
    colliding = [k for k, p in enumerate(problems) if p]
    assert colliding
    found = 0
    for k in colliding[:20]:
        legs = env.detour(config.nominal, q[i[k]], q[j[k]], tools, config.q_home_rad)
        if legs is None:
            continue
        found += 1
        np.testing.assert_array_equal(legs[-1], q[j[k]])
        starts = [q[i[k]], *legs[:-1]]
        assert env.path_problems(config.nominal, np.array(starts), np.array(legs)) == [None] * len(legs)
    assert found


def _passes(env, nominal, q_from, q_to, tools) -> bool:
    try:
        env.check_joint_move(nominal, q_from, q_to, tools)
    except EnvelopeError:
        return False
    return True


def test_moves_checked_at_once_are_judged_as_one_by_one(config):
    """Envelope.clear_moves (a plan's moves in one pass) against check_joint_move move by move: moves that
    leave the box, cross a joint limit or collide on the way, and moves that keep clear, long and short."""
    env, tools, nominal = config.envelope, config.nests_flange_m, config.nominal
    lo, hi = np.array(nominal.joint_limits).T
    rng = np.random.default_rng(5)
    near = config.q_home_rad + rng.uniform(-1, 1, (60, 6)) * np.deg2rad([40, 20, 30, 150, 150, 90])
    q_from = np.vstack([near[:30], rng.uniform(lo, hi, (30, 6)), near[:1]])
    q_to = np.vstack([near[30:], rng.uniform(lo, hi, (30, 6)), near[:1] + 1e-4])
    one_by_one = [_passes(env, nominal, a, b, tools) for a, b in zip(q_from, q_to, strict=True)]
    assert 10 < sum(one_by_one) < len(one_by_one) - 10  # both kinds, many of each
    assert env.clear_moves(nominal, q_from, q_to, tools).tolist() == one_by_one


def test_the_travel_order_laid_out_ahead_is_the_order_step_by_step(config):
    """clear_travel_order checks the plain order's moves ahead at once; where the nearest move collides it
    must still pick as step by step: the nearest candidate whose move keeps clear, else the nearest."""
    env, nominal = config.envelope, config.nominal
    rng = np.random.default_rng(1)
    q = config.q_home_rad + rng.uniform(-1, 1, (90, 6)) * np.deg2rad([120, 60, 80, 180, 180, 180])
    q = q[~env.outside(nominal, q, config.nests_flange_m)]
    left, current, expected, swerves = np.ones(len(q), bool), config.q_home_rad, [], 0
    for _ in range(len(q)):
        cost = np.where(left, np.max(np.abs(q - current), axis=1), np.inf)
        nearest = np.argsort(cost)[: min(ORDER_CANDIDATES, int(left.sum()))]
        ok = np.flatnonzero(
            np.isnan(config.bodies.path_collisions(nominal, np.tile(current, (len(nearest), 1)), q[nearest]))
        )
        pick = int(nearest[ok[0]]) if ok.size else int(nearest[0])
        swerves += pick != nearest[0]
        expected.append(pick)
        left[pick] = False
        current = q[pick]
    assert swerves >= 2  # the case the look-ahead must not get wrong
    assert clear_travel_order(nominal, env, q, config.q_home_rad).tolist() == expected
