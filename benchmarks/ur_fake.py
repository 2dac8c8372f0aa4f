"""Benchmark of the fake UR controller under the real ur-rtde client.

Starts `hil sim`, connects one RTDEReceiveInterface and one RTDEControlInterface (the load), then
  1. RTDE period statistics: the controller's own tick periods (from the cell's clock) and the
     inter-arrival times of data packages seen by a raw RTDE observer socket;
  2. the handshake latency of blocking commands (getForwardKinematics, isSteady): ready -> command
     -> done -> clear, i.e. about two controller cycles.

Run: PYTHONPATH=. python benchmarks/ur_fake.py [--personality eseries|cb3] [--seconds 5]
"""

from __future__ import annotations

import argparse
import os
import socket
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fakes.launch import sim_cell  # noqa: E402
from fakes.rtde_wire import frame  # noqa: E402


def observe_rtde(host: str, frequency: float, seconds: float, out: list[float]) -> None:
    """A raw RTDE client: subscribe to the timestamp at `frequency` and record package arrival times."""
    with socket.create_connection((host, 30004), timeout=5) as sock:

        def request(kind: str, payload: bytes = b"") -> None:
            sock.sendall(frame(ord(kind), payload))

        def message() -> tuple[int, bytes]:
            header = _exact(sock, 3)
            size, kind = struct.unpack(">HB", header)
            return kind, _exact(sock, size - 3)

        request("V", struct.pack(">H", 2))
        message()
        request("O", struct.pack(">d", frequency) + b"timestamp,")
        message()
        request("S")
        message()
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            kind, _ = message()
            if kind == ord("U"):
                out.append(time.perf_counter())
        request("P")


def _exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("RTDE closed")
        data += chunk
    return data


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def period_row(name: str, periods_ms: np.ndarray, nominal_ms: float) -> str:
    late = int(np.sum(periods_ms > 1.5 * nominal_ms))
    return (
        f"| {name} | {len(periods_ms)} | {np.mean(periods_ms):.3f} | {np.percentile(periods_ms, 50):.3f} | "
        f"{np.percentile(periods_ms, 99):.3f} | {periods_ms.max():.2f} | {late} ({100 * late / len(periods_ms):.2f} %) |"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--personality", choices=["eseries", "cb3"], default="eseries")
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--commands", type=int, default=300)
    args = parser.parse_args()
    import rtde_control
    import rtde_receive

    robot = "ur10e" if args.personality == "eseries" else "ur10"
    with sim_cell(robot=robot, personality=args.personality) as cell:
        frequency = cell.info["robot"]["frequency_hz"]
        nominal_ms = 1000.0 / frequency
        rx = rtde_receive.RTDEReceiveInterface(cell.host)
        ctrl = rtde_control.RTDEControlInterface(cell.host)
        try:
            # 1. periods while both clients are connected and streaming
            cell.control.call("clock.stats", reset=True)
            cpu_before, wall_before = _cpu_seconds(cell.process.pid), time.perf_counter()
            arrivals: list[float] = []
            observer = threading.Thread(
                target=observe_rtde, args=(cell.host, frequency, args.seconds, arrivals)
            )
            observer.start()
            observer.join()
            sim_cpu = (_cpu_seconds(cell.process.pid) - cpu_before) / (time.perf_counter() - wall_before)
            server = cell.control.call("clock.stats")
            server_periods = np.array(cell.control.call("clock.periods")) * 1000.0
            client_periods = np.diff(np.array(arrivals)) * 1000.0

            # 2. blocking-command handshake latency
            latencies = {}
            for name, call in (
                ("getForwardKinematics()", ctrl.getForwardKinematics),
                ("isSteady()", ctrl.isSteady),
            ):
                samples = []
                for _ in range(args.commands):
                    t0 = time.perf_counter()
                    call()
                    samples.append((time.perf_counter() - t0) * 1000.0)
                latencies[name] = np.array(samples)
        finally:
            ctrl.disconnect()
            rx.disconnect()

    print(
        f"# fake UR controller, {args.personality} at {frequency:.0f} Hz (nominal period {nominal_ms:.1f} ms)"
    )
    print("# load: one RTDEReceiveInterface + one RTDEControlInterface; late = period > 1.5 x nominal\n")
    print("| stream | periods | mean ms | p50 ms | p99 ms | max ms | late |")
    print("|---|---|---|---|---|---|---|")
    print(period_row("controller ticks (server clock)", server_periods, nominal_ms))
    print(period_row("data packages at an observer client", client_periods, nominal_ms))
    print(
        f"\nserver clock: {server['late_ticks']} ticks started > half a period late out of {server['ticks']}"
    )
    print(f"hil sim process CPU while streaming: {100 * sim_cpu:.0f} % of one core; load average {_load()}\n")
    print("| blocking command | calls | p50 ms | p90 ms | p99 ms | max ms | cycles (p50) |")
    print("|---|---|---|---|---|---|---|")
    for name, samples in latencies.items():
        print(
            f"| {name} | {len(samples)} | {np.percentile(samples, 50):.2f} | {np.percentile(samples, 90):.2f} | "
            f"{np.percentile(samples, 99):.2f} | {samples.max():.2f} | {np.percentile(samples, 50) / nominal_ms:.1f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
