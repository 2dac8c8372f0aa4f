"""What native libraries print while instruments are connected (ur-rtde's C++ writes to the process's stdout and
stderr), kept out of the user's terminal: every line goes to the `hil.native` log, which a session stores in the
campaign log, and with `--verbose` to stderr as well.

Python's own output is unaffected: during the capture `sys.stdout` and `sys.stderr` write to copies of the
original descriptors, and only the descriptors 1 and 2 that native code writes to lead into a pipe.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

log = logging.getLogger("hil.native")

_terminal: tuple[int, int] | None = None  # copies of the original stdout and stderr, made once per process


def _terminal_fds() -> tuple[int, int]:
    """Copies of descriptors 1 and 2 as they were first (kept open: faulthandler may write to them at exit)."""
    global _terminal
    if _terminal is None:
        _terminal = (os.dup(1), os.dup(2))
    return _terminal


def _text_file(fd: int, like: TextIO) -> TextIO:
    """A line-buffered text file on `fd` with the encoding of the stream it stands in for."""
    encoding = getattr(like, "encoding", None) or "utf-8"
    errors = getattr(like, "errors", None) or "strict"
    return open(fd, "w", buffering=1, encoding=encoding, errors=errors, closefd=False)  # noqa: SIM115


@contextmanager
def capture_native_output(verbose: bool = False) -> Iterator[None]:
    """Inside the block, lines written to descriptors 1 and 2 by native code are logged (and echoed to stderr
    when `verbose`); Python's sys.stdout and sys.stderr still reach the terminal."""
    sys.stdout.flush()
    sys.stderr.flush()
    out_fd, err_fd = _terminal_fds()
    saved_streams = sys.stdout, sys.stderr
    read_fd, write_fd = os.pipe()
    reader = threading.Thread(
        target=_forward, args=(read_fd, err_fd, verbose), name="hil-native-output", daemon=True
    )
    sys.stdout, sys.stderr = _text_file(out_fd, saved_streams[0]), _text_file(err_fd, saved_streams[1])
    os.dup2(write_fd, 1)
    os.dup2(write_fd, 2)
    os.close(write_fd)
    reader.start()
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        os.dup2(out_fd, 1)  # closes the pipe's last write ends: the reader sees the end
        os.dup2(err_fd, 2)
        reader.join(timeout=1.0)
        sys.stdout, sys.stderr = saved_streams


def _forward(read_fd: int, err_fd: int, verbose: bool) -> None:
    """Read native output line by line: log each line, echo it to the terminal's stderr when verbose."""
    with open(read_fd, "rb", closefd=True) as pipe:
        for raw in pipe:
            line = raw.decode(errors="replace").rstrip()
            if not line:
                continue
            log.info("%s", line)
            if verbose:
                os.write(err_fd, f"  [native] {line}\n".encode())
