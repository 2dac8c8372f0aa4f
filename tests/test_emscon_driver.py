"""Driver <-> fake emScon tracker over TCP and over a pseudo-terminal, on the simulated cell."""

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from rfc2217_bridge import Rfc2217Bridge

from drivers import emscon_codec as codec
from drivers.emscon import EmsconConfig, EmsconTracker
from fakes.cell import SimCellConfig, SimulatedCell, SmrLocation
from fakes.emscon_server import EmsconServer, EmsconServerConfig, ServerThread
from hil.instruments.tracker import (
    MeteoOutOfRangeError,
    NoTargetError,
    NotInitializedError,
    Tracker,
    TrackerCommandError,
    TrackerConfigError,
    TrackerConnectionError,
    TrackerProtocolError,
    TrackerTimeoutError,
)

pytestmark = [
    pytest.mark.sim,
    pytest.mark.timeout(60),
]  # starts a simulated cell or a fake server over sockets

MEAS_S = 0.01  # stationary measurement time used by the tests (fast; the fake waits it in wall time)
SMR = 2  # a floor-nest SMR of the default cell (always faces the tracker)


@pytest.fixture
def cell():
    return SimulatedCell(SimCellConfig(seed=1))


@pytest.fixture
def server_thread(cell):
    server = EmsconServer(cell, config=EmsconServerConfig(init_delay_s=0.01))
    thread = ServerThread(server)
    with thread:
        yield thread


@pytest.fixture(params=["tcp", "pty", "rfc2217"])
def url(request, server_thread):
    """The same fake over TCP, over a serial line (pty), and over that line behind an RFC 2217 server."""
    if request.param == "tcp":
        return server_thread.server.url
    device = server_thread.run(server_thread.server.open_pty())
    if request.param == "pty":
        return device
    bridge = Rfc2217Bridge(device)
    request.addfinalizer(bridge.close)
    return bridge.url


LATE_S = 2.0  # how late a timeout may be noticed on a loaded machine (the driver polls every 20 ms)


def _tracker(url, **options) -> EmsconTracker:
    # Generous margins where a test does not time out on purpose: a busy 2-core machine may take seconds to
    # deliver an answer sent byte by byte. The tests of timeouts set their own and bound how late they fire.
    options = {"meas_time_s": MEAS_S, "measurement_margin_s": 10.0, "command_timeout_s": 10.0, **options}
    return EmsconTracker(EmsconConfig(url=url, **options))


def _fault(thread: ServerThread, **request) -> dict:
    return thread.call(thread.server.control_handlers()["tracker.fault"], request)


def _tolerance_m(cell, p, shots) -> float:
    """5 sigma of a mean of `shots` readings plus 4 sigma of the SMR's fixed centring offset."""
    sigma = float(cell.tracker_sigma_m(np.linalg.norm(p)))
    return 5 * sigma / np.sqrt(shots) + 4 * cell.config.smr_centering_sigma_m


def test_measure_a_static_smr_matches_the_cell_truth(url, cell, server_thread):
    truth = cell.smr_center_tracker(SMR)
    with _tracker(url) as tracker:
        assert isinstance(tracker, Tracker)
        assert tracker.initialized  # the fake started uninitialized: the driver ran Initialize
        tracker.point_at(truth + np.array([0.01, -0.01, 0.005]))  # aim near it; the search finds it
        m = tracker.measure(shots=20)
    sigma = float(cell.tracker_sigma_m(np.linalg.norm(truth)))
    assert np.linalg.norm(m.p_tracker_m - truth) < _tolerance_m(cell, truth, 20)
    assert np.all(m.spread_m > 0.4 * sigma) and np.all(m.spread_m < 2.0 * sigma)
    np.testing.assert_allclose(m.std_m, sigma, rtol=1e-5)  # a-priori sigma at the measured distance
    assert m.shots_used == 20 and m.rejected_shots == ()
    meteo = cell.meteo()
    assert m.temperature_c == pytest.approx(meteo.temperature_c)
    assert m.pressure_hpa == pytest.approx(meteo.pressure_hpa, abs=0.01)
    assert m.humidity_pct == pytest.approx(meteo.humidity_pct, abs=0.05)
    assert abs(m.timestamp_s - time.time()) < 5
    assert cell.time_s == pytest.approx(20 * MEAS_S)  # the fake moved the cell clock per measurement
    assert server_thread.server.state.exit_requests == 0


