"""Benchmark: emScon driver round-trip overhead per measurement beyond the configured measurement time.

The fake tracker runs in a separate process (its own interpreter, so no GIL sharing with the driver) and
waits exactly the measurement time per shot; everything above that is driver + protocol + fake overhead.
Run: PYTHONPATH=. python benchmarks/tracker.py [--shots 200]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import time

from drivers.emscon import EmsconTracker


def _serve(conn, seed: int) -> None:
    from fakes.cell import CellConfig, SimulatedCell
    from fakes.emscon_server import EmsconServer, EmsconServerConfig

    async def main() -> None:
        cell = SimulatedCell(CellConfig(seed=seed))
        server = EmsconServer(cell, config=EmsconServerConfig(initialized=True, initial_lock_smr=2))
        await server.start()
        pty = await server.open_pty()
        conn.send((server.url, pty))
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, conn.recv)  # until the parent says stop
        await server.close()

    asyncio.run(main())


def _bench(url: str, meas_time_s: float, shots: int) -> dict:
    with EmsconTracker(url=url, meas_time_s=meas_time_s) as tracker:
        tracker.measure()  # warm-up
        per_shot = []
        for _ in range(shots):
            start = time.perf_counter()
            tracker.measure()
            per_shot.append(time.perf_counter() - start)
        start = time.perf_counter()
        for _ in range(shots):
            tracker.state()  # GetSystemStatus + GetMeasurementStatusInfo: two plain round trips
        state_s = (time.perf_counter() - start) / shots / 2
    overhead = sorted(t - meas_time_s for t in per_shot)
    return {
        "overhead_mean_ms": 1e3 * statistics.fmean(overhead),
        "overhead_p50_ms": 1e3 * overhead[len(overhead) // 2],
        "overhead_p95_ms": 1e3 * overhead[int(0.95 * (len(overhead) - 1))],
        "command_rtt_ms": 1e3 * state_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shots", type=int, default=200)
    args = parser.parse_args()
    parent, child = mp.Pipe()
    proc = mp.get_context("spawn").Process(target=_serve, args=(child, 0), daemon=True)
    proc.start()
    try:
        tcp_url, pty_path = parent.recv()
        print(
            f"{'transport':<10} {'meas_time_ms':>12} {'shots':>6} {'overhead_mean_ms':>17} "
            f"{'overhead_p50_ms':>16} {'overhead_p95_ms':>16} {'command_rtt_ms':>15}"
        )
        for name, url in (("tcp", tcp_url), ("pty", pty_path)):
            for meas_time_s in (0.01, 0.1):
                shots = args.shots if meas_time_s < 0.05 else max(10, args.shots // 10)
                r = _bench(url, meas_time_s, shots)
                print(
                    f"{name:<10} {meas_time_s * 1e3:>12.0f} {shots:>6} {r['overhead_mean_ms']:>17.2f} "
                    f"{r['overhead_p50_ms']:>16.2f} {r['overhead_p95_ms']:>16.2f} {r['command_rtt_ms']:>15.2f}"
                )
    finally:
        parent.send("stop")
        proc.join(5)
        if proc.is_alive():
            proc.terminate()


if __name__ == "__main__":
    main()
