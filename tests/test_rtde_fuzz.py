"""Property test: random malformed RTDE traffic never crashes or wedges the fake controller."""

from __future__ import annotations

import socket
import struct
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fakes.launch import sim_cell

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets

RTDE_TYPES = [ord(c) for c in "VvOISPUM"] + [0, 1, 255]


@pytest.fixture(scope="module")
def cell():
    with sim_cell(robot="ur10e", time_scale=1.0) as running:
        yield running


def _handshake_ok(host: str) -> bool:
    """A fresh client still gets its protocol-version and controller-version replies promptly."""
    with socket.create_connection((host, 30004), timeout=2.0) as sock:
        sock.settimeout(2.0)
        sock.sendall(struct.pack(">HBH", 5, ord("V"), 2) + struct.pack(">HB", 3, ord("v")))
        data = b""
        while len(data) < 4 + 19:
            chunk = sock.recv(64)
            if not chunk:
                return False
            data += chunk
        return data[2] == ord("V") and data[3] == 1 and data[6] == ord("v")


def _frame(kind: int, payload: bytes, lie: int | None) -> bytes:
    size = 3 + len(payload) if lie is None else lie
    return struct.pack(">HB", size & 0xFFFF, kind) + payload


messages = st.tuples(
    st.sampled_from(RTDE_TYPES),
    st.binary(max_size=300),
    st.one_of(st.none(), st.integers(0, 0xFFFF)),
)
setup_prefix = st.sampled_from(
    [
        b"",
        _frame(ord("I"), b"input_int_register_30,input_double_register_30,", None),
        _frame(ord("O"), struct.pack(">d", 500.0) + b"timestamp,actual_q,", None)
        + _frame(ord("S"), b"", None),
        _frame(ord("O"), struct.pack(">d", 500.0) + b"no_such_variable,", None),
    ]
)


@pytest.mark.timeout(120)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(prefix=setup_prefix, garbage=st.lists(messages, min_size=1, max_size=6), raw=st.binary(max_size=64))
def test_malformed_packets_never_wedge_the_fake(cell, prefix, garbage, raw):
    with socket.create_connection((cell.host, 30004), timeout=2.0) as sock:
        stream = prefix + b"".join(_frame(k, p, lie) for k, p, lie in garbage) + raw
        try:
            sock.sendall(stream)
            time.sleep(0.005)
        except OSError:
            pass  # the fake may close a connection that broke the protocol
    assert cell.process.poll() is None, cell.log_tail()
    assert _handshake_ok(cell.host), cell.log_tail()


@pytest.mark.timeout(30)
def test_fake_still_serves_a_real_client_after_the_fuzzing(cell):
    rtde_receive = pytest.importorskip("rtde_receive")
    rx = rtde_receive.RTDEReceiveInterface(cell.host)
    try:
        t0 = rx.getTimestamp()
        time.sleep(0.1)
        assert rx.getTimestamp() > t0
        assert len(rx.getActualQ()) == 6
    finally:
        rx.disconnect()