@pytest.mark.parametrize(
    ("length", "angle", "cs"),
    [
        (codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE, codec.CoordinateSystem.RHR),
        (codec.LengthUnit.METER, codec.AngleUnit.RADIAN, codec.CoordinateSystem.SCC),
        (codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE, codec.CoordinateSystem.SCW),
        (codec.LengthUnit.INCH, codec.AngleUnit.GON, codec.CoordinateSystem.SCC),
    ],
)
def test_units_and_coordinate_systems_round_trip(server_thread, cell, length, angle, cs):
    truth = cell.smr_center_tracker(3)
    with _tracker(
        server_thread.server.url, length_unit=length, angle_unit=angle, coordinate_system=cs
    ) as tracker:
        tracker.point_at(truth)
        m = tracker.measure(shots=5)
        state = server_thread.call(server_thread.server.control_handlers()["tracker.state"], {})
    assert state["units"][:2] == (length, angle) and state["coordinate_system"] == cs
    assert np.linalg.norm(m.p_tracker_m - truth) < _tolerance_m(cell, truth, 5)
    sigma = float(cell.tracker_sigma_m(np.linalg.norm(truth)))
    np.testing.assert_allclose(m.std_m, sigma, rtol=1e-5)  # angular stds come back as lengths


@pytest.mark.parametrize("mode", ["bytewise", "merged"])
def test_split_and_merged_packets_decode_exactly(url, cell, server_thread, mode):
    truth = cell.smr_center_tracker(SMR)
    with _tracker(url) as tracker:
        tracker.point_at(truth)
        _fault(server_thread, kind="framing", mode=mode)
        m = tracker.measure(shots=3)
        state = tracker.state()
    assert np.linalg.norm(m.p_tracker_m - truth) < _tolerance_m(cell, truth, 3)
    assert [p.raw for p in tracker.last_results] == list(server_thread.server.sent_results)[-3:]
    assert state.target_locked and state.details["serial_number"] == 390123


def test_extended_statistics_results(server_thread, cell):
    truth = cell.smr_center_tracker(SMR)
    with _tracker(server_thread.server.url, extended_statistics=True) as tracker:
        tracker.point_at(truth)
        m = tracker.measure(shots=2)
    assert np.linalg.norm(m.p_tracker_m - truth) < _tolerance_m(cell, truth, 2)


def test_lock_picks_the_nearest_smr_within_the_search_radius(server_thread, cell):
    a = cell.smr_center_tracker(SMR)
    cell.place_smr(3, SmrLocation("fixed", point_m=tuple(a + np.array([0.03, 0.0, 0.0]))))
    with _tracker(server_thread.server.url) as tracker:
        tracker.point_at(a + np.array([0.02, 0.0, 0.0]))  # 1 cm from SMR 3, 2 cm from SMR 2
        assert np.linalg.norm(tracker.measure().p_tracker_m - cell.smr_center_tracker(3)) < 1e-3
        tracker.point_at(a + np.array([0.005, 0.0, 0.0]))
        assert np.linalg.norm(tracker.measure().p_tracker_m - a) < 1e-3
        with pytest.raises(NoTargetError, match="no reflector locked"):
            tracker.point_at(a + np.array([0.0, 0.0, 0.2]))  # nothing within 5 cm
        with pytest.raises(NoTargetError):
            tracker.measure()
        with pytest.raises(NoTargetError, match="FIND_REFLECTOR"):
            tracker.find_target(float(np.linalg.norm(a)))  # searches where the beam points: nothing there
        tracker.point_at(a)
        tracker.find_target()  # at the last distance, around the current direction
        assert np.linalg.norm(tracker.measure().p_tracker_m - a) < 1e-3


