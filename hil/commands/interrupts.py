"""Ctrl-C while instruments are connected: the Session stops the robot and closes the store, and the process
is gone within a bounded time whatever a driver call is doing.

Python runs a signal handler only in the main thread, between bytecodes: a Ctrl-C that lands while the main
thread waits in a driver's C++ call (ur-rtde) runs no Python handler until that call returns, and a C++
destructor that blocks with the GIL held stops every Python thread. So the guard does not rely on the handler
alone: the C-level handler writes each signal to a pipe (``signal.set_wakeup_fd``); a watcher thread reads it
and arms two deadlines, one in Python (exit 130) and, behind it, faulthandler's C watchdog, which needs no GIL,
prints every thread's stack to stderr (where it hung) and exits 1.
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from typing import Any

INTERRUPT_GRACE_S = 5.0  # after a Ctrl-C the process is gone by then, whatever a driver does
BACKSTOP_S = 2.0  # then faulthandler's C thread ends it even if the GIL is held
EXIT_INTERRUPTED = 130

_forced_exit_note: list[tuple[int, bytes]] = []  # (a copy of stderr as it was, the text) for `_leave_now`


def say_on_forced_exit(note: str) -> None:
    """What to print if the deadline ends the process before the clean-up could say it (the cause and the
    command that resumes). Written to a copy of stderr taken now, so captured native output cannot swallow it."""
    if _forced_exit_note:
        os.close(_forced_exit_note.pop()[0])
    _forced_exit_note.append((os.dup(2), note.encode("utf-8", "replace") + b"\n"))


@contextmanager
def interrupt_guard() -> Iterator[None]:
    """First Ctrl-C: KeyboardInterrupt in the main thread (the Session's clean-up is bounded in time) and the
    deadlines armed; a second Ctrl-C exits at once. Outside the main thread it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous_handler = signal.getsignal(signal.SIGINT)
    previous_wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    stop = threading.Event()
    watcher = threading.Thread(target=_watch, args=(read_fd, stop), name="hil-interrupt-watcher", daemon=True)
    watcher.start()
    signal.signal(signal.SIGINT, _raise_keyboard_interrupt)
    leaving_on_error = True
    try:
        yield
        leaving_on_error = False
    finally:
        signal.signal(signal.SIGINT, previous_handler)
        signal.set_wakeup_fd(previous_wakeup)
        with _deadline_lock:  # after this, the watcher arms nothing (see _arm_deadlines)
            stop.set()
        os.write(write_fd, b"\0")  # wake the watcher so it sees `stop`
        os.close(write_fd)
        if not leaving_on_error:  # an interrupt handled inside, and the work went on: no deadline any more
            _disarm_deadlines()


_stop_paths: list[Callable[[str], None]] = []  # what a Ctrl-C asks to stop: the open sessions' engines
CTRL_C = "stopped by the operator (Ctrl-C)"


@contextmanager
def stop_on_interrupt(request_stop: Callable[[str], None]) -> Iterator[None]:
    """While inside, a Ctrl-C takes the same stop path as any other stop button: `request_stop` (the
    engine's) is called with why, then the KeyboardInterrupt breaks the call in flight (a move, a
    measurement), so the robot is stopped at once and the run cannot go on past its next checkpoint."""
    _stop_paths.append(request_stop)
    try:
        yield
    finally:
        _stop_paths.remove(request_stop)


def _raise_keyboard_interrupt(signum: int, frame: Any) -> None:
    _arm_deadlines()  # here too: after the handler the main thread may block holding the GIL, the watcher then never runs
    for request_stop in list(_stop_paths):
        request_stop(CTRL_C)
    raise KeyboardInterrupt


_deadline_lock = threading.RLock()  # re-entrant: the signal handler may run while the main thread holds it
_deadline: list[threading.Timer] = []  # the armed exit timer, if any


def _arm_deadlines(unless: threading.Event | None = None) -> None:
    """Leave with 130 after INTERRUPT_GRACE_S; faulthandler's C thread, behind it, dumps every thread's stack
    and exits 1 even if the GIL is never released again. Arming twice keeps the first deadline. `unless`, set
    (under the lock, so a guard that has handled the interrupt and left cannot be re-armed late by a slow
    watcher thread): nothing is armed."""
    with _deadline_lock:
        if _deadline or (unless is not None and unless.is_set()):
            return
        # sys.stderr, not descriptor 2: while native output is captured, 2 leads into a pipe
        faulthandler.dump_traceback_later(INTERRUPT_GRACE_S + BACKSTOP_S, exit=True, file=sys.stderr)
        timer = threading.Timer(INTERRUPT_GRACE_S, _leave_now)
        timer.daemon = True
        timer.start()
        _deadline.append(timer)


def _disarm_deadlines() -> None:
    with _deadline_lock:
        for timer in _deadline:
            timer.cancel()
        _deadline.clear()
        faulthandler.cancel_dump_traceback_later()


def _watch(read_fd: int, stop: threading.Event) -> None:
    """Read signal numbers off the wakeup pipe: on the first SIGINT arm the deadlines, on the second leave."""
    interrupts = 0
    try:
        while True:
            data = os.read(read_fd, 64)
            if stop.is_set() or not data:
                return
            interrupts += data.count(signal.SIGINT)
            if interrupts >= 2 and not stop.is_set():
                _leave_now()
            if interrupts == 1:
                _arm_deadlines(unless=stop)
    finally:
        os.close(read_fd)


def _leave_now() -> None:
    """Every measurement is committed before the next motion: nothing is lost by not waiting for a driver.
    No flush: the main thread may hold stdout's lock, blocked on a full pipe; the note goes out with a bare
    write on its own descriptor."""
    for fd, note in _forced_exit_note:
        with suppress(OSError):
            os.write(fd, note)
    os._exit(EXIT_INTERRUPTED)
