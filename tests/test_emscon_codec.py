"""emScon TPI codec: sizes and bytes from the fact sheet, round trips, the frame splitter, CS and units."""

import numpy as np
import pytest

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, CoordinateSystem, DataType


def test_example_bytes_from_the_fact_sheet():
    assert codec.pack_command(Command.INITIALIZE).hex(" ") == "0c 00 00 00 00 00 00 00 07 00 00 00"
    assert (
        codec.pack_answer(Command.INITIALIZE, 0).hex(" ") == "10 00 00 00 00 00 00 00 07 00 00 00 00 00 00 00"
    )
    assert codec.pack_command(Command.START_MEASUREMENT).hex(" ") == "0c 00 00 00 00 00 00 00 31 00 00 00"
    units = codec.Units(codec.LengthUnit.MILLIMETER, codec.AngleUnit.RADIAN, 0, codec.PressureUnit.MBAR, 0)
    assert codec.pack_command(Command.SET_UNITS, *units.as_tuple()) == bytes.fromhex(
        "20000000 00000000 05000000 01000000 00000000 00000000 00000000 00000000"
    )
    assert codec.pack_command(Command.SET_STATIONARY_MODE_PARAMS, 1000, 0).hex(" ") == (
        "14 00 00 00 00 00 00 00 1c 00 00 00 e8 03 00 00 00 00 00 00"
    )
    assert codec.pack_status_change(27).hex(" ") == "0c 00 00 00 08 00 00 00 1b 00 00 00"
    assert codec.pack_error(49, 37).hex(" ") == "10 00 00 00 01 00 00 00 31 00 00 00 25 00 00 00"
    result = codec.pack_single_meas_result(0, (3000.0, 0, 0), (0, 0, 0), 0, (0, 0, 0), 0, (20, 1013, 45))
    assert result[:28].hex(" ") == (
        "9c 00 00 00 02 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 70 a7 40"
    )


@pytest.mark.parametrize(
    ("command", "size"),
    [
        (Command.GET_SYSTEM_STATUS, 56),
        (Command.GET_TRACKER_STATUS, 20),
        (Command.GET_UNITS, 36),
        (Command.GET_STATIONARY_MODE_PARAMS, 24),
        (Command.GET_REFLECTORS, 100),
        (Command.GET_SYSTEM_SETTINGS, 52),
        (Command.GET_ENVIRONMENT_PARAMS, 40),
        (Command.GET_SEARCH_PARAMS, 28),
        (Command.GET_DIRECTION, 32),
        (Command.GET_MEASUREMENT_STATUS_INFO, 24),
        (Command.START_MEASUREMENT, 16),
    ],
)
def test_answer_sizes_match_the_compiled_headers(command, size):
    assert len(codec.pack_answer(command, 0)) == size
    assert len(codec.pack_answer(command, 39)) == size  # failures are full size, zero-filled


@pytest.mark.parametrize(
    ("command", "size"),
    [
        (Command.SET_UNITS, 32),
        (Command.SET_SYSTEM_SETTINGS, 48),
        (Command.SET_ENVIRONMENT_PARAMS, 36),
        (Command.GO_POSITION, 40),
        (Command.FIND_REFLECTOR, 20),
        (Command.SET_SEARCH_PARAMS, 24),
        (Command.SET_STATISTIC_MODE, 20),
    ],
)
def test_command_sizes_match_the_compiled_headers(command, size):
    layout = codec.command_params(command)
    values = layout.unpack(bytes(layout.size))
    assert len(codec.pack_command(command, *values)) == size


def test_result_packets_round_trip_in_both_statistic_modes():
    for extended, size, data_type in (
        (False, 156, DataType.SINGLE_MEAS_RESULT),
        (True, 204, DataType.SINGLE_MEAS_RESULT2),
    ):
        raw = codec.pack_single_meas_result(
            0,
            (1.0, 2.0, 3.0),
            (4e-6, 5e-6, 6e-6),
            9e-6,
            (7e-6, 8e-6, 9e-6),
            1.5e-5,
            (20.5, 1013.2, 44.0),
            extended,
        )
        assert len(raw) == size
        packet = codec.decode_server_packet(raw)
        assert packet.data_type == data_type
        assert packet.values == (1.0, 2.0, 3.0)
        assert packet.std == (4e-6, 5e-6, 6e-6)
        assert packet.std_total == 9e-6
        assert packet.apriori_std == (7e-6, 8e-6, 9e-6)
        assert packet.apriori_std_total == 1.5e-5
        assert (packet.temperature, packet.pressure, packet.humidity) == (20.5, 1013.2, 44.0)


def test_reflector_answer_carries_a_utf16_name():
    raw = codec.pack_answer(Command.GET_REFLECTORS, 0, 3, 2, 6, 0.0, codec.encode_name("RRR 0.5in"))
    packet = codec.decode_server_packet(raw)
    assert packet.values[:3] == (3, 2, 6)
    assert codec.decode_name(packet.values[4]) == "RRR 0.5in"
    assert raw[36:54] == "RRR 0.5in".encode("utf-16-le")


