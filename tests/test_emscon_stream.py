"""Continuous-time sampling through the emScon driver and the fake tracker: MultiMeasResult packets on the
wire, stamped with the cell's clock, following the SMR the cell moves; refusals and a beam break."""

import time

import numpy as np
import pytest

from drivers import emscon_codec as codec
from drivers.emscon import EmsconConfig, EmsconTracker
from fakes.cell import SimCellConfig, SimulatedCell
from fakes.emscon_server import EmsconServer, EmsconServerConfig, ServerThread
from hil.instruments.tracker import (
    NoTargetError,
    StreamingTracker,
    TrackerCommandError,
    TrackerConfigError,
)

pytestmark = [pytest.mark.sim, pytest.mark.timeout(60)]

SMR = 2  # a floor-nest SMR of the default cell (always faces the tracker)


def _wait_for(condition, timeout_s: float = 20.0) -> None:
    """Wait until `condition()` holds (a state of the fake), failing after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the fake never reached the state waited for"
        time.sleep(0.005)


@pytest.fixture
def cell():
    return SimulatedCell(SimCellConfig(seed=1))


def _serve(cell, **config) -> ServerThread:
    return ServerThread(EmsconServer(cell, config=EmsconServerConfig(init_delay_s=0.01, **config)))


def test_multi_meas_result_round_trips_through_the_codec():
    samples = [(12.25, (1.0, -2.0, 0.5)), (12.5, (1.001, -2.0, 0.5))]
    packet = codec.pack_multi_meas_result(0, samples, (20.0, 1013.0, 45.0))
    assert len(packet) == 48 + 36 * 2
    decoded = codec.decode_server_packet(packet)
    assert isinstance(decoded, codec.MultiMeasPacket)
    assert decoded.times_s == pytest.approx((12.25, 12.5), abs=1e-6)
    assert decoded.values == ((1.0, -2.0, 0.5), (1.001, -2.0, 0.5))
    assert decoded.meas_mode == codec.MeasMode.CONTINUOUS_TIME and decoded.temperature == 20.0
    with pytest.raises(codec.CodecError):
        codec.decode_server_packet(
            packet[:-36].replace(packet[:4], (len(packet) - 36).to_bytes(4, "little"), 1)
        )


def test_stream_samples_the_smr_on_the_cells_clock(cell):
    """A sample every separation of the cell's clock, stamped with it, each where the cell has the SMR within
    the tracker's noise (a moving SMR: tests/test_iso9283_sim.py); stationary mode again afterwards."""
    with (
        _serve(cell, wall_time_scale=0.2) as server,
        EmsconTracker(EmsconConfig(url=server.url, meas_time_s=0.01, command_timeout_s=10.0)) as tracker,
    ):
        assert isinstance(tracker, StreamingTracker)
        assert tracker.check_stream(0.02) == pytest.approx(0.02)
        tracker.point_at(cell.smr_center_tracker(SMR))
        t0 = cell.time_s
        tracker.start_stream(0.02)
        _wait_for(lambda: cell.time_s > t0 + 0.5)
        stream = tracker.stop_stream()
        m = tracker.measure()  # back in stationary mode
    assert len(stream.t_s) >= 20 and np.all(np.diff(stream.t_s) > 0)
    assert np.diff(stream.t_s) == pytest.approx(0.02, abs=1e-6)  # the fake's own clock: one sample per step
    truth = cell.smr_center_tracker(SMR)
    sigma = float(cell.tracker_sigma_m(np.linalg.norm(truth)))
    assert np.all(np.linalg.norm(stream.p_tracker_m - truth, axis=1) < 6 * sigma + 0.001)
    assert np.linalg.norm(m.p_tracker_m - truth) < 0.001


def test_a_tracker_without_continuous_modes_refuses_before_anything_is_measured(cell):
    with (
        _serve(cell, continuous_modes=False) as server,
        EmsconTracker(EmsconConfig(url=server.url, meas_time_s=0.01)) as tracker,
    ):
        with pytest.raises(TrackerCommandError, match="cannot sample a moving SMR"):
            tracker.check_stream(0.01)
        with pytest.raises(TrackerConfigError):
            tracker.check_stream(0.0001)
        tracker.point_at(cell.smr_center_tracker(SMR))
        tracker.measure()  # still measures stationary points
        assert server.state.command_counts["START_MEASUREMENT"] == 1


def test_a_stream_without_a_locked_smr_is_refused_and_the_tracker_stays_stationary(cell):
    with _serve(cell) as server, EmsconTracker(EmsconConfig(url=server.url, meas_time_s=0.01)) as tracker:
        with pytest.raises(NoTargetError):
            tracker.start_stream(0.01)
        assert server.state.meas_mode == codec.MeasMode.STATIONARY
        tracker.point_at(cell.smr_center_tracker(SMR))
        tracker.measure()


def test_a_beam_break_during_the_stream_is_an_error_at_its_end(cell):
    thread = _serve(cell, wall_time_scale=0.2)
    with thread, EmsconTracker(EmsconConfig(url=thread.server.url, meas_time_s=0.01)) as tracker:
        tracker.point_at(cell.smr_center_tracker(SMR))
        tracker.start_stream(0.02)
        t0 = cell.time_s
        _wait_for(lambda: cell.time_s > t0 + 0.1)
        thread.call(thread.server.control_handlers()["tracker.fault"], {"kind": "no_target"})
        _wait_for(lambda: thread.server.state.measuring == 0)
        with pytest.raises(NoTargetError, match="beam broke after"):
            tracker.stop_stream()
