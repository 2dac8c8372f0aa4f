"""The faults the fake emScon tracker can be told to show, and the control requests that set them.

The faults are one record shared by the wire (dropped, slow, injected or garbled answers, framing), the
beam (no target, beam breaks) and the measurement (outliers); the server turns a control request into it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from typing import Literal

# what a fault request asks of the server beyond setting the record (it needs the server's loop or clients)
ServerAction = Literal["block_beam", "drop_now", "clear"]


@dataclass
class Faults:
    """The active faults; all off by default."""

    beam_break_count: int = 0
    beam_break_rate: float = 0.0  # chance that any shot breaks the beam (people walking through the cell)
    no_target: bool = False
    slow_delay_s: float = 0.0
    drop_next_command: bool = False
    line_down: bool = False  # the serial line (pty) is "unplugged": nothing in, nothing out
    garbage_bytes: int = 0
    inject: bytes | None = None  # sent instead of everything the next command would have produced
    outlier_count: int = 0  # the next N results are offset by outlier_offset_m along x (air turbulence)
    outlier_offset_m: float = 0.0
    framing: str = "normal"  # "normal" | "bytewise" | "merged"

    def to_dict(self) -> dict:
        """JSON-able view (bytes as hex)."""
        return {k: v.hex() if isinstance(v, bytes) else v for k, v in self.__dict__.items()}

    def reset(self) -> None:
        """All faults off, in place (the wire, the beam and the measurement hold this same record)."""
        for f in fields(self):
            setattr(self, f.name, f.default)

    def set_from_request(self, request: dict) -> ServerAction | None:
        """Set the fault a control request names; returns what the server must do itself, if anything.

        kind: beam_break (count: the next N shots; rate: each shot with that chance), no_target, slow
        (delay_s), drop (when: next|now; TCP is closed, the serial line goes silent until cleared), garbage
        (n_bytes), inject (hex: raw bytes that replace the next answer), outlier (count, offset_m), framing
        (mode: normal|bytewise|merged), clear.
        """
        kind = request.get("kind")
        if kind == "beam_break":
            count = int(request.get("count", 1 if "rate" not in request else 0))
            rate = float(request.get("rate", 0.0))
            if count < 0 or not 0.0 <= rate < 1.0:
                raise ValueError("beam_break needs count >= 0 and rate in [0, 1)")
            self.beam_break_count, self.beam_break_rate = count, rate
        elif kind == "no_target":
            return "block_beam"
        elif kind == "slow":
            delay = float(request.get("delay_s", 1.0))
            if not 0 <= delay <= 3600:
                raise ValueError("slow delay_s must be in [0, 3600]")
            self.slow_delay_s = delay
        elif kind == "drop":
            if request.get("when", "next") == "now":
                return "drop_now"
            self.drop_next_command = True
        elif kind == "garbage":
            self.garbage_bytes = max(4, int(request.get("n_bytes", 32)))
        elif kind == "inject":
            try:
                self.inject = bytes.fromhex(str(request.get("hex", "")))
            except ValueError as exc:
                raise ValueError(f"inject needs 'hex': the bytes as a hex string ({exc})") from exc
            if not self.inject:
                raise ValueError("inject needs 'hex': at least one byte as a hex string")
        elif kind == "outlier":
            self.outlier_count = int(request.get("count", 1))
            self.outlier_offset_m = float(request.get("offset_m", 1e-3))
        elif kind == "framing":
            mode = request.get("mode", "normal")
            if mode not in ("normal", "bytewise", "merged"):
                raise ValueError("framing mode must be normal, bytewise or merged")
            self.framing = mode
        elif kind == "clear":
            return "clear"
        else:
            raise ValueError(
                f"unknown tracker fault {kind!r}; use beam_break, no_target, slow, drop, garbage, inject, outlier, framing, clear"
            )
        return None


def garbage(n_bytes: int) -> bytes:
    """n_bytes of junk whose first size field claims 2 GiB, so that the client's framing loses step."""
    return (b"\xff\xff\xff\x7f" + os.urandom(max(0, n_bytes - 4)))[:n_bytes]
