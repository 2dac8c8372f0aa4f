"""The RTDE server side of the fake UR controller: one `RtdeConnection` per client socket.

Answers the setup requests (V, v, O, I, S, P), applies client data packages to the controller's inputs,
and queues output data packages that the controller's clock pushes every cycle. Malformed input closes
that one connection and never touches the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from typing import Any, Protocol

from fakes import rtde_wire as w
from fakes.rtde_output import OutputPacker
from fakes.ur_modes import Personality

log = logging.getLogger(__name__)

MAX_BACKLOG_BYTES = 4 * 1024 * 1024  # a client that does not drain its socket gets dropped


class RtdeController(Protocol):
    """What an RTDE connection asks of the controller (fakes.ur_controller.UrController plays it)."""

    personality: Personality

    def next_output_recipe_id(self) -> int: ...

    def claim_inputs(self, conn: RtdeConnection, names: list[str]) -> set[str]: ...

    def rtde_disconnected(self, conn: RtdeConnection) -> None: ...

    def apply_inputs(self, values: dict[str, Any]) -> None: ...


class RtdeConnection:
    """State of one RTDE client: its recipes, whether it streams, and its writer."""

    def __init__(
        self, controller: RtdeController, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ):
        self.controller = controller
        self.reader = reader
        self.writer = writer
        self.output_recipe: w.Recipe | None = None
        self.packer: OutputPacker | None = None  # packs the output recipe's data packages, built on first use
        self.output_every_n_ticks = 1
        self.input_recipes: dict[int, w.Recipe] = {}
        self.streaming = False
        self.closed = False
        self.peer = writer.get_extra_info("peername")

    # ---- outbound -------------------------------------------------------------------------------
    def send(self, message_type: int, payload: bytes = b"") -> None:
        if self.closed:
            return
        transport = self.writer.transport
        if transport.is_closing():
            self.abort()
            return
        if transport.get_write_buffer_size() > MAX_BACKLOG_BYTES:
            log.warning("RTDE client %s does not drain its socket; dropping it", self.peer)
            self.abort()
            return
        self.writer.write(w.frame(message_type, payload))

    def send_package(self, payload: bytes) -> None:
        """Push one output data package (its payload from `OutputPacker.package`)."""
        self.send(w.DATA_PACKAGE, payload)

    def abort(self) -> None:
        """Drop the connection at once (fault injection, protocol violation, backlog)."""
        if not self.closed:
            self.closed = True
            self.streaming = False
            with contextlib.suppress(Exception):
                self.writer.transport.abort()

    # ---- inbound --------------------------------------------------------------------------------
    async def serve(self) -> None:
        log.info("RTDE client %s connected", self.peer)
        try:
            while not self.closed:
                header = await self.reader.readexactly(w.HEADER.size)
                size, message_type = w.HEADER.unpack(header)
                if size < w.HEADER.size:
                    log.warning("RTDE %s: message length %d < 3; closing", self.peer, size)
                    break
                payload = await self.reader.readexactly(size - w.HEADER.size)
                if not self.handle(message_type, payload):
                    break
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            log.info("RTDE client %s gone", self.peer)
            self.abort()
            self.controller.rtde_disconnected(self)
            with contextlib.suppress(Exception):
                self.writer.close()

    def handle(self, message_type: int, payload: bytes) -> bool:
        """Process one request; False closes the connection (protocol violation)."""
        c = self.controller
        if message_type != w.DATA_PACKAGE:
            log.debug("RTDE %s: request %r (%d bytes)", self.peer, chr(message_type), len(payload))
        if message_type == w.REQUEST_PROTOCOL_VERSION:
            if len(payload) != 2:
                return self._violation("protocol version request must carry a uint16")
            (version,) = struct.unpack(">H", payload)
            self.send(w.REQUEST_PROTOCOL_VERSION, bytes([1 if version in (1, 2) else 0]))
        elif message_type == w.GET_URCONTROL_VERSION:
            self.send(w.GET_URCONTROL_VERSION, struct.pack(">IIII", *c.personality.version))
        elif message_type == w.CONTROL_PACKAGE_SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif message_type == w.CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(payload)
        elif message_type == w.CONTROL_PACKAGE_START:
            ok = self.output_recipe is not None
            self.streaming = ok
            self.send(w.CONTROL_PACKAGE_START, bytes([1 if ok else 0]))
        elif message_type == w.CONTROL_PACKAGE_PAUSE:
            self.streaming = False
            self.send(w.CONTROL_PACKAGE_PAUSE, bytes([1]))
        elif message_type == w.DATA_PACKAGE:
            return self._data(payload)
        else:
            return self._violation(f"unknown message type {message_type}")
        return True

    def _violation(self, what: str) -> bool:
        log.warning("RTDE %s: %s; closing the connection", self.peer, what)
        return False

    def _setup_outputs(self, payload: bytes) -> None:
        if len(payload) < 8:
            self.send(w.CONTROL_PACKAGE_SETUP_OUTPUTS, bytes([0]) + b"NOT_FOUND")
            return
        (frequency,) = struct.unpack(">d", payload[:8])
        names = w.split_names(payload[8:])
        types = [w.output_type(n) or "NOT_FOUND" for n in names]
        base = self.controller.personality.frequency_hz
        ok = bool(names) and "NOT_FOUND" not in types and 0 < frequency <= base + 1e-9
        if not (0 < frequency <= base + 1e-9):
            log.warning("RTDE %s: output frequency %.1f Hz outside (0, %.0f]", self.peer, frequency, base)
        recipe_id = self.controller.next_output_recipe_id() if ok else 0
        if ok:
            self.output_recipe = w.Recipe.build(recipe_id, names, types)
            self.packer = None
            self.output_every_n_ticks = max(1, round(base / frequency))
        self.send(w.CONTROL_PACKAGE_SETUP_OUTPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def _setup_inputs(self, payload: bytes) -> None:
        names = w.split_names(payload)
        types = [w.input_type(n) or "NOT_FOUND" for n in names]
        if not names or "NOT_FOUND" in types:
            self.send(w.CONTROL_PACKAGE_SETUP_INPUTS, bytes([0]) + ",".join(types).encode())
            return
        in_use = self.controller.claim_inputs(self, names)
        if in_use:
            log.warning(
                "RTDE %s: input registers %s are in use by another connection", self.peer, sorted(in_use)
            )
            types = ["IN_USE" if n in in_use else t for n, t in zip(names, types, strict=True)]
            self.send(w.CONTROL_PACKAGE_SETUP_INPUTS, bytes([0]) + ",".join(types).encode())
            return
        recipe_id = len(self.input_recipes) + 1  # numbered 1, 2, ... per connection
        if recipe_id > 255:
            self.send(w.CONTROL_PACKAGE_SETUP_INPUTS, bytes([0]) + b"NOT_FOUND")
            return
        self.input_recipes[recipe_id] = w.Recipe.build(recipe_id, names, types)
        self.send(w.CONTROL_PACKAGE_SETUP_INPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def _data(self, payload: bytes) -> bool:
        if not payload:
            return self._violation("empty data package")
        recipe = self.input_recipes.get(payload[0])
        if recipe is None:
            log.warning("RTDE %s: data package for unknown input recipe %d ignored", self.peer, payload[0])
            return True
        try:
            values = recipe.unpack(payload[1:])
        except struct.error:
            # ur-rtde sends some packages with the wrong size (fact sheet Q1/Q2): be strict and loud,
            # but tolerate a longer package by taking its prefix, as the client relies on that.
            if len(payload) - 1 > recipe.packer.size:
                log.warning(
                    "RTDE %s: input recipe %d package is %d bytes, expected %d; using its prefix",
                    self.peer,
                    recipe.recipe_id,
                    len(payload) - 1,
                    recipe.packer.size,
                )
                values = recipe.unpack(payload[1 : 1 + recipe.packer.size])
            else:
                log.warning(
                    "RTDE %s: input recipe %d package is %d bytes, expected %d; ignored",
                    self.peer,
                    recipe.recipe_id,
                    len(payload) - 1,
                    recipe.packer.size,
                )
                return True
        if log.isEnabledFor(logging.DEBUG) and (len(values) < 3 or recipe.recipe_id == 1):
            log.debug("RTDE %s: data recipe %d %s", self.peer, recipe.recipe_id, values)
        self.controller.apply_inputs(values)
        return True