def test_moving_the_locked_smr_too_fast_breaks_the_beam_until_reacquired(url, server_thread, cell):
    old = cell.smr_center_tracker(SMR)
    with _tracker(url) as tracker:
        tracker.point_at(old)
        tracker.measure()
        new = old + np.array([0.0, 0.3, 0.0])
        cell.place_smr(SMR, SmrLocation("fixed", point_m=tuple(new)))  # a jump, no time passes
        with pytest.raises(NoTargetError):
            tracker.measure()
        assert tracker.state().target_locked is False
        tracker.point_at(new)
        assert np.linalg.norm(tracker.measure().p_tracker_m - new) < 1e-3


def test_slow_motion_is_followed_and_turning_the_smr_away_breaks_the_beam(server_thread, cell):
    q = cell.commanded_q
    q[4] += 1.5  # wrist turned so that the tool-nest SMR faces the tracker
    cell.set_commanded_joints(q)
    with _tracker(server_thread.server.url) as tracker:
        tracker.point_at(cell.smr_center_tracker(1))
        for _ in range(5):  # slow motion: 1 mrad per step with 0.1 s of simulated time
            q[0] += 1e-3
            cell.set_commanded_joints(q)
            cell.advance_time(0.1)
            truth = cell.smr_center_tracker(1)
            assert np.linalg.norm(tracker.measure().p_tracker_m - truth) < 1e-3
        q[4] -= 1.5  # now the SMR opening points away from the tracker: occluded
        cell.set_commanded_joints(q)
        cell.advance_time(0.1)
        with pytest.raises(NoTargetError):
            tracker.measure()


def test_not_initialized_and_meteo_out_of_range_are_typed(server_thread):
    with _tracker(server_thread.server.url, auto_initialize=False) as tracker:
        assert not tracker.state().initialized
        with pytest.raises(NotInitializedError):
            tracker.measure()
        tracker.initialize()
        assert tracker.state().initialized
        with pytest.raises(MeteoOutOfRangeError, match="and their units"):
            tracker.set_environment(20.0, 101.3, 45.0)  # kPa passed as hPa
        t, p, h = tracker.environment()
        assert (t, p, h) == pytest.approx((20.0, 1013.25, 45.0), abs=0.1)


@pytest.mark.parametrize("probe", [True, False])
def test_meteo_from_the_hall_and_object_temperature_from_the_arm(probe):
    """The weather station follows the hall's air, the object probe the warming arm; no probe: None."""
    cfg = SimCellConfig(seed=1, thermal=True, warmup_k=6.0, warmup_tau_s=600.0, air_warmup_fraction=0.25)
    cell = SimulatedCell(cfg)
    server = EmsconServer(cell, config=EmsconServerConfig(init_delay_s=0.01, object_probe=probe))
    with ServerThread(server), _tracker(server.url) as tracker:
        tracker.point_at(cell.smr_center_tracker(SMR))
        cell.advance_time(1200.0)
        arm_c, meteo = float(cell.structure_temperature_c()), cell.meteo()
        assert arm_c - cfg.ambient_c > 4.0 and meteo.temperature_c < arm_c - 3.0
        t, p, h = tracker.environment()
        assert (t, p, h) == pytest.approx(
            (meteo.temperature_c, meteo.pressure_hpa, meteo.humidity_pct), abs=0.05
        )
        m = tracker.measure()
        assert m.temperature_c == pytest.approx(float(cell.meteo().temperature_c), abs=0.05)
        if probe:
            assert m.object_temperature_c == pytest.approx(float(cell.structure_temperature_c()), abs=0.05)
            assert tracker.has_object_probe is True
        else:
            assert m.object_temperature_c is None and tracker.object_temperature() is None
            assert tracker.has_object_probe is False
            asked = server.state.command_counts["GET_OBJECT_TEMPERATURE"]
            tracker.measure()
            assert server.state.command_counts["GET_OBJECT_TEMPERATURE"] == asked  # asked once, remembered


