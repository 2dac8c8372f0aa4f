"""The whole simulated cell in one process on one asyncio event loop (`python -m fakes.sim`, `hil sim`).

One `SimulatedCell`, the fake UR controller on its fixed ports, the fake emScon tracker, the control
channel, and one clock task that owns simulated time: every tick moves it on by one controller period x the
time scale, however late the tick (a loaded machine runs the cell slower, never differently). Adding a server is
two lines in `build()`: `self.add_server(server)` and `self.control.add_handlers(server.control_handlers())`.
Prints one JSON line on stdout once every server listens, then runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fakes.cell import EffectFlags, SimCellConfig, SimulatedCell, SmrLocation
from fakes.control_channel import ControlChannel
from fakes.emscon_server import EmsconServer, EmsconServerConfig
from fakes.launch import EXIT_ADDRESS_IN_USE
from fakes.ur_controller import UrController

log = logging.getLogger(__name__)

_WAKE_EARLY_S = 0.0006


@dataclass
class SimOptions:
    host: str = "127.0.0.2"
    robot: str = "ur10"
    seed: int = 0
    personality: str | None = None
    time_scale: float = 1.0
    control_port: int = 0
    tracker_port: int = 7000
    script_start_delay_s: float = 0.05
    powered: bool = True
    tracker_air_c: float | None = None  # the air temperature the tracker's station reads (None: the hall's)
    weather_monitor: bool = True  # False: the tracker has none and uses the meteo a client enters
    effects: EffectFlags = field(
        default_factory=lambda: EffectFlags()
    )  # e.g. {'thermal': True}; unset: defaults
    # Called with (ready line, ground truth) once every server listens, before the ready line is printed
    # (e.g. `hil sim --write-cell` writes the cell configuration for this cell).
    on_ready: Callable[[dict, dict], None] | None = None


class SimClock:
    """Fixed-rate wall-clock ticker advancing simulated time by a fixed step per tick (period x time scale);
    keeps period statistics for benchmarks."""

    def __init__(self, period_s: float, time_scale: float = 1.0):
        self.period_s = period_s
        self.time_scale = time_scale
        self.listeners: list = []  # callables f(dt_sim) run in order every tick
        self.late_ticks = 0
        self.ticks = 0
        self.periods: deque[float] = deque(maxlen=20000)

    def set_time_scale(self, value: float) -> None:
        value = float(value)
        if not 0 < value <= 1000:
            raise ValueError(f"time scale must be in (0, 1000], got {value}")
        self.time_scale = value

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        deadline = last = loop.time()
        while True:
            deadline += self.period_s
            delay = deadline - loop.time()
            if delay > _WAKE_EARLY_S:
                # the selector rounds timeouts up to whole milliseconds: wake a little early, then sleep
                # the sub-millisecond rest precisely (the loop has nothing else due before the tick)
                await asyncio.sleep(delay - _WAKE_EARLY_S)
                rest = deadline - loop.time()
                if 0 < rest <= _WAKE_EARLY_S:
                    time.sleep(rest)
                # let the servers read what arrived meanwhile, so this tick sees the latest commands
                await asyncio.sleep(0)
                await asyncio.sleep(0)
            else:
                await asyncio.sleep(0)  # behind schedule: still let the servers read their sockets
                if delay < -5 * self.period_s:  # hopelessly behind (suspended): resynchronise
                    deadline = loop.time()
            now = loop.time()
            if now - deadline > 0.5 * self.period_s:
                self.late_ticks += 1
            wall_dt = now - last
            last = now
            self.ticks += 1
            self.periods.append(wall_dt)
            dt_sim = self.period_s * self.time_scale  # fixed: the simulation never depends on the load
            for listener in self.listeners:
                try:
                    listener(dt_sim)
                except Exception:  # one failing tick must not stop the simulated world
                    log.exception("clock listener failed")

    def stats(self) -> dict:
        periods_ms = np.array(self.periods) * 1000.0
        if len(periods_ms) == 0:
            return {"ticks": self.ticks}
        return {
            "ticks": self.ticks,
            "late_ticks": self.late_ticks,
            "period_ms": self.period_s * 1000.0,
            "p50_ms": float(np.percentile(periods_ms, 50)),
            "p99_ms": float(np.percentile(periods_ms, 99)),
            "max_ms": float(periods_ms.max()),
            "samples": len(periods_ms),
        }

    def reset_stats(self) -> None:
        self.periods.clear()
        self.late_ticks = 0


class SimProcess:
    """Everything of one simulated cell: build, start, announce, run, close."""

    def __init__(self, options: SimOptions):
        self.options = options
        self.servers: list = []
        self.cell = SimulatedCell(
            SimCellConfig(
                robot=options.robot, seed=options.seed, tracker_air_c=options.tracker_air_c, **options.effects
            )
        )
        self.control = ControlChannel(options.host, options.control_port)
        self.robot: UrController | None = None
        self.clock: SimClock | None = None
        self.announcement: dict = {}
        self.announcers: list = []  # callables returning extra keys for the ready line (after start)

    def add_server(self, server) -> None:
        """Any object with `async start()` and `async close()` joins the cell."""
        self.servers.append(server)

    def build(self) -> None:
        o = self.options
        self.robot = UrController(
            self.cell,
            host=o.host,
            personality=o.personality,
            script_start_delay_s=o.script_start_delay_s,
            powered=o.powered,
        )
        self.add_server(self.robot)
        self.control.add_handlers(robot_handlers(self.robot))
        self.clock = SimClock(self.robot.period_s, o.time_scale)
        self.clock.listeners.append(self.cell.advance_timer)
        self.clock.listeners.append(self.robot.tick)
        self.control.add_handlers(cell_handlers(self.cell, self.clock, epoch_s=time.time()))
        # The cell's clock task moves simulated time on: a measurement waits for it (scaled by --time-scale)
        # instead of sleeping the unscaled measurement time and advancing the clock a second time.
        tracker = EmsconServer(
            self.cell,
            o.host,
            o.tracker_port,
            EmsconServerConfig(advance_clock=False, weather_monitor=o.weather_monitor),
        )
        # a continuous measurement samples the arm after every tick of the clock, as that tick left it
        tracker.beam.tick_driven = True
        self.clock.listeners.append(tracker.beam.on_tick)
        self.add_server(tracker)
        self.control.add_handlers(tracker.control_handlers())
        self.announcers.append(lambda: {"tracker": {"url": tracker.url, "port": tracker.port}})

    def built(self) -> tuple[UrController, SimClock]:
        """The controller and the clock that build() made."""
        if self.robot is None or self.clock is None:
            raise RuntimeError("SimProcess.build() has not run")
        return self.robot, self.clock

    def announce(self) -> dict:
        robot, clock = self.built()
        info = {
            "robot": {
                "host": self.options.host,
                "model": self.options.robot,
                "rtde_port": robot.ports["rtde"],
                "dashboard_port": robot.ports["dashboard"],
                "script_ports": [robot.ports[k] for k in ("primary", "secondary", "realtime")],
                "personality": robot.personality.name,
                "version": ".".join(map(str, robot.personality.version)),
                "frequency_hz": robot.personality.frequency_hz,
            },
            "control": self.control.address,
            "seed": self.options.seed,
            "time_scale": clock.time_scale,
        }
        for announcer in self.announcers:
            info.update(announcer())
        self.announcement = info
        return info

    async def run(self, ready_out=sys.stdout) -> int:
        self.build()
        started: list = []
        try:
            for server in [*self.servers, self.control]:
                await server.start()
                started.append(server)
        except OSError as exc:
            for server in reversed(started):
                await server.close()
            if exc.errno == errno.EADDRINUSE:
                print(f"sim cell: address in use on {self.options.host}: {exc}", file=sys.stderr)
                return EXIT_ADDRESS_IN_USE
            raise
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        # SIGINT ignored when the cell started (fakes.launch: its starter stops it) stays ignored
        ignored = {signal.SIGINT} if signal.getsignal(signal.SIGINT) == signal.SIG_IGN else set()
        for sig in {signal.SIGINT, signal.SIGTERM} - ignored:
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(sig, stop.set)
        clock_task = asyncio.create_task(self.built()[1].run())
        info = self.announce()
        if self.options.on_ready is not None:
            self.options.on_ready(info, self.cell.ground_truth())
        print(json.dumps(info), file=ready_out, flush=True)
        try:
            await stop.wait()
        finally:
            clock_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await clock_task
            for server in reversed(started):
                await server.close()
        return 0


def robot_handlers(robot: UrController) -> dict:
    """Control commands that reach into the fake robot controller."""

    def fault(request: dict) -> dict:
        at_move = request.get("at_move")
        return robot.inject_fault(
            str(request["kind"]),
            at_move=None if at_move is None else int(at_move),
            fraction=float(request.get("fraction", 0.5)),
            duration_s=float(request.get("duration_s", 3.0)),
        )

    def set_remote(request: dict) -> bool:
        robot.remote_control = bool(request["value"])
        return robot.remote_control

    return {
        "robot.state": lambda request: robot.state(),
        "robot.fault": fault,
        "robot.clear_faults": lambda request: robot.clear_faults(),
        "robot.release_estop": lambda request: robot.release_emergency_stop(),
        "robot.set_remote_control": set_remote,
        "robot.last_program": lambda request: robot.last_program_text,
    }


def cell_handlers(cell: SimulatedCell, clock: SimClock, epoch_s: float = 0.0) -> dict:
    """Control commands for the simulated world: truth, the operator's hands, the clock (`cell.clock`: the
    physics clock as UNIX seconds counted from `epoch_s`, the cell's start)."""

    def place_smr(request: dict) -> dict:
        point = request.get("point_m")
        location = SmrLocation(
            kind=request["kind"],
            index=request.get("index"),
            point_m=tuple(float(x) for x in point) if point is not None else None,
        )
        cell.place_smr(int(request["smr_id"]), location)
        return {
            "smr_id": int(request["smr_id"]),
            "center_tracker_m": cell.smr_center_tracker(int(request["smr_id"])),
        }

    def set_time_scale(request: dict) -> float:
        clock.set_time_scale(request["value"])
        return clock.time_scale

    def clock_stats(request: dict) -> dict:
        stats = clock.stats()
        if request.get("reset"):
            clock.reset_stats()
        return stats

    return {
        "ping": lambda request: {"pong": True, "time_s": cell.time_s, "wall": time.time()},
        "ground_truth": lambda request: cell.ground_truth(),
        "place_smr": place_smr,
        "smr_location": lambda request: cell.smr_location(int(request["smr_id"])),
        "unmount_tool": lambda request: cell.unmount_tool(),
        "mount_tool": lambda request: cell.mount_tool(float(request.get("rotation_rad", 0.0))),
        "cell.state": lambda request: {
            "time_s": cell.time_s,
            "physics_time_s": cell.physics_time_s,
            "commanded_q": cell.commanded_q,
            "true_joints": cell.true_joints(),
            "T_base_flange_true": cell.T_base_flange_true(),
            "smr_ids": cell.smr_ids,
        },
        "cell.clock": lambda request: {
            "unix_s": epoch_s + cell.physics_time_s,
            "physics_s": cell.physics_time_s,
            "timer_s": cell.time_s,
        },
        "time_scale": lambda request: clock.time_scale,
        "set_time_scale": set_time_scale,
        "clock.stats": clock_stats,
        "clock.periods": lambda request: list(clock.periods),
    }


def run_cell(options: SimOptions) -> int:
    """Run the cell until SIGINT/SIGTERM; the exit status (0, or EXIT_ADDRESS_IN_USE)."""
    logging.basicConfig(
        level=logging.DEBUG if os.environ.get("HIL_SIM_DEBUG") else logging.WARNING,
        format="sim cell %(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return asyncio.run(SimProcess(options).run())
