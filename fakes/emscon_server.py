"""A fake Leica emScon tracker server speaking the TPI binary protocol over TCP and over a pseudo-terminal.

Results come from the simulated cell: the SMR the beam is locked on, in the tracker frame, with the cell's
noise model and the meteo of its clock. Server-side state (units, coordinate system, measurement mode,
reflector, system settings, environment, search parameters) is shared by every connection, as on a real
emScon server. Choices the fact sheet marks as assumptions (emscon_protocol.md §8) are made as it
recommends: failure answers are full size, "no target" is status 37 (configurable), a beam break during a
measurement is an error packet (command 49) instead of the result, Set* commands are followed by their
"...Changed" status event to every client, cylindrical/left-handed systems answer NotImplemented.
The fake's dStd equals its a-priori std (it does not model averaging within lMeasTime).

This module holds the server (listening, clients, the control channel) and its public names; the parts are
emscon_wire (client streams and framing), emscon_commands (the command set), emscon_measure (the beam and
the measurement), emscon_faults (fault injection) and emscon_state (configuration and shared state).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from fakes.emscon_commands import CommandSet
from fakes.emscon_faults import Faults
from fakes.emscon_measure import Beam
from fakes.emscon_state import EmsconServerConfig, Reflector, TrackerState
from fakes.emscon_wire import ClientStream, PtyLine

__all__ = ["EmsconServer", "EmsconServerConfig", "Reflector", "ServerThread", "main"]

log = logging.getLogger(__name__)


class EmsconServer:
    """The fake emScon server: `await start()`, `.url`, `await open_pty()`, `await close()`."""

    def __init__(
        self, cell, host: str = "127.0.0.1", port: int = 0, config: EmsconServerConfig | None = None
    ):
        self.cell = cell
        self.host = host
        self.requested_port = port
        self.config = config or EmsconServerConfig()
        self.faults = Faults()
        self.state = TrackerState.powered_on(self.config)
        self.beam = Beam(cell, self.config, self.state, self.faults, self.broadcast)
        self.commands = CommandSet(self.beam, self.broadcast)
        self.port: int | None = None
        self.pty_path: str | None = None
        self._server: asyncio.AbstractServer | None = None
        self._sessions: set[ClientStream] = set()
        self._poll_task: asyncio.Task | None = None
        self._pty: PtyLine | None = None

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    @property
    def sent_results(self) -> deque[bytes]:
        """The raw result packets sent (the last 1000), for tests."""
        return self.beam.sent_results

    # ---- lifecycle ---------------------------------------------------------------------------------------
    async def start(self) -> None:
        self.beam.loop = asyncio.get_running_loop()
        self._server = await asyncio.start_server(self._on_client, self.host, self.requested_port)
        self.port = self._server.sockets[0].getsockname()[1]
        if self.config.initial_lock_smr is not None:
            self.beam.lock(self.config.initial_lock_smr)
        self._poll_task = self.beam.loop.create_task(self.beam.poll())
        log.info("fake emScon tracker on %s", self.url)

    async def close(self) -> None:
        if self._poll_task is not None:
            self._poll_task.cancel()
        self.beam.stop_stream()
        for session in list(self._sessions):
            for task in list(session.tasks):
                task.cancel()
            session.shutdown()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        if self._pty is not None:
            self._pty.close()
            self._pty = None

    async def open_pty(self) -> str:
        """Serve the same protocol on a pseudo-terminal; returns the serial device path for the driver."""
        if self.beam.loop is None:
            self.beam.loop = asyncio.get_running_loop()
        self._pty = PtyLine(self.beam.loop)
        self.pty_path = self._pty.path
        session = ClientStream(self, self._pty.write, None)
        self._sessions.add(session)
        self._pty.listen(session)
        return self.pty_path

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        session = ClientStream(self, writer.write, writer.close)
        self._sessions.add(session)
        try:
            while not session.closed:
                data = await reader.read(65536)
                if not data:
                    break
                session.feed(data)
        except (ConnectionError, OSError):
            pass
        finally:
            for task in list(session.tasks):
                task.cancel()
            session.shutdown()

    def broadcast(self, *packets: bytes) -> None:
        for session in list(self._sessions):
            session.send(*packets)

    async def handle(self, session: ClientStream, packet: bytes, command: int) -> None:
        """Answer one command packet on `session` (unsolicited events go to every client)."""
        await self.commands.handle(session, packet, command)

    def forget(self, session: ClientStream) -> None:
        """A client stream closed."""
        self._sessions.discard(session)

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the server runs on (set by start() or open_pty())."""
        return self.beam.running_loop()

    def _call_in_loop(self, fn: Callable[[], object]) -> None:
        """Run fn on the server's loop (control handlers may be called from another thread)."""
        loop = self.beam.loop
        if loop is None:
            fn()
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            fn()
        else:
            loop.call_soon_threadsafe(fn)

    # ---- control channel (fault injection) ---------------------------------------------------------------
    def control_handlers(self) -> dict[str, Callable[[dict], dict]]:
        """Commands for the control channel: tracker.fault, tracker.clear, tracker.state, tracker.guide_beam."""
        return {
            "tracker.guide_beam": self._ctl_guide_beam,
            "tracker.fault": self._ctl_fault,
            "tracker.clear": self._ctl_clear,
            "tracker.state": self._ctl_state,
        }

    def _ctl_fault(self, request: dict) -> dict:
        """Inject a fault (see Faults.set_from_request for the kinds and their parameters)."""
        action = self.faults.set_from_request(request)
        if action == "block_beam":
            self._call_in_loop(self.beam.block)
        elif action == "drop_now":
            self._call_in_loop(self._drop_all)
        elif action == "clear":
            return self._ctl_clear(request)
        return {"ok": True, "faults": self.faults.to_dict()}

    def _ctl_guide_beam(self, request: dict) -> dict:
        """The operator's hand: catch the beam on SMR `smr_id` and let the tracker lock onto it."""
        smr_id = int(request.get("smr_id", 1))
        if smr_id not in self.cell.smr_ids:
            raise ValueError(f"no SMR {smr_id}; the cell has SMRs {self.cell.smr_ids}")
        if not self.beam.visible(smr_id):
            raise ValueError(f"SMR {smr_id} faces away from the tracker: the beam cannot be caught on it")
        self._call_in_loop(
            lambda: self.beam.acquire(np.asarray(self.cell.smr_center_tracker(smr_id), dtype=float))
        )
        return {"smr_id": smr_id}

    def _ctl_clear(self, request: dict) -> dict:
        was_blocked = self.faults.no_target
        self.faults.reset()
        if was_blocked:
            self._call_in_loop(self.beam.unblock)
        return {"ok": True, "faults": self.faults.to_dict()}

    def _drop_all(self) -> None:
        """TCP connections are closed; the serial line goes silent until the faults are cleared."""
        if self._pty is not None:
            self.faults.line_down = True
        for session in list(self._sessions):
            if not session.is_serial:
                session.shutdown()

    def _ctl_state(self, request: dict) -> dict:
        st = self.state
        return {
            "url": self.url,
            "pty": self.pty_path,
            "clients": len(self._sessions),
            "initialized": st.initialized,
            "locked_smr": st.locked_smr,
            "units": st.units.as_tuple(),
            "coordinate_system": int(st.cs),
            "meas_time_ms": st.meas_time_ms,
            "reflector_id": st.reflector_id,
            "system_settings": list(st.settings),
            "exit_requests": st.exit_requests,
            "commands": dict(st.command_counts),
            "busy_replies": st.busy_replies,
            "faults": self.faults.to_dict(),
        }


