"""Joints that keep clear of the arm itself and of the cell, and an order of visiting them whose moves do too.

The nominal IK answers a tool pose with the configuration nearest a reference posture, 2 pi turns
included; on a UR arm that is often an elbow at 234 deg (reached from home's 90 deg through the fold at
180 deg) or a wrist turned back towards the forearm. A UR-shaped arm reaches a tool pose in up to 8
closed-form configurations (shoulder, elbow and wrist each one way or the other; 2 pi turns change no
geometry), so `plan_clear_joints` chooses, per pose:

- among the configurations with the reference posture's shoulder and elbow (the others reach over
  backwards or hang the elbow below the shoulder, towards a floor or table that no body model holds);
- with the elbow and joint 5 turned only within the range each turns from the reference without folding
  the arm onto itself (`FOLDING`);
- inside the envelope and keeping every margin: the plan's preferred configuration (one wrist for the whole
  plan: consecutive moves stay small, the SMR keeps facing the tracker between poses), else the one with
  the largest clearance up to `COMFORT_M` beyond its margin, the nearest the reference among equals.

A pose with no such configuration is left out with the reason `NO_CLEAR`. Other six-joint arms (no closed
form here) get the nominal IK near the reference with the same rule on the folding joints: where its answer
turns the elbow or joint 5 beyond the range each turns from the reference without folding, the IK is solved
again inside that range from each of the arm's configurations (`_unfolded_ik`), the clearest kept. On an
arm whose elbow turns further than a half turn (a FANUC-like forearm that may swing over the top), the
answer nearest the reference is otherwise often the elbow bent the other way, reached from the reference
only through the fold (upper arm and forearm in one another), so that no move and no detour gets there; a
pose reached only so is left out with `NO_CLEAR`. Every answer is then checked the same way.

`clear_travel_order` is the greedy nearest-neighbour order of hil.runner.planners.travel_order (the largest
joint travel, wrist joints included, so wrist moves stay small) that passes over a neighbour whose direct
move would come too close to anything while another of the next nearest can be reached directly.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from hil.geometry.arm_configurations import arm_configuration_seeds, has_parallel_shoulder_and_elbow
from hil.geometry.collision import clear_range_rad
from hil.geometry.ik import (
    IKOptions,
    is_ur_like,
    nearest_equivalent,
    ur_analytic_ik,
    ur_branch_index,
)
from hil.geometry.kinematics import KinematicModel
from hil.runner.envelope import Envelope
from hil.runner.planners import SINGULAR_SIGMA_M, JointPlan, plan_joints

if TYPE_CHECKING:
    from hil.runner.cell_config import CellConfig

TWO_PI = 2.0 * np.pi
# Clearance beyond the margins past which a configuration counts as clear as any other: 0.1 m, twice the
# cell margin's default, about a forearm's radius.
COMFORT_M = 0.10
# Neighbours tried per step of the order before a move that needs a detour is accepted.
ORDER_CANDIDATES = 8
ORDER_LOOKAHEAD = 32  # steps of the plain travel order whose moves are checked at once (clear_travel_order)
NO_CLEAR = "no clear configuration"  # the reason a pose is left out when none of its configurations is clear
# the joints that fold a UR-shaped arm onto itself when turned far from its reference posture: the elbow
# (joint 3: the forearm onto the upper arm) and joint 5 (the tool onto the forearm)
FOLDING = (2, 4)
ARM_BITS = (
    4 + 1
)  # the shoulder and elbow bits of a closed-form branch index (hil.geometry.ik.ur_branch_index)


def plan_clear_joints(
    nominal: KinematicModel,
    envelope: Envelope,
    T_base_tool: np.ndarray,
    p_flange_tool_m: np.ndarray,
    p_flange_tools_m: np.ndarray,
    q_near: np.ndarray,
    singular_sigma_m: float = SINGULAR_SIGMA_M,
    like: np.ndarray | None = None,
) -> JointPlan:
    """Joints for tool poses (N, 4, 4) with the tool point `p_flange_tool_m`, usable only when reachable,
    within limits, away from singularities and inside the envelope (box and, when it checks them, the
    collisions of every tool point `p_flange_tools_m`), reason "envelope" otherwise. With collision checks
    on a UR-shaped arm, each pose's configuration is the clearest of its closed-form branches, on another
    six-joint arm the nominal IK's unless it folds the elbow or joint 5 (see module);
    `like` (M, 6), joints planned before (a grid for its validation poses): only their configuration and
    turns, so the new poses lie where those were measured (a pose clear only in another is left out)."""
    T = np.asarray(T_base_tool, float)
    first = plan_joints(nominal, T, p_flange_tool_m, q_near=q_near, singular_sigma_m=singular_sigma_m)
    if envelope.bodies is not None and is_ur_like(nominal) and len(T):
        seeds = _clearest_branch(nominal, envelope, T, p_flange_tool_m, p_flange_tools_m, q_near, like)
        has_seed = np.all(np.isfinite(seeds), axis=1)
        # a pose the nominal IK cannot use keeps its reason (unreachable, singular, ...)
        q, usable = first.q.copy(), np.zeros(len(T), bool)
        reason = np.where(first.usable, NO_CLEAR, first.reason.astype(object))
        if has_seed.any():
            chosen = plan_joints(
                nominal, T[has_seed], p_flange_tool_m, q_near, singular_sigma_m, q_seed=seeds[has_seed]
            )
            unfolded = _unfolded(nominal, envelope, q_near).within_limits(chosen.q, tol=1e-9)
            rows = np.flatnonzero(has_seed)
            q[rows], usable[rows] = chosen.q, chosen.usable & unfolded
            reason[rows] = np.where(unfolded, chosen.reason.astype(object), NO_CLEAR)
        first = JointPlan(q, usable, reason.astype(str))
    elif envelope.bodies is not None and nominal.n_joints == 6 and len(T):
        first = _unfolded_ik(
            nominal, envelope, T, p_flange_tool_m, p_flange_tools_m, q_near, singular_sigma_m, first
        )
    reason = first.reason.astype(object)
    usable = first.usable.copy()
    if usable.any():
        rows = np.flatnonzero(usable)
        outside = envelope.outside(nominal, first.q[rows], p_flange_tools_m)
        reason[rows[outside]] = "envelope"
        usable[rows[outside]] = False
    return JointPlan(first.q, usable, reason.astype(str))


def plan_cell_joints(config: CellConfig, T_base_tool: np.ndarray, nest: int = 1) -> JointPlan:
    """Joints for tool poses (N, 4, 4) with the SMR in tool nest `nest` (1-based), planned as the shipped
    procedures plan them: reachable, away from singularities, inside the cell's envelope and, with its
    collision checks (the default), in a configuration clear of the arm itself, the tracker and the
    keep-out boxes, near home. The planner a plug-in procedure calls with its cell config: the nominal IK
    alone (`plan_joints`) may answer with a folded elbow that the engine then refuses to move to."""
    nests = np.atleast_2d(config.nests_flange_m)
    if not 1 <= nest <= len(nests):
        raise ValueError(f"the tool has nests 1..{len(nests)}, not {nest}")
    return plan_clear_joints(
        config.nominal, config.envelope, T_base_tool, nests[nest - 1], nests, config.q_home_rad
    )


def _unfolded_ik(
    nominal: KinematicModel,
    envelope: Envelope,
    T_base_tool: np.ndarray,
    p_flange_tool_m: np.ndarray,
    p_flange_tools_m: np.ndarray,
    q_near: np.ndarray,
    singular_sigma_m: float,
    nearest: JointPlan,
) -> JointPlan:
    """The plan `nearest` (the nominal IK near q_near) with each answer that turns a FOLDING joint beyond
    where it turns from q_near without folding solved again inside that range: on an arm with parallel
    joints 2 and 3, from each of its arm and wrist configurations (hil.geometry.arm_configurations), the
    clearest kept (as `_branch_scores` says, the nearest q_near among equals); on others, the nominal IK
    again. A pose the IK reaches only beyond that range is marked NO_CLEAR (no move from the reference's
    side gets there without passing the fold); one it does not reach at all keeps its reason."""
    unfolded = _unfolded(nominal, envelope, q_near)
    folded = nearest.usable & ~unfolded.within_limits(nearest.q, tol=1e-9)
    if not folded.any():
        return nearest
    rows = np.flatnonzero(folded)
    if has_parallel_shoulder_and_elbow(nominal):
        candidates = _configurations(
            unfolded, T_base_tool[rows], p_flange_tool_m, nearest.q[rows], q_near, singular_sigma_m
        )
        again = _clearest(nominal, envelope, candidates, p_flange_tools_m, q_near)
    else:
        again = plan_joints(unfolded, T_base_tool[rows], p_flange_tool_m, q_near, singular_sigma_m)
    q, usable, reason = nearest.q.copy(), nearest.usable.copy(), nearest.reason.astype(object)
    q[rows] = np.where(again.usable[:, None], again.q, nearest.q[rows])
    usable[rows] = again.usable
    reason[rows] = np.where(again.usable, again.reason.astype(object), NO_CLEAR)
    return JointPlan(q, usable, reason.astype(str))


def _configurations(
    unfolded: KinematicModel,
    T_base_tool: np.ndarray,
    p_flange_tool_m: np.ndarray,
    q: np.ndarray,
    q_near: np.ndarray,
    singular_sigma_m: float,
) -> JointPlan:
    """(M, 8) candidates for the tool poses (M, 4, 4) that q (M, 6) reaches: the IK inside the unfolded
    model's limits from each of q's arm and wrist configurations (2 pi-shifted nearest q_near), usable
    where it converged away from a singularity. A configuration no shift brings inside is not tried."""
    seeds = arm_configuration_seeds(unfolded, q)  # (8, M, 6)
    shifted, inside = nearest_equivalent(unfolded, seeds, np.broadcast_to(q_near, seeds.shape))
    answers, usable = np.full(seeds.shape, np.nan), np.zeros(seeds.shape[:2], bool)
    for k in range(len(seeds)):
        rows = np.flatnonzero(inside[k])
        if not rows.size:
            continue
        found = plan_joints(
            unfolded, T_base_tool[rows], p_flange_tool_m, q_near, singular_sigma_m,
            q_seed=shifted[k, rows], options=IKOptions(restarts=0),
        )  # fmt: skip
        answers[k, rows], usable[k, rows] = found.q, found.usable
    q_out = np.swapaxes(answers, 0, 1)
    return JointPlan(q_out, usable.T, np.where(usable.T, "ok", NO_CLEAR))


def _clearest(
    nominal: KinematicModel,
    envelope: Envelope,
    candidates: JointPlan,
    p_flange_tools_m: np.ndarray,
    q_near: np.ndarray,
) -> JointPlan:
    """Per pose (M,) the clearest of its usable candidates (M, B, 6) (the nearest q_near among equals to a
    millimetre), one outside the envelope only when none is inside (the envelope check then says so);
    NO_CLEAR when none is usable."""
    q, usable = candidates.q, candidates.usable
    score = _branch_scores(nominal, envelope, np.nan_to_num(q), usable, p_flange_tools_m)
    distance = np.linalg.norm(np.nan_to_num(q) - q_near, axis=2)
    key = np.where(np.isfinite(score), np.round(score, 3) * 1e6 - distance, -1e9 - distance)
    key = np.where(usable, key, -np.inf)
    pick = np.argmax(key, axis=1)
    rows = np.arange(len(q))
    found = usable[rows, pick]
    return JointPlan(q[rows, pick], found, np.where(found, "ok", NO_CLEAR))


def _clearest_branch(
    nominal: KinematicModel,
    envelope: Envelope,
    T_base_tool: np.ndarray,
    p_flange_tool_m: np.ndarray,
    p_flange_tools_m: np.ndarray,
    q_near: np.ndarray,
    like: np.ndarray | None,
) -> np.ndarray:
    """(N, 6) per pose a closed-form configuration (2 pi-shifted into the limits, nearest q_near) inside the
    envelope with q_near's shoulder and elbow: the plan's preferred branch where it keeps its margins, else
    the pose's clearest; NaN where none is inside the envelope. `_branch_scores` says what clearest means."""
    assert envelope.bodies is not None
    T_flange_tool = np.eye(4)
    T_flange_tool[:3, 3] = np.asarray(p_flange_tool_m, float)
    T_base_flange = T_base_tool @ np.linalg.inv(T_flange_tool)
    branches, valid = ur_analytic_ik(nominal, T_base_flange)  # (N, 8, 6)
    N, B, n = branches.shape
    ref = np.broadcast_to(np.asarray(q_near, float), (N, B, n))
    unfolded = _unfolded(nominal, envelope, q_near)
    shifted, in_limits = nearest_equivalent(unfolded, np.nan_to_num(branches), ref)
    # the reference posture's shoulder and elbow (a UR home: elbow up, facing forward); the others reach
    # over backwards or hang the elbow below the shoulder, towards a floor or table no body model holds
    same_arm = (np.arange(B) & ARM_BITS) == (
        int(ur_branch_index(nominal, np.asarray(q_near, float)[None])[0]) & ARM_BITS
    )
    score = _branch_scores(nominal, envelope, shifted, valid & in_limits & same_arm, p_flange_tools_m)
    distance = np.linalg.norm(shifted - ref, axis=2)
    # the clearest (to a millimetre), then the nearest
    key = np.where(np.isfinite(score), np.round(score, 3) * 1e6 - distance, -np.inf)
    # but the plan's preferred branch wherever it keeps its margins: one configuration (the one clear at
    # the most poses, then the clearest at its median pose) keeps consecutive moves small and the SMR
    # facing the tracker between poses (a wrist flip on the way turns it out of the beam)
    clear = score >= 0
    median = np.array([np.median(score[clear[:, b], b]) if clear[:, b].any() else -np.inf for b in range(B)])
    preferred = int(np.lexsort((median, clear.sum(axis=0)))[-1])
    if like is not None and len(like):
        preferred = int(np.bincount(ur_branch_index(nominal, like), minlength=B).argmax())
    pick = np.where(clear[:, preferred], preferred, np.argmax(key, axis=1))
    seeds = shifted[np.arange(N), pick]
    found = np.isfinite(key[np.arange(N), pick])
    if like is not None and len(like):
        found &= pick == preferred  # only where those were measured: another wrist is another arm's data
    seeds[~found] = np.nan
    if found.any():
        around = seeds[found] if like is None or not len(like) else np.asarray(like, float)
        seeds[found] = _compact(unfolded, seeds[found], around, np.asarray(q_near, float))
    return seeds


