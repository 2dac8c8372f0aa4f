"""The fake emScon tracker's wire: client byte streams (TCP or a pseudo-terminal) cut into command packets.

A stream runs one command at a time (a second one is answered ServerBusy), applies the faults that act on
the wire (a dropped connection or silent line, a slow answer, injected or garbled bytes) and writes the
answers with the framing fault in force (normal, byte by byte, or a command's output in one write).
"""

from __future__ import annotations

import asyncio
import logging
import os
import tty
from collections.abc import Awaitable, Callable
from typing import Protocol

from drivers import emscon_codec as codec
from drivers.emscon_codec import Status
from fakes.emscon_faults import Faults, garbage
from fakes.emscon_state import TrackerState

log = logging.getLogger("fakes.emscon_server")

_FLUSH = object()  # writer-queue marker: end of a command's output (used by the "merged" framing mode)


class StreamOwner(Protocol):
    """What a client stream needs of the server that owns it."""

    @property
    def faults(self) -> Faults: ...

    @property
    def state(self) -> TrackerState: ...

    def handle(self, stream: ClientStream, packet: bytes, command: int) -> Awaitable[None]:
        """Answer one command packet on the stream."""
        ...

    def forget(self, stream: ClientStream) -> None:
        """The stream closed: it is no longer a client."""
        ...


class ClientStream:
    """One client byte stream (a TCP connection or the pty): splits packets, runs one command at a time."""

    def __init__(self, owner: StreamOwner, write: Callable[[bytes], None], close: Callable[[], None] | None):
        self.owner = owner
        self._write = write
        self._close = close
        self.splitter = codec.FrameSplitter()
        self.busy = False
        self.closed = False
        self.queue: asyncio.Queue = asyncio.Queue()
        self.writer_task = asyncio.get_running_loop().create_task(self._writer())
        self.tasks: set[asyncio.Task] = set()

    @property
    def is_serial(self) -> bool:
        """The pty line (it has no close: a serial line cannot be hung up from this end)."""
        return self._close is None

    def send(self, *packets: bytes, flush: bool = True) -> None:
        """Queue packets for the client; flush ends the command's output (merged framing sends it at once)."""
        if self.closed or (self.is_serial and self.owner.faults.line_down):
            return
        for packet in packets:
            self.queue.put_nowait(packet)
        if flush:
            self.queue.put_nowait(_FLUSH)

    async def _writer(self) -> None:
        """Write queued packets as the framing fault says: whole, byte by byte, or a command's output merged."""
        held: list[bytes] = []
        while True:
            item = await self.queue.get()
            mode = self.owner.faults.framing
            if item is _FLUSH:
                if held:
                    self._write(b"".join(held))
                    held.clear()
                continue
            if mode == "merged":
                held.append(item)
            elif mode == "bytewise":
                for i in range(len(item)):
                    self._write(item[i : i + 1])
                    await asyncio.sleep(0.0002)
            else:
                self._write(item)

    def feed(self, data: bytes) -> None:
        """Bytes from the client: split packets and start each command, or answer ServerBusy while one runs."""
        if self.is_serial and self.owner.faults.line_down:
            return
        try:
            packets = self.splitter.feed(data)
        except codec.CodecError as exc:
            log.warning("fake tracker: framing error from client, closing: %s", exc)
            packets = exc.packets
            self.splitter.reset()
            self.shutdown()
        for packet in packets:
            command = codec.COMMAND_HEAD.unpack_from(packet)[2] if len(packet) >= 12 else -1
            if self.busy:
                self.owner.state.busy_replies += 1
                self.send(codec.pack_answer(command, Status.SERVER_BUSY))
                continue
            self.busy = True
            task = asyncio.get_running_loop().create_task(self._run(packet, command))
            self.tasks.add(task)
            task.add_done_callback(self.tasks.discard)

    async def _run(self, packet: bytes, command: int) -> None:
        """Run one command, after the wire faults (drop, slow, inject, garbage) have had their say."""
        try:
            faults = self.owner.faults
            if faults.drop_next_command:
                faults.drop_next_command = False
                if self.is_serial:  # a serial line cannot be closed from this end: it goes silent
                    faults.line_down = True
                else:
                    self.shutdown()
                return
            if faults.slow_delay_s > 0:
                await asyncio.sleep(faults.slow_delay_s)
            if faults.inject is not None:
                data, faults.inject = faults.inject, None
                self.send(data)
                return
            if faults.garbage_bytes > 0:
                n, faults.garbage_bytes = faults.garbage_bytes, 0
                self.send(garbage(n))
            await self.owner.handle(self, packet, command)
        except Exception:  # a fake must survive its own bugs long enough to report them
            log.exception("fake tracker: command %s failed", command)
            self.send(codec.pack_answer(command, Status.UNKNOWN))
        finally:
            self.busy = False
            self.send(flush=True)

    def shutdown(self) -> None:
        """Close the stream (TCP: the connection) and leave the owner's clients."""
        if self.closed:
            return
        self.closed = True
        self.writer_task.cancel()
        if self._close is not None:
            self._close()
        self.owner.forget(self)


class PtyLine:
    """A pseudo-terminal serving as the tracker's serial line: its master end on the event loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: a clean 8-bit line
        os.set_blocking(master, False)
        self.loop = loop
        self.fds: tuple[int, int] | None = (master, slave)
        self.path = os.ttyname(slave)  # the serial device for the driver
        self._out = bytearray()

    def listen(self, stream: ClientStream) -> None:
        """Feed what the driver writes on the line into `stream`."""
        assert self.fds is not None
        self.loop.add_reader(self.fds[0], self._readable, stream)

    def _readable(self, stream: ClientStream) -> None:
        if self.fds is None:
            return
        try:
            data = os.read(self.fds[0], 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # EIO while no one holds the slave open (we do, so this is rare)
            return
        if data:
            stream.feed(data)

    def write(self, data: bytes) -> None:
        """Send bytes to the driver; what the line does not take now is sent when it can."""
        self._out.extend(data)
        self._flush()

    def _flush(self) -> None:
        if self.fds is None:
            return
        master = self.fds[0]
        try:
            while self._out:
                n = os.write(master, self._out)
                del self._out[:n]
        except BlockingIOError:
            self.loop.add_writer(master, self._flush)
            return
        except OSError:
            self._out.clear()
        self.loop.remove_writer(master)

    def close(self) -> None:
        """Stop serving the line and close both ends."""
        if self.fds is None:
            return
        master, slave = self.fds
        self.loop.remove_reader(master)
        self.loop.remove_writer(master)
        os.close(master)
        os.close(slave)
        self.fds = None
