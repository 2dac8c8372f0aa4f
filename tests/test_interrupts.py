"""Ctrl-C ends the process within a bounded time even when the main thread is stuck in a native call that
never returns (a driver waiting on a controller that is gone): with the GIL released, and with it held."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

# A normal pthread mutex locked twice by one thread deadlocks and is deaf to signals: a native call that
# never returns. Through ctypes.CDLL the GIL is released; through ctypes.PyDLL it is held.
PROGRAM = textwrap.dedent(
    """
    import ctypes, time
    from hil.commands import interrupts
    interrupts.INTERRUPT_GRACE_S = 1.0
    interrupts.BACKSTOP_S = 1.0
    libc, libc_holding_gil = ctypes.CDLL(None), ctypes.PyDLL(None)
    mutex = ctypes.create_string_buffer(64)  # zeroed: PTHREAD_MUTEX_INITIALIZER
    libc.pthread_mutex_lock(mutex)
    interrupts.say_on_forced_exit("interrupted (Ctrl-C): resume with: hil run grid_sampling")
    with interrupts.interrupt_guard():
        if MODE == "gil_released":
            while True:  # the program swallows KeyboardInterrupt, as a stuck clean-up would
                try:
                    print("ready", flush=True)
                    libc.pthread_mutex_lock(mutex)  # there, the Python handler never gets to run
                except KeyboardInterrupt:
                    pass
        else:
            try:
                print("ready", flush=True)
                time.sleep(60)
            except KeyboardInterrupt:  # the handler ran; now clean-up blocks with the GIL held
                libc_holding_gil.pthread_mutex_lock(mutex)
    """
)


def _interrupt_stuck_process(mode: str) -> tuple[int, str]:
    process = subprocess.Popen(
        [sys.executable, "-c", f"MODE = {mode!r}\n{PROGRAM}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert process.stdout.readline().strip() == "ready", process.stderr.read()
        process.send_signal(signal.SIGINT)
        code = process.wait(60)
    finally:
        if process.poll() is None:
            process.kill()
    return code, process.stderr.read()


def test_ctrl_c_leaves_when_the_main_thread_is_stuck_in_a_native_call():
    code, stderr = _interrupt_stuck_process("gil_released")
    assert code == 130, stderr
    assert "interrupted (Ctrl-C): resume with: hil run grid_sampling" in stderr  # the cause, the way back


def test_ctrl_c_leaves_when_clean_up_blocks_holding_the_gil_and_says_where():
    code, stderr = _interrupt_stuck_process("gil_held")
    assert code == 1, stderr  # faulthandler's watchdog: it needs no GIL
    assert "Timeout" in stderr and "pthread_mutex_lock" not in stderr  # a Python stack dump, not a crash
    assert "<string>" in stderr  # ... pointing at the stuck line


def test_an_interrupt_handled_inside_the_guard_leaves_no_deadline_behind():
    """A caller that catches the KeyboardInterrupt and carries on is not killed by the exit deadline."""
    program = textwrap.dedent(
        """
        import os, signal, time
        from hil.commands import interrupts
        interrupts.INTERRUPT_GRACE_S = 0.5
        interrupts.BACKSTOP_S = 0.5
        with interrupts.interrupt_guard():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(60)
            except KeyboardInterrupt:
                pass
        time.sleep(2.0)  # past both deadlines
        print("still here", flush=True)
        """
    )
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "still here" in done.stdout, done.stderr
