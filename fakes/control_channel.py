"""The simulated cell's control channel: JSON lines over loopback TCP, dispatched to named handlers.

Request: one line `{"cmd": "name", ...arguments}`. Reply: one line `{"ok": true, "result": ...}` or
`{"ok": false, "error": "..."}`. Handlers are plain functions of the request dict returning something
JSON-serialisable; any server of the cell adds its own with `add_handlers`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable, Mapping

from hil.data.jsonable import to_jsonable

log = logging.getLogger(__name__)

Handler = Callable[[dict], object]
MAX_REQUEST_BYTES = 1 << 20


class ControlChannel:
    """Loopback JSON-lines server dispatching `cmd` to registered handlers."""

    def __init__(self, host: str, port: int = 0):
        self.host = host
        self.port = port
        self.handlers: dict[str, Handler] = {"help": lambda request: sorted(self.handlers)}
        self._server: asyncio.AbstractServer | None = None

    def add_handlers(self, handlers: Mapping[str, Handler]) -> None:
        clash = set(handlers) & set(self.handlers)
        if clash:
            raise ValueError(f"control commands registered twice: {sorted(clash)}")
        self.handlers.update(handlers)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port, limit=MAX_REQUEST_BYTES)
        self.port = self._server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)

    def dispatch(self, request: dict) -> dict:
        """Run one request; never raises."""
        name = request.get("cmd") if isinstance(request, dict) else None
        handler = self.handlers.get(name) if isinstance(name, str) else None
        if handler is None:
            return {"ok": False, "error": f"unknown command {name!r}; known: {sorted(self.handlers)}"}
        try:
            return {"ok": True, "result": to_jsonable(handler(request))}
        except Exception as exc:  # a bad request must not take the cell down
            log.warning("control command %s failed: %s", name, exc)
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                line = await reader.readline()
                if not line:
                    break
                try:
                    request = json.loads(line)
                except json.JSONDecodeError as exc:
                    reply = {"ok": False, "error": f"request is not JSON: {exc}"}
                else:
                    reply = self.dispatch(request)
                writer.write((json.dumps(reply) + "\n").encode())
                await writer.drain()
        except ConnectionError:
            pass
        except (asyncio.LimitOverrunError, ValueError) as exc:  # line beyond MAX_REQUEST_BYTES, bad UTF-8
            log.warning("control channel: dropping a client that broke the JSON-lines protocol: %s", exc)
        finally:
            with contextlib.suppress(Exception):
                writer.close()
