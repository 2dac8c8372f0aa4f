"""The active diagnosis loop on simulated cells: diagnose, propose at most 100 poses, measure them on the same
cell, diagnose again (at most 2 rounds). Effects are not declared to the diagnosis. Each later diagnosis is
given the effects the one before named (run_diagnosis' previous_effects), as hil's active_loop procedure does;
the random and D-optimal columns' diagnoses are given the first diagnosis' effects alike.

Run:  PYTHONPATH=. python benchmarks/active_loop.py [--seeds 0-2] [--cases clean,gravity_cyclic1] [--quick]

Per case and seed: the effects named after each round, the rounds proposed, the poses the rounds measured
(sequential: a round is measured in blocks of --block poses, the longer campaign diagnosed after each, and
rows whose questions that diagnosis decided are not measured, as hil's active_loop procedure does), the
validation RMS of the final model against a model that carries the true effects (goal <= 1.1x), and how many
extra poses each way needed to name the right effect: the proposed plan, random reachable poses, a D-optimal
plan for the geometric model alone (greedy log-det on the same pool); '-' = not named within the budget.

The comparison is at one granularity: every way is diagnosed after each block of --block poses, and its
count is the poses measured up to the first block after which the diagnosis names every true effect. The
plan stops where its own rule says (at most 2 rounds of at most 100 poses, fewer when its questions are
decided); random and D-optimal poses go on, block after block, up to 2 x 100 poses.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

CASES = {
    "clean": {"config": {"compliance": False}, "named": set(), "families": ()},
    "gravity_cyclic1": {
        "config": {"cyclic": True, "cyclic_joints": (1,)},
        "named": {("cyclic", 1), ("gravity_compliance", 2)},
        "families": ("gravity_compliance", "cyclic"),
    },
    "two_on_joint2": {
        "config": {"cyclic": True, "cyclic_joints": (2,), "backlash": True, "backlash_joints": (2,)},
        "named": {("cyclic", 2), ("backlash", 2)},
        "families": ("gravity_compliance", "cyclic", "backlash"),
    },
}
MAX_ROWS = 100


def _cell(case: str, seed: int):
    from fakes.cell import SimCellConfig, SimulatedCell

    return SimulatedCell(SimCellConfig(robot="ur10", seed=seed, **CASES[case]["config"]))


def _rms_mm(model, df) -> float:
    err = model.predict(df) - df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))) * 1000)


def _named(report) -> set:
    return {(e["name"], e["joint"]) for e in report.effects_added}


def run_case(case: str, seed: int, compare: bool, block: int) -> dict:
    from calib_data import true_effect_model
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from hil.analysis.design.plan import propose
    from hil.analysis.design.rounds import block_record, plan_blocks, still_to_measure
    from hil.analysis.diagnosis.pipeline import run_diagnosis

    cell = _cell(case, seed)
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=seed, keep_singular=False))
    first = train
    val = simulate_campaign(cell, held_out_joints(cell, 100, seed=seed + 1))
    want = CASES[case]["named"]
    rounds, found, t0 = 0, [], time.perf_counter()
    report = run_diagnosis(train, "ur10")
    found.append(_named(report))
    extra_plan, planned = None, 0
    for _ in range(2):
        sigma = float(np.sqrt(np.mean(report.noise.sigma_axis_m**2)))
        plan = propose(train, report.model, report.undecided, MAX_ROWS, sigma, seed=seed, block_rows=block)
        if not plan.purpose:
            break
        rounds += 1
        planned += len(plan.purpose)
        before, todo = report, np.ones(len(plan.purpose), bool)
        for k, idx in enumerate(plan_blocks(len(plan.purpose), block), start=1):
            idx = idx[todo[idx]]
            if not len(idx):
                continue
            train = pd.concat([train, simulate_campaign(cell, plan.q[idx])], ignore_index=True)
            report = run_diagnosis(train, "ur10", previous_effects=before.effects_added)
            if extra_plan is None and want and want <= _named(report):
                extra_plan = len(train) - len(first)
            todo &= still_to_measure(plan.purpose, block_record(k, 0, plan.groups, report))
            if not todo[idx[-1] + 1 :].any():
                break
        found.append(_named(report))
    if want and want <= found[0]:
        extra_plan = 0
    truth = true_effect_model(train, "ur10", CASES[case]["families"]) if CASES[case]["families"] else None
    final = _rms_mm(report.model, val)
    row = {
        "case": case,
        "seed": seed,
        "poses": len(first),
        "round0": _fmt(found[0]),
        "final": _fmt(found[-1]),
        "rounds": rounds,
        "named": want <= found[-1] and (bool(want) or not found[-1]),
        "val_mm": final,
        "ratio": final / _rms_mm(truth, val) if truth is not None else float("nan"),
        "plan_extra": extra_plan,
        "measured": f"{len(train) - len(first)}/{planned}",
        "time_s": time.perf_counter() - t0,
    }
    if compare and want:
        start = [{"name": n, "joint": j} for n, j in sorted(found[0], key=str)]
        for how in ("random", "dopt"):
            row[f"{how}_extra"] = (
                0 if want <= found[0] else _extra_needed(cell, first, want, how, seed, start, block)
            )
    return row


def _extra_needed(cell, first, want, how: str, seed: int, start: list[dict], block: int) -> int | None:
    """Extra poses (in blocks of `block`, up to 2 x MAX_ROWS) of random or D-optimal choice that name `want`;
    the longer campaign is diagnosed after each block as a round of the loop is (the first diagnosis' effects
    `start` known). The blocks are measured one after the other on the cell, as a round's are."""
    from fakes.campaign import simulate_campaign
    from hil.analysis.diagnosis.pipeline import run_diagnosis
    from hil.data.dataset import joints_rad

    rng = np.random.default_rng([seed, 11])
    q0 = joints_rad(first)
    lo, hi = q0.min(axis=0) - np.deg2rad(30), q0.max(axis=0) + np.deg2rad(30)
    pool = rng.uniform(lo, hi, (3000, 6))
    order = rng.permutation(len(pool)) if how == "random" else _d_optimal(first, pool, 2 * MAX_ROWS)
    longer = first
    for n in range(block, 2 * MAX_ROWS + 1, block):
        more = simulate_campaign(cell, pool[order[n - block : n]])
        longer = pd.concat([longer, more], ignore_index=True)
        if want <= _named(run_diagnosis(longer, "ur10", previous_effects=start)):
            return n
    return None