def test_outliers_are_rejected_and_reported(server_thread, cell, caplog):
    truth = cell.smr_center_tracker(SMR)
    with _tracker(server_thread.server.url) as tracker:
        tracker.point_at(truth)
        _fault(server_thread, kind="outlier", count=1, offset_m=0.002)
        m = tracker.measure(shots=7)
    assert m.rejected_shots == (0,)
    assert m.shots_used == 6
    assert m.shots_m[0, 0] - truth[0] == pytest.approx(0.002, abs=1e-4)
    assert np.linalg.norm(m.p_tracker_m - truth) < _tolerance_m(cell, truth, 6)
    assert "rejected 1 of 7 shots" in caplog.text


def test_bad_arguments_are_refused_before_anything_is_sent(server_thread):
    tracker = _tracker(server_thread.server.url)
    with pytest.raises(ValueError, match="shots"):
        tracker.measure(shots=0)
    with pytest.raises(ValueError, match="finite"):
        tracker.point_at([1.0, np.nan, 0.0])
    assert not tracker.connected
    with pytest.raises(ValueError, match="ExitApplication"):
        tracker._exchange(codec.Command.EXIT_APPLICATION)
    with pytest.raises(TrackerConfigError, match="coordinate_system"):
        EmsconConfig(url="socket://127.0.0.1:1", coordinate_system=codec.CoordinateSystem.CCW)
    with pytest.raises(
        TrackerConfigError, match=r"length_unit must be one of \['ft', 'in', 'm', 'mm', 'um'\]"
    ):
        EmsconConfig(url="socket://127.0.0.1:1", length_unit="cm")
    with pytest.raises(TrackerConfigError, match=r"unknown emScon settings \['meas_time'\]"):
        EmsconConfig.from_mapping({"url": "socket://127.0.0.1:1", "meas_time": 1.0})
    with pytest.raises(TrackerConnectionError, match="cannot open") as refused:
        EmsconTracker(EmsconConfig(url="socket://127.0.0.1:1")).connect()
    assert refused.value.remedy in str(refused.value)  # what to do next is part of the message


# ---- faults ----------------------------------------------------------------------------------------------
def _locked(url, cell, **options) -> EmsconTracker:
    tracker = _tracker(url, **options)
    tracker.point_at(cell.smr_center_tracker(SMR))
    return tracker


def test_beam_break_on_the_next_measurements(url, server_thread, cell):
    tracker = _locked(url, cell)
    _fault(server_thread, kind="beam_break", count=2)
    for _ in range(2):
        start = time.monotonic()
        with pytest.raises(NoTargetError):
            tracker.measure()
        assert time.monotonic() - start < MEAS_S + tracker.config.measurement_margin_s
    assert tracker.last_async_error is not None
    assert tracker.measure(shots=2).shots_used == 2
    tracker.close()


def test_no_target_until_cleared(url, server_thread, cell):
    tracker = _locked(url, cell)
    _fault(server_thread, kind="no_target")
    start = time.monotonic()
    with pytest.raises(NoTargetError):
        tracker.measure()
    assert time.monotonic() - start < MEAS_S + tracker.config.measurement_margin_s
    assert tracker.state().target_locked is False
    server_thread.call(server_thread.server.control_handlers()["tracker.clear"], {})
    tracker.measure()
    tracker.close()


def test_slow_answers_time_out_then_recover(url, server_thread, cell):
    tracker = _locked(url, cell, measurement_margin_s=0.2)
    _fault(server_thread, kind="slow", delay_s=0.6)
    start = time.monotonic()
    with pytest.raises(TrackerTimeoutError):
        tracker.measure()
    assert time.monotonic() - start < MEAS_S + 0.2 + LATE_S
    _fault(server_thread, kind="clear")
    m = tracker.measure(shots=2)  # resyncs past the late answer and result
    assert np.linalg.norm(m.p_tracker_m - cell.smr_center_tracker(SMR)) < 1e-3
    tracker.close()


