"""Progress with an ETA on long work (rich), quiet when the output is not a terminal."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rich.progress import Progress as RichProgress
    from rich.progress import TaskID


class Progress:
    """Bars with elapsed time and ETA on a terminal, nothing otherwise (logs and CI stay readable).

    `with progress.task("grid", total=315) as advance: ... advance()` for one counted task;
    `with progress.phases() as update: ... update(phase, done, total)` for work that reports its own phases.
    """

    def __init__(self, enabled: bool | None = None, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled

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
        with self._bar() as bar:
            task_id = bar.add_task(description, total=total, completed=done)
            yield lambda n=1: bar.advance(task_id, n)

    @contextmanager
    def phases(self) -> Iterator[Callable[[str, int, int], None]]:
        """An `update(phase, done, total)` callback: one bar per phase, added when the phase first reports."""
        if not self.enabled:
            yield lambda phase, done, total: None
            return
        with self._bar() as bar:
            tasks: dict[str, TaskID] = {}

            def update(phase: str, done: int, total: int) -> None:
                if phase not in tasks:
                    tasks[phase] = bar.add_task(phase, total=max(total, 1))
                bar.update(tasks[phase], completed=done, total=max(total, 1))

            yield update