def _compact(model: KinematicModel, q: np.ndarray, around: np.ndarray, q_near: np.ndarray) -> np.ndarray:
    """The joint sets (M, n) turned by 2 pi where that brings them nearest the circular mean of `around`
    (in its turn nearest q_near) inside the limits: a UR base whose poses lie about 180 deg from home's
    would otherwise be split between -170 and +170 deg, a 340 deg move between two neighbouring poses."""
    centre = np.arctan2(np.sin(around).mean(axis=0), np.cos(around).mean(axis=0))
    centre += TWO_PI * np.round((q_near - centre) / TWO_PI)
    compact, ok = nearest_equivalent(model, q, np.broadcast_to(centre, q.shape))
    return np.where(ok[:, None], compact, q)


def _unfolded(nominal: KinematicModel, envelope: Envelope, q_near: np.ndarray) -> KinematicModel:
    """The model with the FOLDING joints limited to where each turns from q_near, the others held, without
    folding the arm onto itself: a UR elbow at 234 deg stands where it would at -126 deg, but reaching it
    from 90 deg passes through the fold at 180 deg (forearm and upper arm are adjacent: only the elbow
    moves that fold); on the LR Mate (elbow limits -160..190 deg) the forearm folds onto the upper arm at
    90 deg from its zero. Joint 5 likewise swings the tool into the forearm."""
    assert envelope.bodies is not None
    limits = np.array(nominal.joint_limits, float)
    for joint in FOLDING:
        lo, hi = clear_range_rad(envelope.bodies, nominal, np.asarray(q_near, float), joint)
        limits[joint] = max(limits[joint, 0], lo), min(limits[joint, 1], hi)
    return replace(nominal, joint_limits=limits)