def test_failed_answers_carry_no_values_and_short_failures_are_accepted():
    full = codec.decode_server_packet(codec.pack_answer(Command.GET_SYSTEM_STATUS, 39))
    short = codec.decode_server_packet(codec.ANSWER_HEAD.pack(16, 0, Command.GET_SYSTEM_STATUS, 39))
    assert full.status == short.status == 39
    assert full.values is None and short.values is None
    with pytest.raises(codec.CodecError, match="expected 56"):
        codec.decode_server_packet(codec.ANSWER_HEAD.pack(16, 0, Command.GET_SYSTEM_STATUS, 0))


def test_client_packets_are_checked_against_their_layout():
    packet = codec.decode_client_packet(codec.pack_command(Command.GO_POSITION, 1.0, 2.0, 3.0, 1))
    assert packet.command == Command.GO_POSITION and packet.params == (1.0, 2.0, 3.0, 1)
    with pytest.raises(codec.CodecError, match="must be 40 bytes"):
        codec.decode_client_packet(codec.COMMAND_HEAD.pack(36, 0, Command.GO_POSITION) + bytes(24))


def _stream() -> tuple[bytes, list[bytes]]:
    packets = [
        codec.pack_status_change(6),
        codec.pack_answer(Command.START_MEASUREMENT, 0),
        codec.pack_status_change(26),
        codec.pack_single_meas_result(
            0, (1.0, 2.0, 3.0), (1e-6,) * 3, 2e-6, (1e-6,) * 3, 2e-6, (20.0, 1013.0, 45.0)
        ),
        codec.pack_error(49, 37),
        codec.pack_answer(Command.GET_REFLECTORS, 0, 1, 1, 5, 0.0, codec.encode_name("RRR 1.5in")),
    ]
    return b"".join(packets), packets


def test_splitter_cuts_every_packet_for_every_split_point():
    stream, packets = _stream()
    for cut in range(1, len(stream)):
        splitter = codec.FrameSplitter()
        got = splitter.feed(stream[:cut]) + splitter.feed(stream[cut:])
        assert got == packets, cut
        assert len(splitter) == 0


def test_splitter_survives_byte_by_byte_and_one_chunk():
    stream, packets = _stream()
    splitter = codec.FrameSplitter()
    got = []
    for i in range(len(stream)):
        assert splitter.bytes_needed() >= 1
        got += splitter.feed(stream[i : i + 1])
    assert got == packets
    assert codec.FrameSplitter().feed(stream) == packets


@pytest.mark.parametrize("size", [0, 7, 11, -5, 2**31 - 1, 70000])
def test_splitter_rejects_implausible_sizes_keeping_packets_before(size):
    good = codec.pack_status_change(27)
    splitter = codec.FrameSplitter()
    with pytest.raises(codec.CodecError, match="implausible packet size") as info:
        splitter.feed(good + size.to_bytes(4, "little", signed=True) + b"\0" * 12)
    assert info.value.packets == [good]
    assert info.value.data[:4] == size.to_bytes(4, "little", signed=True)
    splitter.reset()
    assert splitter.feed(good) == [good]


@pytest.mark.parametrize("cs", [CoordinateSystem.RHR, CoordinateSystem.SCC, CoordinateSystem.SCW])
@pytest.mark.parametrize(
    "units",
    [
        codec.Units(),
        codec.Units(codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE),
        codec.Units(codec.LengthUnit.INCH, codec.AngleUnit.GON),
        codec.Units(codec.LengthUnit.MICRON, codec.AngleUnit.RADIAN),
    ],
)
def test_coordinates_round_trip_through_every_cs_and_unit(cs, units):
    p = np.random.default_rng(3).uniform(-5, 5, (50, 3))
    np.testing.assert_allclose(
        codec.wire_to_cartesian(codec.cartesian_to_wire(p, cs, units), cs, units), p, atol=1e-12
    )


def test_spherical_convention_zenith_angle_and_counter_clockwise_hz():
    hz, v, d = codec.cartesian_to_wire(np.array([0.0, 2.0, 0.0]), CoordinateSystem.SCC, codec.Units())
    assert (hz, v, d) == pytest.approx((np.pi / 2, np.pi / 2, 2.0))
    hz, v, d = codec.cartesian_to_wire(np.array([0.0, 2.0, -2.0]), CoordinateSystem.SCW, codec.Units())
    assert (hz, v, d) == pytest.approx((-np.pi / 2, 3 * np.pi / 4, np.sqrt(8)))


def test_std_conversion_round_trips_in_spherical():
    p = np.array([1.0, 2.0, -0.5])
    units = codec.Units(codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE)
    sigma = np.array([1e-5, 2e-5, 3e-5])
    wire = codec.cartesian_std_to_wire(sigma, p, CoordinateSystem.SCC, units)
    values = codec.cartesian_to_wire(p, CoordinateSystem.SCC, units)
    np.testing.assert_allclose(
        codec.spherical_std_to_cartesian_m(wire, values, CoordinateSystem.SCC, units), sigma
    )


def test_meteo_units_round_trip():
    units = codec.Units(temperature=codec.TemperatureUnit.FAHRENHEIT, pressure=codec.PressureUnit.INHG)
    assert units.temperature_to_wire(20.0) == pytest.approx(68.0)
    assert units.temperature_from_wire(units.temperature_to_wire(21.3)) == pytest.approx(21.3)
    assert units.pressure_to_wire(1013.25) == pytest.approx(29.92, abs=0.01)
    with pytest.raises(ValueError):
        codec.Units.from_tuple((9, 0, 0, 0, 0))
