"""A cell's writing loop, alone in a process: the shared store's crash tests kill it, lose its server and run
it again. `python tests/pg_writer.py URL STEP N`: records points STEP/p0..p{N-1} of `grid_sampling` into the
campaign URL names, skipping those already recorded (the runner's resume rule), each committed before the next.
Prints `done MAX_INSERT_S` at the end; exits 3 with the store's message when the server is lost. With a fourth
argument `--on-go`, it opens the campaign, prints `ready` and waits for a line on its input before recording
(two writers then start at the same moment)."""

from __future__ import annotations

import sys
import time

import numpy as np

from hil.data.pg_errors import CampaignStoreLost
from hil.data.pg_store import PgCampaignStore
from hil.data.store import MeasurementRecord


def record(step: str, i: int) -> MeasurementRecord:
    """Point i of `step`: its values carry i and the step, so a mixed-up row is seen."""
    tag = sum(map(ord, step))
    return MeasurementRecord(
        procedure="grid_sampling", step=step, point_id=f"p{i}", q_target_rad=np.full(6, i * 1e-3),
        q_rad=np.full(6, i * 1e-3), T_base_flange=np.eye(4), p_tracker_m=np.array([i, tag, 1.0]),
        spread_m=np.zeros(3), std_m=np.zeros(3), shots=10, rejected_shots=(), smr=1, location="nest1",
        temperature_c=20.0, pressure_hpa=1013.0, humidity_pct=40.0, timestamp_s=1.7e9 + i,
    )  # fmt: skip


def main(url: str, step: str, n: int, on_go: bool) -> int:
    slowest = 0.0
    try:
        with PgCampaignStore(url) as store:
            if on_go:
                print("ready", flush=True)
                sys.stdin.readline()
            for i in range(n):
                if store.has_measurement("grid_sampling", step, f"p{i}"):
                    continue
                started = time.perf_counter()
                store.record_measurement(record(step, i))
                slowest = max(slowest, time.perf_counter() - started)
                print(i, flush=True)
    except CampaignStoreLost as exc:
        print(exc.message, file=sys.stderr, flush=True)
        return 3
    print(f"done {slowest:.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:] == ["--on-go"]))
