"""The fake emScon tracker's beam on the simulated cell: lock, follow and search the SMRs, and measure.

A measurement is the locked SMR's centre from the cell (with the cell's noise model), its a-priori std from
the cell's tracker noise and the meteo in use, packed in the client's units and coordinate system; faults
break the beam during a shot or offset a result (an outlier).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, Status, StatusChange
from fakes.emscon_faults import Faults
from fakes.emscon_state import Client, EmsconServerConfig, TrackerState

log = logging.getLogger("fakes.emscon_server")


@dataclass
class _Stream:
    """A running continuous-time stream: to whom, under which lock, how often, how many, when next."""

    client: Client
    generation: int
    separation_s: float
    count: int  # 0: until StopMeasurement
    due_s: float  # the next sample's instant on the cell clock
    sent: int = 0


class Beam:
    """The beam and its lock on an SMR, shared by every client; `broadcast` sends an event to all of them."""

    def __init__(
        self,
        cell,
        config: EmsconServerConfig,
        state: TrackerState,
        faults: Faults,
        broadcast: Callable[..., None],
    ):
        self.cell = cell
        self.config = config
        self.state = state
        self.faults = faults
        self.broadcast = broadcast
        self.loop: asyncio.AbstractEventLoop | None = None  # the server's loop, once started
        self.generation = 0  # counts lock changes: a shot whose lock changed meanwhile has no result
        self.fault_rng = np.random.default_rng([getattr(cell.config, "seed", 0), 3])  # random beam breaks
        self.sent_results: deque[bytes] = deque(maxlen=1000)  # raw result packets, for tests
        self.stream_task: asyncio.Task | None = None  # the continuous-time stream on the fake's own clock
        self.stream_state: _Stream | None = None  # the continuous-time stream, while one runs
        self.tick_driven = False  # True inside `hil sim`: the cell's clock calls on_tick after every tick

    def running_loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the server runs on (set by its start() or open_pty())."""
        if self.loop is None:
            raise RuntimeError("the fake tracker is not started: await start() or open_pty() first")
        return self.loop

    def visible(self, smr_id: int) -> bool:
        """Whether the SMR faces the tracker within its opening angle."""
        return self.cell.smr_facing_angle_rad(smr_id) <= self.config.acceptance_half_angle_rad

    def lock(self, smr_id: int) -> None:
        """Lock the beam on an SMR where it is now."""
        st = self.state
        st.locked_smr = smr_id
        st.lock_p_m = np.asarray(self.cell.smr_center_tracker(smr_id), dtype=float)
        st.lock_sim_s = self.cell.time_s
        st.lock_wall_s = self.loop.time() if self.loop else 0.0
        st.direction = st.lock_p_m / np.linalg.norm(st.lock_p_m)
        self.generation += 1

    def lose_lock(self, command: int = Command.UNKNOWN) -> None:
        """The beam broke: tell every client (an error event if they asked for unsolicited ones)."""
        st = self.state
        if st.locked_smr is None:
            return
        log.info("fake tracker: beam to SMR %s broken", st.locked_smr)
        st.locked_smr = None
        self.generation += 1
        if st.settings[4]:
            self.broadcast(codec.pack_error(command, self.config.no_target_status))
        self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))

    def track(self) -> None:
        """Follow the locked SMR; lose it if it moved faster than the tracker follows or turned away."""
        st = self.state
        if st.locked_smr is None:
            return
        p = np.asarray(self.cell.smr_center_tracker(st.locked_smr), dtype=float)
        wall = self.running_loop().time()
        dt = max(self.cell.time_s - st.lock_sim_s, wall - st.lock_wall_s, 0.0)
        allowed = self.config.capture_m + self.config.max_tracking_speed_m_s * dt
        if np.linalg.norm(p - st.lock_p_m) > allowed or not self.visible(st.locked_smr):
            self.lose_lock(Command.START_MEASUREMENT if st.measuring else Command.UNKNOWN)
            return
        st.lock_p_m, st.lock_sim_s, st.lock_wall_s = p, self.cell.time_s, wall
        st.direction = p / np.linalg.norm(p)

    async def poll(self) -> None:
        """Follow the locked SMR every track_poll_s, as the tracker does between commands."""
        while True:
            await asyncio.sleep(self.config.track_poll_s)
            try:
                self.track()
            except Exception:
                log.exception("fake tracker: tracking poll failed")

    def search(self, p_aim_m: np.ndarray, radius_m: float) -> int | None:
        """The visible SMR nearest the aimed point within the search radius, if any."""
        best, best_d = None, radius_m
        for smr_id in self.cell.smr_ids:
            d = float(np.linalg.norm(self.cell.smr_center_tracker(smr_id) - p_aim_m))
            if d <= best_d and self.visible(smr_id):
                best, best_d = smr_id, d
        return best

    def ready(self) -> bool:
        """Whether a shot can be taken: locked, laser on, beam not blocked."""
        st = self.state
        return st.locked_smr is not None and st.laser_on and not self.faults.no_target

    def acquire(self, p_aim_m: np.ndarray) -> bool:
        """Aim at a point and lock the SMR found there; announces the new state to every client."""
        st = self.state
        st.direction = p_aim_m / max(float(np.linalg.norm(p_aim_m)), 1e-9)
        blind = self.faults.no_target or not st.laser_on
        found = None if blind else self.search(p_aim_m, st.search_radius_m)
        if found is None:
            if st.locked_smr is not None:
                st.locked_smr = None
                self.generation += 1
            self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))
            return False
        self.lock(found)
        self.broadcast(
            codec.pack_status_change(StatusChange.DISTANCE_SET),
            codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
        )
        return True

    def meteo(self) -> tuple[float, float, float]:
        """(°C, hPa, %RH) in use: the weather monitor (cell meteo) or the manual values."""
        if self.state.settings[0] == codec.WeatherMonitorStatus.NOT_CONNECTED and self.state.manual_meteo:
            return self.state.manual_meteo
        m = self.cell.meteo()
        return (m.temperature_c, m.pressure_hpa, m.humidity_pct)

    def meteo_wire(self) -> tuple[float, float, float]:
        """The meteo in use in the client's units."""
        t, p, h = self.meteo()
        u = self.state.units
        return (u.temperature_to_wire(t), u.pressure_to_wire(p), h)

    async def measure(self, client: Client) -> tuple | None:
        """StartMeasurement: the plain answer on refusal, else answer, busy event, then the result or an error."""
        st = self.state
        if not st.initialized:
            st.last_result_status = Status.TRACKER_NOT_INITIALIZED
            return (Status.TRACKER_NOT_INITIALIZED,)
        if not self.ready():
            st.last_result_status = self.config.no_target_status
            return (self.config.no_target_status,)
        generation = self.generation
        if st.meas_mode == codec.MeasMode.CONTINUOUS_TIME:
            self.stop_stream()
            client.send(codec.pack_answer(Command.START_MEASUREMENT, Status.ALL_OK), flush=False)
            client.send(codec.pack_status_change(StatusChange.MEAS_STATUS_BUSY))
            self.start_stream(client, generation)
            return None
        client.send(codec.pack_answer(Command.START_MEASUREMENT, Status.ALL_OK), flush=False)
        client.send(codec.pack_status_change(StatusChange.MEAS_STATUS_BUSY), flush=False)
        meas_s = st.meas_time_ms / 1000.0
        st.measuring += 1
        try:
            random_break = (
                self.faults.beam_break_rate > 0 and self.fault_rng.random() < self.faults.beam_break_rate
            )
            if self.faults.beam_break_count > 0 or random_break:
                self.faults.beam_break_count = max(0, self.faults.beam_break_count - 1)
                await self.pass_time(meas_s / 2)
                st.last_result_status = self.config.no_target_status
                client.send(codec.pack_error(Command.START_MEASUREMENT, self.config.no_target_status))
                self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))
                if self.ready():  # the SMR did not move: the tracker catches the beam again
                    self.broadcast(
                        codec.pack_status_change(StatusChange.DISTANCE_SET),
                        codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
                    )
                return None
            await self.pass_time(meas_s)
            self.track()
        finally:
            st.measuring -= 1
        if generation != self.generation or not self.ready():
            st.last_result_status = self.config.no_target_status
            client.send(codec.pack_error(Command.START_MEASUREMENT, self.config.no_target_status))
            return None
        result = self._result_packet()
        self.sent_results.append(result)
        client.send(result, codec.pack_status_change(StatusChange.MEAS_STATUS_READY))
        st.last_result_status = 0
        return None

    def stop_stream(self) -> None:
        """StopMeasurement: end the continuous stream (what it sent so far precedes the answer)."""
        if self.stream_task is not None and not self.stream_task.done():
            self.stream_task.cancel()
        self.stream_task = None
        if self.stream_state is not None:
            self.stream_state = None
            self.state.measuring -= 1

    def start_stream(self, client: Client, generation: int) -> None:
        """Continuous-time mode: a sample of the locked SMR every lTimeSeparation of simulated time, stamped
        with the cell's clock, each sent as a MultiMeasResult; ends on StopMeasurement, after lNumberOfPoints
        (then MeasurementCountReached) or when the beam breaks (then the error packet of StartMeasurement).

        Inside `hil sim` the cell's clock calls `on_tick` after every controller tick, so each sample sees the
        arm as that tick left it (a clock ticking more coarsely than the separation gives a sample per tick);
        with its own clock the fake advances the cell by the separation between samples."""
        self.stop_stream()
        self.state.measuring += 1
        self.stream_state = _Stream(client, generation, self.state.continuous_time[0] / 1000.0,
                                    self.state.continuous_time[1], self.cell.time_s)  # fmt: skip
        if not self.tick_driven:
            self.stream_task = self.running_loop().create_task(self._own_clock_stream())

    def on_tick(self, dt_s: float) -> None:
        """A tick of the cell's clock (a listener after the robot's): take the stream's sample if one is due."""
        stream = self.stream_state
        if stream is None or self.cell.time_s < stream.due_s:
            return
        late = self.cell.time_s - stream.due_s
        stream.due_s += stream.separation_s * (math.floor(late / stream.separation_s) + 1)
        self._sample(stream)

    async def _own_clock_stream(self) -> None:
        """The stream on the fake's own clock: wait a separation (scaled to wall time), advance the cell, sample."""
        while self.stream_state is not None:
            stream = self.stream_state
            await asyncio.sleep(stream.separation_s * self.config.wall_time_scale)
            self.cell.advance_time(stream.separation_s)
            self._sample(stream)

    def _sample(self, stream: _Stream) -> None:
        """One sample of the locked SMR to the streaming client; the end of the stream on a lost beam or count."""
        st = self.state
        client = stream.client
        if getattr(client, "closed", False):
            self.stop_stream()
            return
        self.track()
        if stream.generation != self.generation or not self.ready():
            st.last_result_status = self.config.no_target_status
            client.send(codec.pack_error(Command.START_MEASUREMENT, self.config.no_target_status))
            self.stop_stream()
            return
        p_m = np.asarray(self.cell.measure_smr(st.locked_smr, air_c=self.meteo()[0]), dtype=float)
        values = tuple(codec.cartesian_to_wire(p_m, st.cs, st.units))
        client.send(codec.pack_multi_meas_result(0, [(self.cell.time_s, values)], self.meteo_wire()))
        stream.sent += 1
        if stream.count and stream.sent >= stream.count:
            client.send(
                codec.pack_status_change(StatusChange.MEASUREMENT_COUNT_REACHED),
                codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
            )
            self.stop_stream()

    async def pass_time(self, dt_s: float) -> None:
        """Let dt_s of simulated time pass: advance the cell clock ourselves, or wait for its owner's timer
        clock and then move the physics clock on by exactly dt_s."""
        if self.config.advance_clock:
            await asyncio.sleep(dt_s * self.config.wall_time_scale)
            self.cell.advance_time(dt_s)
            return
        target = self.cell.time_s + dt_s
        while self.cell.time_s < target:
            await asyncio.sleep(self.config.external_clock_poll_s)
        self.cell.advance_physics(dt_s)  # the shot's time, exactly, whatever the ticks

    def _result_packet(self) -> bytes:
        """The result of a shot: the locked SMR with the cell's noise, its std and the meteo, on the wire."""
        st = self.state
        p_m = np.asarray(self.cell.measure_smr(st.locked_smr, air_c=self.meteo()[0]), dtype=float)
        if self.faults.outlier_count > 0:
            self.faults.outlier_count -= 1
            p_m = p_m + np.array([self.faults.outlier_offset_m, 0.0, 0.0])
        sigma_m = float(self.cell.tracker_sigma_m(float(np.linalg.norm(p_m))))
        values = codec.cartesian_to_wire(p_m, st.cs, st.units)
        std = codec.cartesian_std_to_wire(np.full(3, sigma_m), p_m, st.cs, st.units)
        std_total = st.units.length_to_wire(math.sqrt(3.0) * sigma_m)
        return codec.pack_single_meas_result(
            0, values, std, std_total, std, std_total, self.meteo_wire(), extended=bool(st.statistic_mode[0])
        )

    def block(self) -> None:
        """Something blocks the beam (fault no_target): clients hear the measurement is not ready."""
        self.faults.no_target = True
        if self.state.settings[4]:
            self.broadcast(codec.pack_error(Command.UNKNOWN, self.config.no_target_status))
        self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_NOT_READY))

    def unblock(self) -> None:
        """The beam is free again: the tracker catches the SMR if it is still there."""
        self.track()
        if self.ready():
            self.broadcast(
                codec.pack_status_change(StatusChange.DISTANCE_SET),
                codec.pack_status_change(StatusChange.MEAS_STATUS_READY),
            )