def test_garbage_bytes_give_a_protocol_error_with_the_bytes_then_recover(url, server_thread, cell):
    tracker = _locked(url, cell)
    _fault(server_thread, kind="garbage", n_bytes=40)
    start = time.monotonic()
    with pytest.raises(TrackerProtocolError) as info:
        tracker.measure()
    assert time.monotonic() - start < MEAS_S + tracker.config.measurement_margin_s
    assert info.value.data[:4] == b"\xff\xff\xff\x7f"
    tracker.measure()
    tracker.close()


@pytest.mark.parametrize("when", ["next", "now"])
def test_dropped_connection_recovers_on_the_next_call(url, server_thread, cell, when):
    """TCP: the connection closes (typed error, the next call reconnects). Serial line (direct or behind
    RFC 2217): it goes silent (timeout); once it is back the next call resyncs. No reconnecting by hand."""
    tracker = _locked(url, cell, measurement_margin_s=0.3)
    _fault(server_thread, kind="drop", when=when)
    serial_line = not url.startswith("socket://")  # a pty, or a pty behind an RFC 2217 server
    start = time.monotonic()
    with pytest.raises(TrackerTimeoutError if serial_line else TrackerConnectionError):
        tracker.measure()
    assert time.monotonic() - start < MEAS_S + 0.3 + LATE_S
    if serial_line:
        _fault(server_thread, kind="clear")
    else:
        assert not tracker.connected
    tracker.measure()
    assert tracker.connected
    tracker.close()


def test_two_clients_share_the_server_state(server_thread, cell):
    with _tracker(server_thread.server.url) as a, _tracker(server_thread.server.url) as b:
        a.point_at(cell.smr_center_tracker(SMR))
        assert b.measure().p_tracker_m == pytest.approx(cell.smr_center_tracker(SMR), abs=1e-3)
        assert a.state().target_locked


def test_external_clock_as_inside_hil_sim(cell):
    """With advance_clock=False the fake waits for the clock's owner (hil sim's clock task) instead."""
    server = EmsconServer(cell, config=EmsconServerConfig(initialized=True, advance_clock=False))
    thread = ServerThread(server)
    with thread:

        async def clock():  # 10x faster than wall time, ticking every 2 ms
            while True:
                await asyncio.sleep(0.002)
                cell.advance_time(0.02)

        task = thread.call(lambda: thread.loop.create_task(clock()))
        with _tracker(server.url, meas_time_s=0.2, reflector="RRR 0.5in") as tracker:
            assert tracker.state().reflector_id == 2 and server.state.reflector_id == 2
            tracker.point_at(cell.smr_center_tracker(SMR))
            t0_sim, t0_wall = cell.time_s, time.monotonic()
            tracker.measure(shots=3)
            sim_s, wall_s = cell.time_s - t0_sim, time.monotonic() - t0_wall
        thread.call(task.cancel)
        thread.run(asyncio.sleep(0.01))
    assert sim_s >= 3 * 0.2
    assert wall_s < 3 * 0.2  # simulated time ran faster than the wall clock


@pytest.mark.parametrize("initialized", [True, False])
def test_initialize_only_when_the_tracker_is_not_initialized(cell, initialized):
    server = EmsconServer(cell, config=EmsconServerConfig(initialized=initialized, init_delay_s=0.01))
    with ServerThread(server):
        for _ in range(2):  # the second connection finds it initialized either way
            with _tracker(server.url) as tracker:
                assert tracker.initialized
                assert tracker.tracker_info["name"] == "AT901-LR"
        counts = server.state.command_counts
        assert counts["INITIALIZE"] == (0 if initialized else 1)
        assert counts["SET_UNITS"] == 2 and counts["EXIT_APPLICATION"] == 0


