"""Benchmark of the fake UR controller under the real ur-rtde client.

Starts `hil sim`, connects one RTDEReceiveInterface and one RTDEControlInterface (the load), then
  1. RTDE period statistics: the controller's own tick periods (from the cell's clock) and the
     inter-arrival times of data packages seen by a raw RTDE observer socket;
  2. the handshake latency of blocking commands (getForwardKinematics, isSteady, and commands the fake
     acknowledges without modelling them): ready -> command -> done -> clear, about two controller cycles;
then, through the UR driver (drivers/ur.py) on a second cell at time scale 10,
  3. how fast each injected fault surfaces as the driver's typed error, and how long recover() takes;
  4. how fast connecting fails to an address with no controller and to a powered-off arm.

Run: PYTHONPATH=. python benchmarks/ur_fake.py [--personality eseries|cb3] [--seconds 5] [--fault-repeats 3]
"""

from __future__ import annotations

import argparse
import logging
import os
import socket
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.ur import URConfig, URRobot  # noqa: E402
from fakes.launch import random_loopback_host, sim_cell  # noqa: E402
from fakes.rtde_wire import frame  # noqa: E402
from hil.instruments.robot import RobotError  # noqa: E402

HOME = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
FAULTS = {  # kind -> options, as in tests/test_ur_driver.py
    "protective_stop": {},
    "emergency_stop": {},
    "stop_script": {},
    "drop_rtde": {"duration_s": 1.0},
    "stall": {"duration_s": 1.0},
    "latency": {"duration_s": 1.0},
}


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
    parser.add_argument("--fault-repeats", type=int, default=3)
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
                ("setPayload()", lambda: ctrl.setPayload(1.0, [0.0, 0.0, 0.05])),
                ("zeroFtSensor() (not modelled)", ctrl.zeroFtSensor),
                ("endTeachMode() (not modelled)", ctrl.endTeachMode),
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
    logging.getLogger("drivers.ur").setLevel(logging.ERROR)  # its retry warnings would cut into the tables
    faults = fault_latencies(robot, args.personality, args.fault_repeats)
    print(
        f"\n# UR driver, one cell at time scale 10: move 1.2 rad at 0.5 rad/s, fault at 30 % ({args.fault_repeats} each)"
    )
    print(
        "# fault -> error: simulated time from the fault firing to just after the error, in wall ms (an upper"
    )
    print("# bound: it includes one control-channel round trip)\n")
    print(
        "| fault | typed error | fault -> error ms (median, max) | failing move_joints s (max) | recover() s (max) |"
    )
    print("|---|---|---|---|---|")
    for kind, rows in faults.items():
        errors = sorted({row[0] for row in rows})
        after_ms = np.array([row[1] for row in rows])
        print(
            f"| {kind} | {', '.join(errors)} | {np.median(after_ms):.0f}, {after_ms.max():.0f} | "
            f"{max(row[2] for row in rows):.2f} | {max(row[3] for row in rows):.2f} |"
        )
    print("\n| connect to | error | seconds |")
    print("|---|---|---|")
    for what, error, seconds in connect_refusals(robot):
        print(f"| {what} | {error} | {seconds:.2f} |")
    return 0


def fault_latencies(
    robot: str, personality: str, repeats: int
) -> dict[str, list[tuple[str, float, float, float]]]:
    """Per fault kind: (error type, fault -> error wall ms, failing move s, recover s) for each repeat."""
    time_scale = 10.0
    far = [HOME[0] + 1.2, *HOME[1:]]
    results: dict[str, list[tuple[str, float, float, float]]] = {kind: [] for kind in FAULTS}
    with sim_cell(robot=robot, personality=personality, time_scale=time_scale) as cell:
        driver = URRobot(URConfig(cell.host))
        try:
            for _ in range(repeats):
                for kind, options in FAULTS.items():
                    driver.move_joints(np.array(HOME))
                    cell.control.call("robot.fault", kind=kind, at_move=1, fraction=0.3, **options)
                    started = time.perf_counter()
                    try:
                        driver.move_joints(np.array(far), speed=0.5)
                        raise RuntimeError(f"the {kind} fault gave no error")
                    except RobotError as exc:
                        error, failed = type(exc).__name__, time.perf_counter() - started
                    now_s = cell.control.call("ping")["time_s"]
                    fired_s = cell.control.call("robot.state")["faults"][-1]["time_s"]
                    started = time.perf_counter()
                    cell.control.call("robot.clear_faults")
                    cell.control.call("robot.release_estop")
                    driver.recover()
                    recovered = time.perf_counter() - started
                    results[kind].append((error, (now_s - fired_s) / time_scale * 1000.0, failed, recovered))
        finally:
            driver.close()
    return results


def connect_refusals(robot: str) -> list[tuple[str, str, float]]:
    """Time for URRobot() to fail: no controller at the address (2 attempts, 0.5 s probe timeout), and an arm
    that is powered off (refused before the control program is uploaded)."""
    import gc

    gc.collect()  # leftover ur-rtde objects sleep 500 ms in their destructors: not part of these timings
    nothing = URConfig(random_loopback_host(), connect_timeout_s=0.5, connect_attempts=2)
    rows = [("no controller (2 attempts, 0.5 s timeout)", *_time_connect(nothing))]
    with sim_cell(robot=robot, time_scale=10.0, extra_args=("--powered-off",)) as off:
        rows.append(("a powered-off arm", *_time_connect(URConfig(off.host))))
    return rows


def _time_connect(config: URConfig) -> tuple[str, float]:
    """The error type URRobot(config) raised ("none" if it connected) and the seconds it took."""
    started = time.perf_counter()
    try:
        URRobot(config).close()
        error = "none"
    except RobotError as exc:
        error = type(exc).__name__
    return error, time.perf_counter() - started


if __name__ == "__main__":
    sys.exit(main())