def _branch_scores(
    nominal: KinematicModel,
    envelope: Envelope,
    q: np.ndarray,
    usable: np.ndarray,
    p_flange_tools_m: np.ndarray,
) -> np.ndarray:
    """(N, B) how clear each pose's configurations q (N, B, n) are: the smallest slack (clearance beyond
    its margin) of the body pairs that tell them apart, capped at COMFORT_M; -inf where a configuration is
    unusable or outside the envelope. A pair that keeps the same clearance (to a millimetre) in all of a
    pose's configurations (two wrist housings whose distance no joint changes) decides nothing between
    them and is left out, unless it is too close, which no choice then cures."""
    assert envelope.bodies is not None
    N, B, n = q.shape
    flat = q.reshape(-1, n)
    rows = np.flatnonzero(usable.ravel())
    pair_slack = np.full((N * B, envelope.bodies.pair_count(nominal)), np.nan)
    inside = np.zeros(N * B, bool)
    if rows.size:
        pair_slack[rows] = envelope.bodies.pair_slack_m(nominal, flat[rows])
        inside[rows] = ~envelope.outside(nominal, flat[rows], p_flange_tools_m)
    pair_slack = pair_slack.reshape(N, B, -1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a pose without any usable configuration
        spread = np.nanmax(pair_slack, axis=1) - np.nanmin(pair_slack, axis=1)  # (N, Q)
    deciding = ~(spread < 1e-3)[:, None, :] | (pair_slack < 0)
    slack = np.where(deciding & ~np.isnan(pair_slack), pair_slack, np.inf).min(axis=2)
    score = np.minimum(slack, COMFORT_M)
    return np.where(inside.reshape(N, B), score, -np.inf)


def clear_travel_order(
    nominal: KinematicModel,
    envelope: Envelope,
    q: np.ndarray,
    q_start: np.ndarray,
) -> np.ndarray:
    """Visiting order (indices) of joint sets (N, n) from q_start: each step the nearest (largest joint
    travel) of the poses left whose direct move keeps clear, among the ORDER_CANDIDATES nearest; the nearest
    when none of them does (its move then needs a detour). Without collision checks, the plain travel order.

    Most nearest moves keep clear, so the plain order is laid out ORDER_LOOKAHEAD steps ahead and its moves
    checked at once; only a step whose nearest move does not keep clear checks its other candidates, and
    the plain order is laid out again from the pose it picks (the same order as step by step, far fewer
    collision passes)."""
    q = np.atleast_2d(np.asarray(q, float))
    left = np.ones(len(q), bool)
    order = np.empty(len(q), int)
    current = np.asarray(q_start, float)
    k = 0
    while k < len(q):
        ahead = _nearest_candidates(
            q, left, current, ORDER_LOOKAHEAD if envelope.bodies is not None else len(q)
        )
        picks = np.array([nearest[0] for nearest in ahead])
        clear = np.ones(len(ahead), bool)
        if envelope.bodies is not None:
            starts = np.vstack([current[None], q[picks[:-1]]])
            clear = np.isnan(envelope.bodies.path_collisions(nominal, starts, q[picks]))
        for nearest, nearest_clear in zip(ahead, clear, strict=True):
            pick = int(nearest[0])
            if not nearest_clear:  # its other candidates, nearest first
                assert envelope.bodies is not None
                others = np.isnan(
                    envelope.bodies.path_collisions(nominal, np.tile(current, (len(nearest), 1)), q[nearest])
                )
                ok = np.flatnonzero(others)
                if ok.size:
                    pick = int(nearest[ok[0]])
            order[k] = pick
            left[pick] = False
            current = q[pick]
            k += 1
            if pick != nearest[0]:
                break  # the plain order laid out past here started from another pose
    return order


def _nearest_candidates(q: np.ndarray, left: np.ndarray, current: np.ndarray, steps: int) -> list[np.ndarray]:
    """The plain travel order's next `steps` steps from `current`: per step, the ORDER_CANDIDATES poses left
    nearest to the one before (largest joint travel), nearest first; the first of each is the step's pose."""
    left = left.copy()
    found = []
    for _ in range(min(steps, int(left.sum()))):
        cost = np.max(np.abs(q - current), axis=1)
        cost[~left] = np.inf
        nearest = np.argsort(cost)[: min(ORDER_CANDIDATES, int(left.sum()))]
        found.append(nearest)
        left[nearest[0]] = False
        current = q[nearest[0]]
    return found
