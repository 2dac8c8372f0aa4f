"""Progress with an ETA on long work: rich bars on a terminal, plain lines every few seconds otherwise (a CI
log or a scheduler sees the work advance)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rich.progress import Progress as RichProgress
    from rich.progress import TaskID


PLAIN_EVERY_S = 5.0  # one plain progress line at most this often


class Progress:
    """Bars with elapsed time and ETA on a terminal; off a terminal one plain line every PLAIN_EVERY_S with
    the same figures; nothing when `enabled` is False.

    `with progress.task("grid", total=315) as advance: ... advance()` for one counted task;
    `with progress.phases() as update: ... update(phase, done, total)` for work that reports its own phases.
    """

    def __init__(
        self,
        enabled: bool | None = None,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.stream = stream or sys.stderr
        terminal = self.stream.isatty()
        self.enabled = True if enabled is None else enabled
        self.plain = not terminal  # lines, not bars (also when enabled on purpose off a terminal)
        self.clock = clock

    @contextmanager
    def _bar(self) -> Iterator[RichProgress]:
        """The rich progress display on the stream (imported only when drawn)."""
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as RichProgress

        columns = (
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
        )
        with RichProgress(*columns, console=Console(file=self.stream), transient=False) as bar:
            yield bar

    @contextmanager
    def task(self, description: str, total: int, done: int = 0) -> Iterator[Callable[..., None]]:
        """An `advance(n=1)` callback for one task of `total` steps, `done` of them already done."""
        if not self.enabled:
            yield lambda n=1: None
            return
        if self.plain:
            line = _PlainLine(self.stream, self.clock, description, total, done)
            yield line.advance
            line.finish()
            return
        with self._bar() as bar:
            task_id = bar.add_task(description, total=total, completed=done)
            yield lambda n=1: bar.advance(task_id, n)

    @contextmanager
    def phases(self) -> Iterator[Callable[[str, int, int], None]]:
        """An `update(phase, done, total)` callback: one bar per phase, added when the phase first reports."""
        if not self.enabled:
            yield lambda phase, done, total: None
            return
        if self.plain:
            lines: dict[str, _PlainLine] = {}

            def update_plain(phase: str, done: int, total: int) -> None:
                if phase not in lines:
                    lines[phase] = _PlainLine(self.stream, self.clock, phase, max(total, 1), 0)
                lines[phase].set(done, max(total, 1))

            yield update_plain
            for line in lines.values():
                line.finish()
            return
        with self._bar() as bar:
            tasks: dict[str, TaskID] = {}

            def update(phase: str, done: int, total: int) -> None:
                if phase not in tasks:
                    tasks[phase] = bar.add_task(phase, total=max(total, 1))
                bar.update(tasks[phase], completed=done, total=max(total, 1))

            yield update


class _PlainLine:
    """`description: done/total (pct), elapsed, ETA` on its own line, at most every PLAIN_EVERY_S, and once at the
    end when it wrote before (short work prints nothing)."""

    def __init__(self, stream: TextIO, clock: Callable[[], float], description: str, total: int, done: int):
        self.stream, self.clock, self.description = stream, clock, description
        self.total, self.done, self.start_done = max(total, 1), done, done
        self.started = self.last = clock()
        self.written = False
        self.shown: tuple[int, int] | None = None  # the done/total of the last line written

    def advance(self, n: int = 1) -> None:
        self.set(self.done + n, self.total)

    def set(self, done: int, total: int) -> None:
        self.done, self.total = done, total
        if self.clock() - self.last >= PLAIN_EVERY_S:
            self.write()

    def finish(self) -> None:
        if self.written and self.shown != (self.done, self.total):  # the last line once, not twice
            self.write()

    def write(self) -> None:
        now = self.clock()
        self.last, self.written, self.shown = now, True, (self.done, self.total)
        elapsed = now - self.started
        rate = (self.done - self.start_done) / elapsed if elapsed > 0 else 0.0
        left = self.total - self.done
        eta = "done" if left <= 0 else f"ETA {_duration(left / rate)}" if rate > 0 else "ETA unknown"
        percent = 100.0 * self.done / self.total
        print(
            f"{self.description}: {self.done}/{self.total} ({percent:.0f}%), {_duration(elapsed)} elapsed, {eta}",
            file=self.stream,
            flush=True,
        )


def _duration(seconds: float) -> str:
    """12s, 3m05s, 1h02m."""
    s = int(round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"
