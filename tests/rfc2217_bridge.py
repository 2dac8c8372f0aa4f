"""Test support: an RFC 2217 (telnet COM-port control) server in front of a serial device, as a
terminal server in a cell would be, built on pyserial's own `PortManager`, so the driver can be
tested with an `rfc2217://` URL against the fake tracker's pseudo-terminal."""

from __future__ import annotations

import contextlib
import socket
import threading

import serial
import serial.rfc2217


class Rfc2217Bridge:
    """Serve one serial device on a loopback TCP port with RFC 2217; one client at a time."""

    def __init__(self, device: str, host: str = "127.0.0.1") -> None:
        self._serial = _ThreeWireSerial(device, timeout=0.05)
        self._listener = socket.create_server((host, 0))
        self._listener.settimeout(0.2)
        self.url = f"rfc2217://{host}:{self._listener.getsockname()[1]}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="rfc2217-bridge", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with client:
                self._bridge(client)

    def _bridge(self, client: socket.socket) -> None:
        client.settimeout(0.05)
        manager = serial.rfc2217.PortManager(self._serial, _SocketWriter(client))
        while not self._stop.is_set():
            data = self._serial.read(4096)
            if data:
                client.sendall(b"".join(manager.escape(data)))
            try:
                incoming = client.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not incoming:
                return
            self._serial.write(b"".join(manager.filter(incoming)))

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._listener.close()
        self._thread.join(timeout=2)
        self._serial.close()


class _SocketWriter:
    """The `write` end PortManager sends its telnet negotiation through."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock

    def write(self, data: bytes) -> None:
        self._sock.sendall(data)


class _ThreeWireSerial(serial.Serial):
    """A serial line without modem-control wires (TX, RX, ground), like a pseudo-terminal: RTS/DTR/break
    requests are accepted and ignored, and the status lines read as a plain connected line."""

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
