"""The next measurements: joint configurations that decide a diagnosis' open questions (hil.analysis.diagnosis.questions).

Two kinds of rows, in the order to measure them:

1. What physics asks for, built directly: a single-joint sweep over most of a turn where a once-per-turn
   error is uncovered; the joint moved up then down through the same range where backlash has one
   approach direction (row order is motion order, as the campaign reads it); the campaign's first poses
   measured again at the end of the plan where drift has no evidence.
2. Poses that separate rival models, chosen greedily from a pool of reachable configurations by a
   Bayesian T-optimal criterion. T-optimality (Atkinson & Fedorov) maximises the lack of fit of one model
   when its rival is true; linearised about the fitted model, the lack of fit a rival coefficient of size
   delta leaves after every other parameter is refitted is delta^2 / Cov_cc (its Schur complement). The
   rival's size is unknown (the question is open because it is small or hidden), so instead of a point
   estimate each coefficient is taken at its *smallest relevant size* (the size that moves the SMR by
   `RELEVANT_LENGTH_M` RMS on the campaign's poses): the Bayesian variant with that prior. Its evidence
   z = size / (sigma * sqrt(Cov_cc)) is the signal-to-noise the diagnosis' test sees; a question is
   decided when every rival coefficient reaches `DECISIVE_Z` (a two-sided test at 1e-3 with power 0.9
   against an effect of that size). The greedy gain saturates at that threshold, so poses go to the
   questions still short of it: the plan stops for each question when its evidence passes, not at a count.
   Why not D-optimality: it shrinks the variance of one model fixed in advance, spending poses on
   parameters no question is about; the rival columns here are what the next test needs.
   A marginal candidate that the full-fit test finds is the exception (`held_out_z`): its evidence is the
   held-out test's own z, scaled by the same standard errors, so a question is decided only when the
   selection's own test can decide it and the loop plans another round until then.
   The design's rows are cut into blocks of `BLOCK_ROWS` in greedy order (a short tour inside each block), so
   a round measured block by block and stopped when its questions are decided has measured the most
   informative rows first (hil.analysis.design.rounds).

Reachability and line of sight are the caller's: `admissible(q) -> bool mask` (joint limits of the robot
file are always applied here). hil.runner knows the cell's envelope and tracker; this layer does not.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import Problem
from hil.analysis.design import BLOCK_ROWS
from hil.analysis.diagnosis.evidence import DECISIVE_Z, Rival, rival_for, scaled_rows, unmeasured_problem
from hil.analysis.diagnosis.questions import (
    MIN_REVISITS,
    MIN_ROWS_PER_DIRECTION,
    DriftUnmonitored,
    OneApproachDirection,
    PeriodNotCovered,
    Question,
    question_to_dict,
    with_questions,
)
from hil.data.dataset import joints_rad, pose_ids
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import CYCLIC_MIN_PERIODS

# A test-led question's held-out z grows with the poses that show its effect (`Rival.test_z_after` counts
# campaign-average poses); a designed pose shows it better, by about 2.6-4 campaign-average poses on the
# simulated cells (gravity_cyclic1 seed 4: held-out z 2.1 on 96 poses, decided after 65 designed ones). A
# question the whole budget would not decide even at this bound is hopeless and is not planned (the demo's
# first round spent 36 of 40 poses moving a held-out z of 1.4 to 1.5).
MAX_DESIGN_ROW_WORTH = 10.0
SWEEP_SPAN = 0.95 * 2 * np.pi  # a sweep covers this much of a turn where the limits allow
SWEEP_POINTS = 12
APPROACH_STEP_RAD = float(np.deg2rad(3.0))
POOL_SIZE = 1500
POOL_PERTURB_RAD = float(np.deg2rad(30.0))

Admissible = Callable[[np.ndarray], np.ndarray]  # (M, n) joints -> (M,) bool: reachable and measurable


@dataclass
class Proposal:
    """Rows a diagnosis proposes to measure, in order, the question each serves, and each group's expected
    evidence (not hil.runner.plan.Plan, the poses a procedure runs)."""

    q: np.ndarray  # (M, n) rad
    purpose: list[str]
    groups: list[dict] = field(default_factory=list)  # {purpose, rows, question, evidence_before/after, ...}
    not_planned: list[dict] = field(default_factory=list)  # questions this plan does not serve, and why

    def frame(self) -> pd.DataFrame:
        """The plan in the contract: q1_rad .. qn_rad in measurement order, then `purpose`."""
        n = self.q.shape[1] if self.q.ndim == 2 and self.q.size else 6
        df = pd.DataFrame(np.reshape(self.q, (-1, n)), columns=[f"q{j + 1}_rad" for j in range(n)])
        df["purpose"] = pd.Series(self.purpose, dtype=object)
        return df

    def to_dict(self) -> dict:
        """The plan's groups and the questions it does not serve, each question as stored (`Question.to_dict`)."""
        return {
            "rows": len(self.purpose),
            "groups": [with_questions(g, question_to_dict) for g in self.groups],
            "not_planned": [with_questions(n, question_to_dict) for n in self.not_planned],
        }


