"""Client of a simulated cell's control channel (see fakes/control_channel.py)."""

from __future__ import annotations

import contextlib
import io
import json
import socket
import threading
from typing import Any


class ControlError(RuntimeError):
    """The cell refused a control command (the message says why)."""


class ControlClient:
    """Blocking JSON-lines client: `call("robot.fault", kind="protective_stop")` returns the result."""

    def __init__(self, address: str, timeout_s: float = 10.0):
        host, _, port = address.rpartition(":")
        self.host, self.port = host, int(port)
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._file: io.BufferedIOBase | None = None
        self._lock = threading.Lock()

    def _connect(self) -> None:
        self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        self._file = self._sock.makefile("rwb")

    def call(self, cmd: str, **arguments: Any) -> Any:
        """Send one command; its JSON result, whose shape the command defines (see `help`)."""
        with self._lock:
            if self._sock is None or self._file is None:
                self._connect()
            assert self._file is not None  # _connect opened it or raised
            try:
                self._file.write((json.dumps({"cmd": cmd, **arguments}) + "\n").encode())
                self._file.flush()
                line = self._file.readline()
            except OSError:
                self.close()
                raise
            if not line:
                self.close()
                raise ConnectionError(f"control channel {self.host}:{self.port} closed")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise ControlError(f"{cmd}: {reply.get('error')}")
        return reply.get("result")

    def close(self) -> None:
        for item in (self._file, self._sock):
            if item is not None:
                with contextlib.suppress(OSError):
                    item.close()
        self._sock = self._file = None

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
