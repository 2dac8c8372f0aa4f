"""Benchmark: emScon driver round-trip overhead per measurement beyond the configured measurement time.

The fake tracker runs in a separate process (its own interpreter, so no GIL sharing with the driver) and
waits the measurement time per shot; everything above that is driver + protocol + fake overhead. The
"tcp-bare" rows measure the same with a bare socket client: the difference to "tcp" is the driver's share.
Run: PYTHONPATH=. python benchmarks/tracker.py [--shots 200]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import socket
import statistics
import time

from drivers import emscon_codec as codec
from drivers.emscon import EmsconConfig, EmsconTracker


def _serve(conn, seed: int) -> None:
    from fakes.cell import SimCellConfig, SimulatedCell
    from fakes.emscon_server import EmsconServer, EmsconServerConfig

    async def main() -> None:
        cell = SimulatedCell(SimCellConfig(seed=seed))
        server = EmsconServer(cell, config=EmsconServerConfig(initialized=True, initial_lock_smr=2))
        await server.start()
        pty = await server.open_pty()
        conn.send((server.url, pty))
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, conn.recv)  # until the parent says stop
        await server.close()

    asyncio.run(main())


def _bench_raw(url: str, meas_time_s: float, shots: int) -> dict:
    """Baseline: a bare socket client (no driver) measuring the same way; what remains is fake + TCP."""
    host, port = url.removeprefix("socket://").rsplit(":", 1)
    with EmsconTracker(EmsconConfig(url=url, meas_time_s=meas_time_s)):
        pass  # leaves the server in our units and measurement time
    sock = socket.create_connection((host, int(port)))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    splitter = codec.FrameSplitter()
    start_cmd = codec.pack_command(codec.Command.START_MEASUREMENT)
    per_shot = []
    try:
        for _ in range(shots + 1):
            start = time.perf_counter()
            sock.sendall(start_cmd)
            while True:
                packets = splitter.feed(sock.recv(4096))
                if any(codec.HEADER.unpack_from(p)[1] == codec.DataType.SINGLE_MEAS_RESULT for p in packets):
                    break
            per_shot.append(time.perf_counter() - start)
    finally:
        sock.close()
    return _summary(per_shot[1:], meas_time_s)


def _summary(per_shot: list[float], meas_time_s: float) -> dict:
    overhead = sorted(t - meas_time_s for t in per_shot)
    return {
        "overhead_mean_ms": 1e3 * statistics.fmean(overhead),
        "overhead_p50_ms": 1e3 * overhead[len(overhead) // 2],
        "overhead_p95_ms": 1e3 * overhead[int(0.95 * (len(overhead) - 1))],
    }


def _bench(url: str, meas_time_s: float, shots: int) -> dict:
    with EmsconTracker(EmsconConfig(url=url, meas_time_s=meas_time_s)) as tracker:
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
    return {**_summary(per_shot, meas_time_s), "command_rtt_ms": 1e3 * state_s}


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
        runs = [("tcp", tcp_url, _bench), ("pty", pty_path, _bench), ("tcp-bare", tcp_url, _bench_raw)]
        for name, url, bench in runs:
            for meas_time_s in (0.01, 0.1):
                shots = args.shots if meas_time_s < 0.05 else max(10, args.shots // 10)
                r = bench(url, meas_time_s, shots)
                print(
                    f"{name:<10} {meas_time_s * 1e3:>12.0f} {shots:>6} {r['overhead_mean_ms']:>17.2f} "
                    f"{r['overhead_p50_ms']:>16.2f} {r['overhead_p95_ms']:>16.2f} {r.get('command_rtt_ms', float('nan')):>15.2f}"
                )
    finally:
        parent.send("stop")
        proc.join(5)
        if proc.is_alive():
            proc.terminate()


if __name__ == "__main__":
    main()
