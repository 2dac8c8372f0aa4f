"""The fake emScon server on the wire, with a bare socket client: every command of the subset, full-size
answers, answer-then-event and answer-then-result ordering, busy, unknown and malformed commands."""

import socket
import time

import numpy as np
import pytest

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, Status, StatusChange
from fakes.cell import SimCellConfig, SimulatedCell
from fakes.emscon_server import EmsconServer, EmsconServerConfig, ServerThread

pytestmark = [
    pytest.mark.sim,
    pytest.mark.timeout(30),
]  # starts a simulated cell or a fake server over sockets


class RawClient:
    """A minimal TPI client: send bytes, collect decoded packets until a condition holds."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        self.splitter = codec.FrameSplitter()
        self.seen: list = []

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def until(self, condition, timeout_s: float = 2.0) -> list:
        """Packets received until `condition(packet)` is true for one (inclusive)."""
        got = []
        deadline = time.monotonic() + timeout_s
        while True:
            while (raw := self.splitter.pop()) is not None:
                packet = codec.decode_server_packet(raw)
                got.append(packet)
                if condition(packet):
                    self.seen += got
                    return got
            assert time.monotonic() < deadline, f"condition not met; got {got}"
            self.splitter.extend(self.sock.recv(65536))

    def command(self, command: int, *params) -> tuple[codec.AnswerPacket, list]:
        """Send a command; return its answer and every packet received up to it."""
        self.send(codec.pack_command(command, *params))
        got = self.until(lambda p: isinstance(p, codec.AnswerPacket) and p.command == command)
        return got[-1], got

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def setup():
    cell = SimulatedCell(SimCellConfig(seed=2))
    server = EmsconServer(cell, config=EmsconServerConfig(initialized=True, initial_lock_smr=2))
    with ServerThread(server):
        client = RawClient(server.port)
        client.command(Command.SET_STATIONARY_MODE_PARAMS, 5, 0)  # 5 ms measurements
        yield cell, server, client
        client.close()


# (command, parameters, expected status) for every command of the subset except the measurement
SUBSET = [
    (Command.GET_SYSTEM_STATUS, (), 0),
    (Command.GET_TRACKER_STATUS, (), 0),
    (Command.SET_TEMPERATURE_RANGE, (1,), 0),
    (Command.GET_TEMPERATURE_RANGE, (), 0),
    (Command.SET_UNITS, (1, 1, 0, 0, 0), 0),
    (Command.GET_UNITS, (), 0),
    (Command.INITIALIZE, (), 0),
    (Command.SWITCH_LASER, (1,), 0),
    (Command.SET_STATION_ORIENTATION_PARAMS, (0.0,) * 6, 0),
    (Command.SET_STATION_ORIENTATION_PARAMS, (1.0,) + (0.0,) * 5, Status.NOT_IMPLEMENTED),
    (Command.GET_STATION_ORIENTATION_PARAMS, (), 0),
    (Command.SET_TRANSFORMATION_PARAMS, (0.0,) * 6 + (1.0,), 0),
    (Command.GET_TRANSFORMATION_PARAMS, (), 0),
    (Command.SET_ENVIRONMENT_PARAMS, (21.0, 1000.0, 40.0), 0),
    (Command.SET_ENVIRONMENT_PARAMS, (21.0, 100.0, 40.0), Status.METEO_DATA_OUT_OF_RANGE),
    (Command.GET_ENVIRONMENT_PARAMS, (), 0),
    (Command.SET_REFRACTION_PARAMS, (1.00027, 1.00027), 0),
    (Command.GET_REFRACTION_PARAMS, (), 0),
    (Command.SET_MEASUREMENT_MODE, (0,), 0),
    (Command.SET_CONTINUOUS_TIME_MODE_PARAMS, (10, 0, 0, 0), 0),
    (Command.SET_CONTINUOUS_TIME_MODE_PARAMS, (0, 0, 0, 0), Status.WRONG_PARAMETER),
    (Command.GET_CONTINUOUS_TIME_MODE_PARAMS, (), 0),
    (Command.SET_MEASUREMENT_MODE, (1,), 0),  # continuous time
    (Command.SET_MEASUREMENT_MODE, (2,), Status.NOT_IMPLEMENTED),  # continuous distance: not modelled
    (Command.SET_MEASUREMENT_MODE, (0,), 0),
    (Command.GET_MEASUREMENT_MODE, (), 0),
    (Command.SET_COORDINATE_SYSTEM_TYPE, (7,), 0),
    (Command.SET_COORDINATE_SYSTEM_TYPE, (4,), Status.NOT_IMPLEMENTED),
    (Command.GET_COORDINATE_SYSTEM_TYPE, (), 0),
    (Command.SET_STATIONARY_MODE_PARAMS, (5, 1), 0),
    (Command.SET_STATIONARY_MODE_PARAMS, (0, 1), Status.PARAMETER1_OUT_OF_RANGE_NOK),
    (Command.GET_STATIONARY_MODE_PARAMS, (), 0),
    (Command.SET_REFLECTOR, (2,), 0),
    (Command.SET_REFLECTOR, (9,), Status.WRONG_PARAMETER1),
    (Command.GET_REFLECTOR, (), 0),
    (Command.SET_SEARCH_PARAMS, (50.0, 3000), 0),
    (Command.GET_SEARCH_PARAMS, (), 0),
    (Command.SET_SYSTEM_SETTINGS, (1, 0, 0, 1, 1, 0, 0, 1, 0), 0),
    (Command.GET_SYSTEM_SETTINGS, (), 0),
    (Command.STOP_MEASUREMENT, (), 0),
    (Command.CHANGE_FACE, (), 0),
    (Command.GET_FACE, (), 0),
    (Command.GET_DIRECTION, (), 0),
    (Command.SET_STATISTIC_MODE, (1, 0), 0),
    (Command.GET_STATISTIC_MODE, (), 0),
    (Command.GET_TP_INFO, (), 0),
    (Command.SET_LONG_SYSTEM_PARAMETER, (codec.SP_TCP_COMMAND_QUEUE_SIZE, 0), 0),
    (Command.SET_LONG_SYSTEM_PARAMETER, (codec.SP_TCP_COMMAND_QUEUE_SIZE, 5), Status.NOT_IMPLEMENTED),
    (Command.GET_LONG_SYSTEM_PARAMETER, (codec.SP_TCP_COMMAND_QUEUE_SIZE,), 0),
    (Command.SET_DOUBLE_SYSTEM_PARAMETER, (1000, 0.5), 0),
    (Command.GET_DOUBLE_SYSTEM_PARAMETER, (1000,), 0),
    (Command.GET_MEASUREMENT_STATUS_INFO, (), 0),
    (Command.GET_CURRENT_PRISM_POSITION, (), 0),
    (Command.GET_OBJECT_TEMPERATURE, (), 0),
    (Command.CLEAR_COMMAND_QUEUE, (0,), 0),
    (Command.GET_TRACKER_INFO, (), 0),
    (Command.GET_SYSTEM_SOFTWARE_VERSION, (), 0),
    (Command.FIND_REFLECTOR, (3000.0,), None),
    (Command.POINT_LASER, (1000.0, 0.0, 0.0), 0),
    (Command.POINT_LASER_HVD, (0.0, 90.0, 1000.0), 0),
    (Command.GO_POSITION_HVD, (0.0, 90.0, 1000.0, 1), 0),
    (Command.GO_POSITION, (1000.0, 0.0, 0.0, 1), 0),
    (Command.GO_BIRD_BATH, (), 0),
    (Command.GO_BIRD_BATH2, (1,), 0),
]


def test_every_command_of_the_subset_answers_at_full_size(setup):
    _, _, client = setup
    for command, params, expected in SUBSET:
        answer, _ = client.command(command, *params)
        assert expected is None or answer.status == expected, (command.name, answer.status)
        assert len(answer.raw) == 16 + codec.answer_values(command).size, command.name
        if answer.status == 0 and answer.values is not None and command != Command.GET_REFLECTORS:
            assert len(answer.values) == len(codec.answer_values(command).unpack(bytes(len(answer.raw) - 16)))


def test_get_reflectors_answers_once_per_reflector(setup):
    _, server, client = setup
    client.send(codec.pack_command(Command.GET_REFLECTORS))
    answers = []
    while len(answers) < len(server.config.reflectors):
        answers += [
            p
            for p in client.until(lambda p: isinstance(p, codec.AnswerPacket))
            if isinstance(p, codec.AnswerPacket)
        ]
    assert [a.values[1] for a in answers] == [1, 2, 3]
    assert {a.values[0] for a in answers} == {3}
    assert codec.decode_name(answers[0].values[4]) == "RRR 1.5in"


def test_set_commands_answer_then_announce_the_change(setup):
    _, _, client = setup
    _, before = client.command(Command.SET_UNITS, 1, 1, 0, 0, 0)
    assert not [p for p in before if getattr(p, "change", None) == StatusChange.UNITS_CHANGED]
    client.until(lambda p: getattr(p, "change", None) == StatusChange.UNITS_CHANGED)
    answer, _ = client.command(Command.GET_UNITS)
    assert answer.values == (1, 1, 0, 0, 0)


def test_start_measurement_answer_comes_before_the_result(setup):
    cell, _, client = setup
    client.send(codec.pack_command(Command.START_MEASUREMENT))
    got = client.until(lambda p: isinstance(p, codec.MeasResultPacket))
    kinds = [type(p).__name__ for p in got if not isinstance(p, codec.StatusChangePacket)]
    assert kinds[-2:] == ["AnswerPacket", "MeasResultPacket"]
    assert got[-1].data_type == codec.DataType.SINGLE_MEAS_RESULT and len(got[-1].raw) == 156
    assert np.linalg.norm(np.array(got[-1].values) - cell.smr_center_tracker(2)) < 1e-3


def test_a_second_command_while_one_is_pending_gets_server_busy(setup):
    _, _, client = setup
    client.send(codec.pack_command(Command.START_MEASUREMENT) + codec.pack_command(Command.GET_UNITS))
    busy = client.until(lambda p: isinstance(p, codec.AnswerPacket) and p.command == Command.GET_UNITS)[-1]
    assert busy.status == Status.SERVER_BUSY
    client.until(lambda p: isinstance(p, codec.MeasResultPacket))


def test_unknown_malformed_and_exit_commands_are_refused(setup):
    _, server, client = setup
    answer, _ = client.command(77)
    assert answer.status == Status.NOT_IMPLEMENTED and len(answer.raw) == 16
    client.send(codec.COMMAND_HEAD.pack(16, 0, Command.SET_UNITS) + bytes(4))  # SetUnits is 32 bytes
    answer = client.until(lambda p: isinstance(p, codec.AnswerPacket))[-1]
    assert answer.status == Status.WRONG_PARAMETER
    answer, _ = client.command(Command.EXIT_APPLICATION)
    assert answer.status == Status.NOT_IMPLEMENTED
    assert server.state.exit_requests == 1  # a real server would have stopped: the fake refuses and counts


def test_laser_off_means_no_target_until_on_and_reacquired(setup):
    cell, _, client = setup
    client.command(Command.SWITCH_LASER, 0)
    answer, _ = client.command(Command.START_MEASUREMENT)
    assert answer.status == Status.NO_DISTANCE_SET
    assert client.command(Command.GET_SYSTEM_STATUS)[0].values[2] == codec.LaserStatus.LASER_OFF
    client.command(Command.SWITCH_LASER, 1)
    assert client.command(Command.GO_POSITION, *cell.smr_center_tracker(2), 1)[0].status == 0
    assert client.command(Command.START_MEASUREMENT)[0].status == 0


def test_go_position_hvd_locks_in_spherical_and_reports_in_the_current_units(setup):
    cell, _, client = setup
    client.command(Command.SET_UNITS, codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE, 0, 0, 0)
    client.command(Command.SET_COORDINATE_SYSTEM_TYPE, codec.CoordinateSystem.RHR)
    p = cell.smr_center_tracker(3)
    units = codec.Units(codec.LengthUnit.MILLIMETER, codec.AngleUnit.DEGREE)
    hz, v, d = codec.cartesian_to_wire(p, codec.CoordinateSystem.SCC, units)
    assert client.command(Command.GO_POSITION_HVD, hz, v, d + 20.0, 1)[0].status == 0  # 2 cm long: found
    info = client.command(Command.GET_MEASUREMENT_STATUS_INFO)[0].values[1]
    assert info & codec.MSI_REFLECTOR_FOUND
    prism = client.command(Command.GET_CURRENT_PRISM_POSITION)[0].values
    np.testing.assert_allclose(prism, p * 1000.0, atol=1e-9)
    direction = client.command(Command.GET_DIRECTION)[0].values
    np.testing.assert_allclose(direction, (hz, v), atol=1e-9)