@dataclass(frozen=True)
class _Design:
    """What every part of a plan is designed against: the campaign, its model, the tracker noise, which
    configurations are admissible, the random draws and the blocks a round is measured in."""

    df: pd.DataFrame
    model: CalibratedModel
    sigma_m: float
    ok: Admissible
    rng: np.random.Generator
    block_rows: int

    @property
    def q_camp(self) -> np.ndarray:
        return joints_rad(self.df)

    @property
    def limits(self) -> np.ndarray:
        return np.asarray(self.model.nominal.joint_limits, float)


@dataclass
class _Draft:
    """A plan being built: its rows so far (joints, purpose), their groups, the questions it leaves and the
    rows still in the budget."""

    budget: int
    rows: list[tuple[np.ndarray, str]] = field(default_factory=list)
    groups: list[dict] = field(default_factory=list)
    not_planned: list[dict] = field(default_factory=list)

    def add(self, q: np.ndarray, purpose: str, group: dict) -> None:
        """Rows q (k, n) that serve `purpose`, out of the budget, with their group."""
        self.rows += [(row, purpose) for row in q]
        self.budget -= len(q)
        self.groups.append({"purpose": purpose, "rows": len(q), **group})


def propose(
    df: pd.DataFrame,
    model: CalibratedModel,
    questions: list[Question],
    max_rows: int,
    sigma_m: float,
    admissible: Admissible | None = None,
    seed: int = 0,
    block_rows: int = BLOCK_ROWS,
) -> Proposal:
    """At most `max_rows` joint configurations, in measurement order, that decide `questions` on `df`.

    `sigma_m`: 1-sigma tracker noise per axis; `admissible`: which configurations the cell can reach and
    the tracker can see (joint limits are applied here in any case); `block_rows`: the blocks a round is
    measured and re-judged in (hil.analysis.design.rounds): the design's rows are ordered so that every
    block boundary of the plan ends a greedy prefix.
    """
    if max_rows < 1:
        raise ValueError(f"a plan needs at least 1 row, got {max_rows}")
    q_camp = joints_rad(df)
    limits = np.asarray(model.nominal.joint_limits, float)

    def ok(q: np.ndarray) -> np.ndarray:
        inside = np.all((q >= limits[:, 0]) & (q <= limits[:, 1]), axis=1)
        return inside & (np.ones(len(q), bool) if admissible is None else np.asarray(admissible(q), bool))

    design = _Design(df, model, sigma_m, ok, np.random.default_rng(seed), block_rows)
    plannable = [qu for qu in questions if qu.plannable]
    plan = Proposal(np.zeros((0, q_camp.shape[1])), [])
    plan.not_planned = [
        {"question": qu, "why": "poses cannot decide it"} for qu in questions if not qu.plannable
    ]
    if not plannable:
        return plan
    drift = [qu for qu in plannable if isinstance(qu, DriftUnmonitored)]
    reserve = min(MIN_REVISITS, max_rows // 2 if len(plannable) > len(drift) else max_rows) if drift else 0
    draft = _Draft(max_rows - reserve, not_planned=plan.not_planned)
    centre = _central_pose(q_camp)
    backlash_joints = _plan_sweeps(draft, design, plannable, centre)
    _plan_back_and_forth(draft, design, plannable, centre, backlash_joints)
    physics_q = np.array([r[0] for r in draft.rows]).reshape(-1, q_camp.shape[1])
    stat = [
        qu
        for qu in plannable
        if not isinstance(qu, PeriodNotCovered | OneApproachDirection | DriftUnmonitored)
    ]
    if stat:
        first_block = block_rows - len(draft.rows) % block_rows
        design_rows, design_groups, skipped = _separate(design, stat, physics_q, draft.budget, first_block)
        draft.rows += design_rows
        draft.groups += design_groups
        draft.not_planned += skipped
    if drift:
        first = _first_poses(df, q_camp, reserve, ok)
        draft.rows += [(q, "revisit") for q in first]
        draft.groups.append({"purpose": "revisit", "rows": len(first), "question": drift[0]})
    plan.q = np.array([r[0] for r in draft.rows]).reshape(-1, q_camp.shape[1])
    plan.purpose = [r[1] for r in draft.rows]
    plan.groups = draft.groups
    return plan


def _plan_sweeps(draft: _Draft, design: _Design, plannable: list[Question], centre: np.ndarray) -> set[int]:
    """A sweep over most of a turn for each uncovered period; where the joint's backlash has one approach
    direction too, the sweep comes back down and serves both. Returns the joints whose backlash is left."""
    backlash = [qu for qu in plannable if isinstance(qu, OneApproachDirection)]
    backlash_joints = {qu.effect["joint"] for qu in backlash}
    q_camp, limits = design.q_camp, design.limits
    for qu in [qu for qu in plannable if isinstance(qu, PeriodNotCovered)]:
        j = qu.effect["joint"] - 1
        both = (j + 1) in backlash_joints
        sweep = _sweep(q_camp, centre, j, limits, design.ok, both, design.rng)
        if sweep is None:
            draft.not_planned.append(
                {"question": qu, "why": "no reachable, visible sweep covers enough of a turn"}
            )
            continue
        if len(sweep) > draft.budget:
            draft.not_planned.append(
                {"question": qu, "why": f"the budget leaves {draft.budget} rows, a sweep needs {len(sweep)}"}
            )
            continue
        span = float(np.rad2deg(np.ptp(np.concatenate([q_camp[:, j], sweep[:, j]]))))
        draft.add(sweep, f"sweep_j{j + 1}", {"question": qu, "range_after_deg": span})
        if both:
            backlash_joints.discard(j + 1)
            draft.groups[-1]["also"] = f"backlash_j{j + 1}"
            draft.groups[-1]["also_question"] = next(b for b in backlash if b.effect["joint"] == j + 1)
    return backlash_joints


def _plan_back_and_forth(
    draft: _Draft, design: _Design, plannable: list[Question], centre: np.ndarray, backlash_joints: set[int]
) -> None:
    """The joint moved up then down through the same range for each backlash with one approach direction
    that no sweep serves."""
    for qu in [qu for qu in plannable if isinstance(qu, OneApproachDirection)]:
        j = qu.effect["joint"] - 1
        if (j + 1) not in backlash_joints:
            continue
        there = _back_and_forth(centre, j, design.limits, design.ok)
        if there is None or len(there) > draft.budget:
            draft.not_planned.append(
                {"question": qu, "why": "no room (limits, envelope or budget) to move it both ways"}
            )
            continue
        draft.add(there, f"backlash_j{j + 1}", {"question": qu})


def _central_pose(q: np.ndarray) -> np.ndarray:
    """The campaign pose nearest its joint-wise median: a posture the cell is known to reach and see."""
    return q[int(np.argmin(np.sum((q - np.median(q, axis=0)) ** 2, axis=1)))]


def _sweep(q_camp, centre, j, limits, ok, both, rng) -> np.ndarray | None:
    """Joint j swept up over most of a turn (then down again when `both`) from a campaign posture; the
    posture whose admissible sweep covers the most of a turn wins (None if none covers enough)."""
    need = CYCLIC_MIN_PERIODS * 2 * np.pi
    postures = [centre, *q_camp[rng.choice(len(q_camp), min(8, len(q_camp)), replace=False)]]
    best, best_span = None, 0.0
    lo_lim, hi_lim = limits[j]
    for base in postures:
        span = min(SWEEP_SPAN, hi_lim - lo_lim)
        lo = float(np.clip(base[j] - span / 2, lo_lim, hi_lim - span))
        values = np.linspace(lo, lo + span, SWEEP_POINTS)
        q = np.tile(base, (SWEEP_POINTS, 1))
        q[:, j] = values
        q = q[ok(q)]
        covered = float(np.ptp(q[:, j])) if len(q) else 0.0
        if covered > best_span:
            best, best_span = q, covered
    if best is None or best_span < need:
        return None
    if both:  # back down through the gaps: every row approached from above, the same range
        down = 0.5 * (best[1:] + best[:-1])[::-1]
        best = np.vstack([best, down[ok(down)]])
    return best


def _back_and_forth(centre, j, limits, ok) -> np.ndarray | None:
    """Joint j moved up through a few steps, then down through the gaps: MIN_ROWS_PER_DIRECTION each way."""
    k = MIN_ROWS_PER_DIRECTION + 1
    offsets = (np.arange(k) - (k - 1) / 2) * APPROACH_STEP_RAD
    up = np.tile(centre, (k, 1))
    up[:, j] = np.clip(centre[j] + offsets, *limits[j])
    down = 0.5 * (up[1:] + up[:-1])[::-1]
    down = np.vstack([down, up[:1] - [APPROACH_STEP_RAD / 2 if i == j else 0.0 for i in range(len(centre))]])
    q = np.vstack([up, down])
    keep = ok(q)
    if np.sum(keep[:k]) < MIN_ROWS_PER_DIRECTION or np.sum(keep[k:]) < MIN_ROWS_PER_DIRECTION:
        return None
    return q[keep]


def _first_poses(df: pd.DataFrame, q_camp: np.ndarray, count: int, ok) -> np.ndarray:
    """The campaign's first `count` admissible poses, measured again at the end of the plan."""
    pose = pose_ids(df)
    _, first_row = np.unique(pose, return_index=True)
    q = q_camp[np.sort(first_row)]
    return q[ok(q)][:count]


# ---- the Bayesian T-optimal design of rows that separate rivals ----------------------------------------


def _woodbury_diag(cov: np.ndarray, A: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """diag of (C^-1 + A^T A)^-1 on `cols` for every candidate block A (M, 3, p), batched."""
    U = A @ cov  # (M, 3, p)
    W = np.linalg.inv(np.eye(3) + U @ A.transpose(0, 2, 1))  # (M, 3, 3)
    Uc = U[:, :, cols]  # (M, 3, k)
    return np.diag(cov)[cols] - np.einsum("mik,mij,mjk->mk", Uc, W, Uc)


def _woodbury_update(cov: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(C^-1 + A^T A)^-1 for rows A (r, p)."""
    U = A @ cov
    return cov - U.T @ np.linalg.solve(np.eye(len(A)) + U @ A.T, U)


def _pool(q_camp: np.ndarray, limits: np.ndarray, ok, rng) -> np.ndarray:
    """Candidate configurations near and around the campaign's (a campaign pose with every joint moved
    up to POOL_PERTURB_RAD, and uniform draws over its joint ranges widened by that), admissible only."""
    n = q_camp.shape[1]
    base = q_camp[rng.integers(0, len(q_camp), POOL_SIZE)]
    near = base + rng.uniform(-POOL_PERTURB_RAD, POOL_PERTURB_RAD, (POOL_SIZE, n))
    lo, hi = q_camp.min(axis=0) - POOL_PERTURB_RAD, q_camp.max(axis=0) + POOL_PERTURB_RAD
    wide = rng.uniform(lo, hi, (POOL_SIZE // 2, n))
    q = np.clip(np.vstack([near, wide]), limits[:, 0], limits[:, 1])
    return q[ok(q)]


def _separate(
    design: _Design, questions: list[Question], physics_q: np.ndarray, budget: int, first_block: int
):
    """Greedy Bayesian T-optimal rows for the statistical questions (see the module docstring), in blocks of
    `design.block_rows` (the first `first_block` long) that follow the greedy order."""
    df, model, sigma_m = design.df, design.model, design.sigma_m
    q_camp = design.q_camp
    camp = Problem.from_frame(model, df)
    rivals, skipped = [], []
    for qu in questions:
        r = rival_for(df, model, camp, qu)
        if r is None:
            skipped.append({"question": qu, "why": "its rival cannot be built on this campaign"})
        else:
            rivals.append(r)
    if not rivals:
        return [], [], skipped
    pool = _pool(q_camp, design.limits, design.ok, design.rng)
    if len(physics_q):  # the physics rows are measured too: count their information
        for r in rivals:
            r.cov = _woodbury_update(
                r.cov,
                scaled_rows(r.trial, unmeasured_problem(model, df, physics_q), r.keep, r.norms).reshape(
                    -1, r.cov.shape[0]
                ),
            )
    blocks = [scaled_rows(r.trial, unmeasured_problem(model, df, pool), r.keep, r.norms) for r in rivals]
    rivals, blocks, z_before = _decidable(rivals, blocks, budget, sigma_m, skipped)
    chosen, serves = _greedy_rows(rivals, blocks, len(pool), budget, sigma_m)
    order = _block_order(
        pool[chosen], physics_q[-1] if len(physics_q) else q_camp[-1], first_block, design.block_rows
    )
    rows = [(pool[chosen[i]], f"separate_{rivals[serves[i]].label}") for i in order]
    groups = _separation_groups(rivals, serves, z_before, sigma_m, skipped)
    return rows, groups, skipped


def _decidable(
    rivals: list[Rival], blocks: list[np.ndarray], budget: int, sigma_m: float, skipped: list[dict]
) -> tuple[list[Rival], list[np.ndarray], list[float]]:
    """The rivals (with their pool rows and evidence z before the plan) that the whole budget could decide;
    the others join `skipped` with the evidence they would reach."""
    z_before = [float(r.z(np.diag(r.cov)[r.cols], sigma_m)) for r in rivals]
    reach = [
        r.test_z_after(MAX_DESIGN_ROW_WORTH * budget)
        if r.z_test is not None
        else _solo_reach(r, A, budget, sigma_m)
        for r, A in zip(rivals, blocks, strict=True)
    ]
    for k in [k for k, z in enumerate(reach) if z < DECISIVE_Z]:  # the whole budget would not decide it
        skipped.append(
            {
                "question": rivals[k].question,
                "why": f"{budget} reachable rows would raise its evidence only to z {reach[k]:.3g} of {DECISIVE_Z}"
                + (
                    f" (its held-out test's, each row counted as {MAX_DESIGN_ROW_WORTH:g} campaign poses)"
                    if rivals[k].z_test is not None
                    else ""
                ),
                "evidence_z": z_before[k],
            }
        )
    keep_k = [k for k, z in enumerate(reach) if z >= DECISIVE_Z]
    return [rivals[k] for k in keep_k], [blocks[k] for k in keep_k], [z_before[k] for k in keep_k]


def _greedy_rows(
    rivals: list[Rival], blocks: list[np.ndarray], pool_size: int, budget: int, sigma_m: float
) -> tuple[list[int], list[int]]:
    """Pool rows chosen one at a time by their summed evidence gain over the questions still open, and the
    rival each serves most; each rival's covariance takes in every chosen row."""
    chosen: list[int] = []
    serves: list[int] = []
    available = np.ones(pool_size, bool)
    needed = [min(r.rows_needed(), budget) for r in rivals]
    for _ in range(budget):
        z_now = np.array([float(r.z(np.diag(r.cov)[r.cols], sigma_m)) for r in rivals])
        served = np.bincount(np.asarray(serves, int), minlength=len(rivals))
        open_ = [
            served[k] < needed[k] if r.z_test is not None else z_now[k] < DECISIVE_Z
            for k, r in enumerate(rivals)
        ]
        if not any(open_) or not available.any():
            break
        gains = np.zeros((len(rivals), pool_size))
        for k, (r, A) in enumerate(zip(rivals, blocks, strict=True)):
            if not open_[k]:
                continue
            z_new = r.z(_woodbury_diag(r.cov, A, r.cols), sigma_m)
            if r.z_test is not None:  # test-led: the design's gain ranks the poses, the count decides
                gains[k] = np.maximum(z_new - z_now[k], 1e-5)
            else:
                gains[k] = np.minimum(z_new, DECISIVE_Z) - min(z_now[k], DECISIVE_Z)
        total = np.where(available, gains.sum(axis=0), -np.inf)
        best = int(np.argmax(total))
        if total[best] <= 1e-6:  # nothing in the pool moves any open question: poses cannot decide them
            break
        chosen.append(best)
        serves.append(int(np.argmax(gains[:, best])))
        available[best] = False
        for r, A in zip(rivals, blocks, strict=True):
            r.cov = _woodbury_update(r.cov, A[best])
    return chosen, serves


def _separation_groups(
    rivals: list[Rival], serves: list[int], z_before: list[float], sigma_m: float, skipped: list[dict]
) -> list[dict]:
    """Each rival's group: the rows that serve it and its evidence before and after; a rival no row serves
    and still undecided joins `skipped`."""
    groups = []
    for k, r in enumerate(rivals):
        count = int(np.sum(np.asarray(serves) == k))
        z_after = float(r.z(np.diag(r.cov)[r.cols], sigma_m))
        if r.z_test is not None:  # test-led: its evidence is the held-out test's (`Rival.rows_needed`)
            z_before[k], z_after = r.z_test, r.test_z_after(count)
        if count == 0 and z_after < DECISIVE_Z:
            skipped.append(
                {"question": r.question, "why": "no reachable pose adds evidence", "evidence_z": z_after}
            )
            continue
        groups.append(
            {
                "purpose": f"separate_{r.label}",
                "rows": count,
                "question": r.question,
                "evidence_z_before": z_before[k],
                "evidence_z_after": z_after,
                "decisive_z": DECISIVE_Z,
            }
        )
    return groups


def _solo_reach(r: Rival, A: np.ndarray, budget: int, sigma_m: float) -> float:
    """The evidence z one question reaches if the whole budget went to it (greedy, stops at DECISIVE_Z)."""
    cov = r.cov
    used = np.zeros(len(A), bool)
    z = float(r.z(np.diag(cov)[r.cols], sigma_m))
    for _ in range(budget):
        if z >= DECISIVE_Z:
            break
        z_new = np.where(used, -np.inf, r.z(_woodbury_diag(cov, A, r.cols), sigma_m))
        best = int(np.argmax(z_new))
        used[best] = True
        cov = _woodbury_update(cov, A[best])
        z = float(z_new[best])
    return z


def _block_order(q: np.ndarray, start: np.ndarray, first: int, size: int) -> list[int]:
    """Rows `q` (in greedy choice order) cut into blocks (`first` rows, then `size` each), each toured by
    `_nearest_neighbour_order` from where the block before ended: every block boundary is a greedy prefix, so
    a round that stops after any block has measured the most informative rows it could."""
    out: list[int] = []
    cut = 0
    while cut < len(q):
        end = min(len(q), cut + (first if cut == 0 else size))
        out += [cut + i for i in _nearest_neighbour_order(q[cut:end], q[out[-1]] if out else start)]
        cut = end
    return out


def _nearest_neighbour_order(q: np.ndarray, start: np.ndarray) -> list[int]:
    """A short joint-space tour through `q` from `start` (greedy nearest neighbour, largest joint move)."""
    left = list(range(len(q)))
    out: list[int] = []
    here = np.asarray(start, dtype=float)
    while left:
        largest_move = np.max(np.abs(q[left] - here), axis=1)
        k = left.pop(int(np.argmin(largest_move)))  # the first of equals, as min() over `left` gives
        out.append(k)
        here = q[k]
    return out
