"""Benchmark of the measurement runner, part one: the campaign store.

Times, on a campaign file in /tmp (WAL, synchronous=FULL, one commit per point as a session does):
  1. record_measurement per call (durable on return);
  2. has_measurement per call (the resume check before every point), for recorded and unknown points;
  3. reading everything back: measurements() and campaign_dataset().

Run: PYTHONPATH=. python benchmarks/runner.py [--points 2000]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.store import CampaignStore, MeasurementRecord, campaign_dataset  # noqa: E402


def make_records(n: int, seed: int = 0) -> list[MeasurementRecord]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        T = np.eye(4)
        T[:3, 3] = rng.normal(size=3)
        q = rng.uniform(-3, 3, 6)
        out.append(
            MeasurementRecord(
                procedure="grid_sampling",
                step="grid",
                point_id=f"g{i:05d}",
                q_target_rad=q,
                q_rad=q + rng.normal(0, 1e-5, 6),
                T_base_flange=T,
                p_tracker_m=rng.normal(size=3),
                spread_m=rng.uniform(0, 1e-5, 3),
                std_m=rng.uniform(0, 1e-5, 3),
                shots=5,
                rejected_shots=(),
                smr=1,
                location="nest1",
                temperature_c=21.0,
                pressure_hpa=1012.0,
                humidity_pct=40.0,
                timestamp_s=1.7e9 + i,
                extra={"attempts": 1, "order": "travel"},
            )
        )
    return out


def timed(calls) -> np.ndarray:
    """Seconds of each call of the zero-argument callables."""
    out = np.empty(len(calls))
    for i, call in enumerate(calls):
        t = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2000)
    args = parser.parse_args()
    records = make_records(args.points)
    folder = Path(tempfile.mkdtemp(prefix="hil-bench-store-", dir="/tmp"))
    try:
        with CampaignStore(folder / "bench.hilc") as store:
            rows = {
                "record_measurement (commit)": timed(
                    [lambda r=r: store.record_measurement(r) for r in records]
                ),
                "has_measurement (recorded)": timed(
                    [lambda r=r: store.has_measurement(r.procedure, r.step, r.point_id) for r in records]
                ),
                "has_measurement (unknown)": timed(
                    [
                        lambda i=i: store.has_measurement("grid_sampling", "grid", f"x{i}")
                        for i in range(args.points)
                    ]
                ),
            }
            reads = {
                f"measurements() of {args.points}": timed([store.measurements] * 5),
                f"campaign_dataset() of {args.points}": timed([lambda: campaign_dataset(store)] * 5),
            }
        size_kb = (folder / "bench.hilc").stat().st_size / 1024
    finally:
        shutil.rmtree(folder)
    print(f"campaign store, {args.points} points, file in /tmp ({size_kb:.0f} KiB after close)")
    print(f"{'operation':<34}{'calls':>7}{'median ms':>11}{'p99 ms':>9}{'max ms':>9}")
    for name, t in {**rows, **reads}.items():
        ms = t * 1000
        print(f"{name:<34}{len(ms):>7}{np.median(ms):>11.3f}{np.percentile(ms, 99):>9.3f}{ms.max():>9.3f}")


if __name__ == "__main__":
    main()
