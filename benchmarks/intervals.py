"""Prediction intervals (hil.model.intervals): coverage and sharpness of the 95 % intervals per simulated
cell and across the public UR10 campaigns.

Run:  PYTHONPATH=. python benchmarks/intervals.py [--seeds 0-2] [--kinds clean,thermal,...] [--real DATA_DIR]
      (or set HIL_REAL_DATA=DATA_DIR, see benchmarks/real_campaigns.py; without it the real part is skipped)

Simulated cells: a UR10 whose hall warms (its links grow only in `thermal`), a 150 mm grid visited in raster
order, then 100 random validation poses measured once the arm is `WARMER_K` warmer than any training row.
Kinds: clean (no undeclared effect; the links do not grow), thermal (aluminium growth), cyclic (joint 1's
once-per-turn error), backlash (joints 1-3), tracker_air (the tracker's station reads air 3 K off: a scale).
Real: trained on one campaign, its intervals on the other with the base re-registered (the diagnosis'
default for another placement), both ways; the figure as it comes (the method is fixed on the simulated
cells and on held-out blocks of one campaign).

Goals (95 %): pooled simulated coverage 92-98 %, no cell below 85 %; each real direction at least 90 %;
median interval at most 2.5x the RMS error of the same predictions on the same points.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

PROBABILITY = 0.95
WARMER_K = 2.0
KINDS = {
    "clean": {"thermal": True, "expansion_per_k": 0.0},
    "thermal": {"thermal": True},
    "cyclic": {"thermal": True, "expansion_per_k": 0.0, "cyclic": True, "cyclic_joints": (1,)},
    "backlash": {"thermal": True, "expansion_per_k": 0.0, "backlash": True},
    "tracker_air": {"thermal": True, "expansion_per_k": 0.0, "tracker_air_c": 23.0},
}


def simulated_cell(kind: str, seed: int):
    """(training, validation) frames of one simulated cell."""
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, **KINDS[kind]))
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=seed))
    hottest = float(train["temperature_c"].max())
    while cell.structure_temperature_c() < hottest + WARMER_K:
        cell.advance_time(60.0)
    return train, simulate_campaign(cell, held_out_joints(cell, 100, seed=seed + 1))


def coverage_row(model, df) -> tuple[float, float, float, int]:
    """(covered share, median interval mm, RMS error mm, rows) of the model's intervals on df."""
    from hil.data.dataset import points_m
    from hil.model.prediction_intervals import prediction_intervals

    iv = prediction_intervals(model, df, PROBABILITY)
    err = np.linalg.norm(model.predict(df) - points_m(df), axis=1)
    return (
        float(np.mean(err <= iv.radius_m)),
        float(np.median(iv.radius_mm)),
        float(np.sqrt(np.mean(err**2)) * 1e3),
        len(err),
    )


def print_row(name: str, cov: float, med: float, rms: float, n: int, extra: str = "") -> None:
    print(f"{name:<22}{n:>5}{cov * 100:>9.1f}{med:>10.4f}{rms:>9.4f}{med / rms:>7.2f}  {extra}")


def header() -> None:
    print(f"{'cell':<22}{'rows':>5}{'cover %':>9}{'med mm':>10}{'RMS mm':>9}{'sharp':>7}")


def simulated(kinds: list[str], seeds: list[int]) -> None:
    from hil.analysis.diagnosis.pipeline import run_diagnosis

    header()
    hits, total, worst = 0.0, 0, 1.0
    for kind in kinds:
        for seed in seeds:
            t0 = time.perf_counter()
            train, val = simulated_cell(kind, seed)
            report = run_diagnosis(train, "ur10", df_validate=val)
            cov, med, rms, n = coverage_row(report.model, val)
            hits += cov * n
            total += n
            worst = min(worst, cov)
            sp = report.model.spread
            extra = f"s0 {np.sqrt(sp.s0_m2) * 1e3:.4f} mm, k {sp.factor(PROBABILITY):.2f} ({time.perf_counter() - t0:.0f} s)"
            print_row(f"{kind} {seed}", cov, med, rms, n, extra)
    print(
        f"pooled simulated coverage {hits / total * 100:.1f} % over {total} rows; lowest cell {worst * 100:.1f} %"
    )


def real(data_dir: Path) -> None:
    from real_campaigns import read_raw, to_contract

    from hil.analysis.calibration.solve import reregister
    from hil.analysis.diagnosis.pipeline import run_diagnosis

    data = {s: to_contract(read_raw(data_dir, s)) for s in ("B", "C")}
    header()
    for train, val in (("C", "B"), ("B", "C")):
        t0 = time.perf_counter()
        report = run_diagnosis(data[train], "ur10")
        moved = reregister(report.model, data[val])
        cov, med, rms, n = coverage_row(moved, data[val])
        held = report.intervals[0]
        print_row(
            f"trained {train}, on {val}",
            cov,
            med,
            rms,
            n,
            f"held-out rows {held['rows']} ({time.perf_counter() - t0:.0f} s)",
        )


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = map(int, text.split("-"))
        return list(range(lo, hi + 1))
    return [int(s) for s in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-2")
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument(
        "--real", default=os.environ.get("HIL_REAL_DATA"), help="the public campaigns' repository"
    )
    parser.add_argument("--real-only", action="store_true")
    args = parser.parse_args()
    if not args.real_only:
        simulated(args.kinds.split(","), _seeds(args.seeds))
    if args.real:
        real(Path(args.real))
    else:
        print("real campaigns: no data directory given (--real or HIL_REAL_DATA); skipped")


if __name__ == "__main__":
    main()