class ServerThread:
    """Run an EmsconServer on its own asyncio loop in a background thread (tests, benchmarks, scripts)."""

    def __init__(self, server: EmsconServer):
        self.server = server
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="emscon-fake", daemon=True)

    def __enter__(self) -> EmsconServer:
        self._thread.start()
        self.run(self.server.start())
        return self.server

    def run(self, coro, timeout: float = 10.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, fn: Callable, *args):
        """Call fn(*args) on the server loop and return its result."""

        async def _wrapper():
            return fn(*args)

        return self.run(_wrapper())

    def __exit__(self, *exc) -> None:
        try:
            self.run(self.server.close())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5)
            self.loop.close()


def main(argv: list[str] | None = None) -> int:
    """Run the fake tracker alone on its own simulated cell (for trying the driver by hand)."""
    import argparse
    import json

    from fakes.cell import SimCellConfig, SimulatedCell

    parser = argparse.ArgumentParser(description="Fake Leica emScon tracker on a simulated cell.")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to bind")
    parser.add_argument("--port", type=int, default=7000, help="TCP port (700 needs root)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell")
    parser.add_argument("--pty", action="store_true", help="also serve on a pseudo-terminal")
    parser.add_argument("--lock", type=int, default=None, help="SMR id locked at start")
    args = parser.parse_args(argv)
    from fakes.launch import is_loopback_host

    if not is_loopback_host(args.host):
        parser.error("--host must be a loopback address (127.0.0.0/8)")

    async def serve() -> None:
        cell = SimulatedCell(SimCellConfig(seed=args.seed))
        server = EmsconServer(cell, args.host, args.port, EmsconServerConfig(initial_lock_smr=args.lock))
        await server.start()
        pty = await server.open_pty() if args.pty else None
        print(json.dumps({"tracker": {"url": server.url, "pty": pty}}), flush=True)
        try:
            await asyncio.Event().wait()
        finally:
            await server.close()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