def test_one_command_in_flight_even_with_several_threads(server_thread, cell):
    with _tracker(server_thread.server.url) as tracker:
        tracker.point_at(cell.smr_center_tracker(SMR))
        with ThreadPoolExecutor(4) as pool:
            results = list(pool.map(lambda _: tracker.measure(shots=3), range(4)))
            states = list(pool.map(lambda _: tracker.state(), range(4)))
    assert all(r.shots_used == 3 for r in results) and all(s.target_locked for s in states)
    assert server_thread.server.state.busy_replies == 0


def test_unsolicited_events_are_tracked_between_answers(server_thread, cell):
    with _tracker(server_thread.server.url) as tracker:
        tracker.point_at(cell.smr_center_tracker(SMR))
        tracker.measure()
        assert tracker.meas_ready is True
        moved = cell.smr_center_tracker(SMR) + np.array([0.2, 0.0, 0.0])
        cell.place_smr(SMR, SmrLocation("fixed", point_m=tuple(moved)))
        time.sleep(0.1)  # the fake's tracking poll notices and sends an error packet and NotReady
        tracker.state()
        assert tracker.meas_ready is False
        assert tracker.last_async_error.status == codec.Status.NO_DISTANCE_SET
        changes = [p.change for _, p in tracker.events if isinstance(p, codec.StatusChangePacket)]
        assert codec.StatusChange.UNITS_CHANGED in changes
        assert changes[-1] == codec.StatusChange.MEAS_STATUS_NOT_READY


def test_settings_changed_by_another_client_are_applied_again(server_thread, cell):
    """Units are server-side state: if another client switches them, results must still come out right."""
    truth = cell.smr_center_tracker(SMR)
    mm_deg = {"length_unit": codec.LengthUnit.MILLIMETER, "angle_unit": codec.AngleUnit.DEGREE}
    with _tracker(server_thread.server.url) as a, _tracker(server_thread.server.url, **mm_deg) as b:
        a.point_at(truth)
        assert np.linalg.norm(a.measure().p_tracker_m - truth) < 1e-3  # a re-applied metres after b's setup
        assert a.foreign_setting_changes > 0
        b.measure()  # b notices a's units and applies millimetres again
        assert server_thread.server.state.units.length == codec.LengthUnit.MILLIMETER
        assert np.linalg.norm(a.measure().p_tracker_m - truth) < 1e-3
        assert np.linalg.norm(b.measure().p_tracker_m - truth) < 1e-3


def test_without_a_weather_monitor_the_distances_follow_the_meteo_entered():
    """A tracker without a weather monitor computes its refraction from the meteo a client enters: entered
    15 K below the hall's air, every distance comes out 0.93 ppm/K x 15 K short, about the tracker (the error
    the diagnosis' tracker_scale family looks for); asking it for a monitor is refused."""
    from fakes.cell import REFRACTION_PER_K

    cell = SimulatedCell(SimCellConfig(seed=1, tracker_mpe_const_m=1e-9, tracker_mpe_per_m=0.0))
    server = EmsconServer(cell, config=EmsconServerConfig(init_delay_s=0.01, weather_monitor=False))
    with ServerThread(server), _tracker(server.url) as tracker:
        truth = cell.smr_center_tracker(SMR)
        tracker.point_at(truth)
        hall_c = float(cell.meteo().temperature_c)
        tracker.set_environment(hall_c, 1013.25, 50.0)
        right = tracker.measure().p_tracker_m
        tracker.set_environment(hall_c - 15.0, 1013.25, 50.0)
        assert tracker.environment()[0] == pytest.approx(hall_c - 15.0)
        cold = tracker.measure().p_tracker_m
        settings = list(server.state.settings)
        settings[0] = codec.WeatherMonitorStatus.READ_AND_CALCULATE_REFRACTIONS
        with pytest.raises(TrackerCommandError, match="27"):
            tracker._exchange(codec.Command.SET_SYSTEM_SETTINGS, *settings)
    np.testing.assert_allclose(cold - right, truth * REFRACTION_PER_K * 15.0, atol=2e-7)
    assert np.linalg.norm(cold - right) > 3e-5  # 14 ppm of the 2.5 m: 35 um, far beyond the 1 nm noise
