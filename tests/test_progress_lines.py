"""Off a terminal, progress is a plain line every few seconds with the ETA (a CI log sees the work advance)."""

from __future__ import annotations

import io

from hil.runner.progress import PLAIN_EVERY_S, Progress


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_plain_lines_every_few_seconds_with_an_eta():
    stream, clock = io.StringIO(), _Clock()
    with Progress(stream=stream, clock=clock).task("grid sampling", total=100, done=10) as advance:
        for _ in range(30):
            clock.now += 1.0  # one point a second
            advance()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 30 // PLAIN_EVERY_S  # every 5 s; the last state was the 30 s line: not printed twice
    assert lines[0] == "grid sampling: 15/100 (15%), 5s elapsed, ETA 1m25s"
    assert lines[-1] == "grid sampling: 40/100 (40%), 30s elapsed, ETA 1m00s"


def test_the_last_state_is_printed_once_at_the_end():
    stream, clock = io.StringIO(), _Clock()
    with Progress(stream=stream, clock=clock).task("grid sampling", total=32) as advance:
        for _ in range(32):
            clock.now += 1.0
            advance()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 32 // PLAIN_EVERY_S + 1 and len(set(lines)) == len(lines)
    assert lines[-1] == "grid sampling: 32/32 (100%), 32s elapsed, done"


def test_short_work_and_disabled_progress_print_nothing():
    stream, clock = io.StringIO(), _Clock()
    with Progress(stream=stream, clock=clock).task("quick", total=3) as advance:
        advance(3)
    with Progress(enabled=False, stream=stream, clock=clock).task("off", total=3) as advance:
        clock.now += 60.0
        advance()
    assert stream.getvalue() == ""