def _d_optimal(first, pool, count: int) -> np.ndarray:
    """Greedy D-optimal order of pool poses for the geometric model alone (log det of its information)."""
    from hil.analysis.calibration.solve import Problem, calibrate, flatten_jacobian, identify
    from hil.analysis.design.plan import _woodbury_update
    from hil.analysis.diagnosis.evidence import unmeasured_problem

    model = calibrate(first, "ur10", "ridge").model
    camp = Problem.from_frame(model, first)
    keep = identify(model, camp).keep_mask
    J = flatten_jacobian(camp.evaluate(model)[1][:, :3])[:, keep]
    norms = np.linalg.norm(J, axis=0)
    cov = np.linalg.inv((J / norms).T @ (J / norms) + 1e-9 * np.eye(J.shape[1]))
    A = camp_rows = unmeasured_problem(model, first, pool).evaluate(model)[1][:, :3, keep] / norms
    del camp_rows
    chosen: list[int] = []
    for _ in range(count):
        # det gain of adding a 3-row block: det(I + A C A^T)
        gain = np.linalg.slogdet(np.eye(3) + A @ cov @ A.transpose(0, 2, 1))[1]
        gain[chosen] = -np.inf
        k = int(np.argmax(gain))
        chosen.append(k)
        cov = _woodbury_update(cov, A[k])
    return np.array(chosen)


def _fmt(named: set) -> str:
    return ", ".join(f"{n} j{j}" if j else n for n, j in sorted(named, key=str)) or "none"


def main() -> None:
    from hil.analysis.design.plan import BLOCK_ROWS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-2", help="a range 'a-b' or a list '0,3,5'")
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--quick", action="store_true", help="skip the random / D-optimal comparison")
    parser.add_argument(
        "--block", type=int, default=BLOCK_ROWS, help="poses between two diagnoses (every way alike)"
    )
    args = parser.parse_args()
    if "-" in args.seeds:
        a, b = (int(x) for x in args.seeds.split("-"))
        seeds = list(range(a, b + 1))
    else:
        seeds = [int(x) for x in args.seeds.split(",")]
    head = f"{'case':<16}{'seed':>4}{'poses':>6}  {'round 0':<34}{'final':<46}{'rounds':>6}{'named':>6}"
    head += f"{'measured':>9}{'val mm':>8}{'x true':>7}{'plan+':>6}{'rand+':>6}{'D-opt+':>7}{'s':>6}"
    print(head)
    for case in args.cases.split(","):
        for seed in seeds:
            r = run_case(case, seed, not args.quick, args.block)

            def n(key: str, r: dict = r) -> str:
                v = r.get(key, "")
                return "-" if v is None else str(v)

            print(
                f"{r['case']:<16}{r['seed']:>4}{r['poses']:>6}  {r['round0']:<34}{r['final']:<46}{r['rounds']:>6}"
                f"{'yes' if r['named'] else 'NO':>6}{r['measured']:>9}{r['val_mm']:>8.4f}{r['ratio']:>7.2f}{n('plan_extra'):>6}"
                f"{n('random_extra'):>6}{n('dopt_extra'):>7}{r['time_s']:>6.0f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
