"""Who drives a campaign: one holder at a time (a `hil run`, the operator console), recorded beside the file.

A run holds an exclusive lock (flock) on `<campaign>.lock` while it can move the robot for that campaign;
the file says who holds it (the command, its process, machine and start time), so the second one is refused
with who holds it, not merely "busy". The operating system releases the lock when the holder's process
ends, however it ends: a killed run leaves no stale lock behind, only a file that the next holder takes over.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO

EXCLUSIVE_TRIES = 5
EXCLUSIVE_RETRY_S = 0.02


class CampaignBusyError(RuntimeError):
    """Another run (a `hil run`, the console) drives this campaign now; the message says which."""


@dataclass(frozen=True)
class Holder:
    """Who drives a campaign: `what` (`hil run registration`, `hil serve at http://...`), its process,
    machine and the time it took the campaign (UNIX s)."""

    what: str
    pid: int
    host: str
    since_s: float

    @classmethod
    def this_process(cls, what: str) -> Holder:
        return cls(what, os.getpid(), socket.gethostname(), time.time())

    def describe(self) -> str:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.since_s))
        return f"{self.what} (process {self.pid} on {self.host}, since {since})"


def lock_path(campaign: str | Path) -> Path:
    """The lock file of a campaign: its name with `.lock` added, in its folder."""
    campaign = Path(campaign)
    return campaign.with_name(campaign.name + ".lock")


class CampaignLock:
    """`with CampaignLock(campaign, Holder.this_process("hil run x")):` the campaign is this run's until the
    block ends; a second holder (any process, or this one) is refused with CampaignBusyError naming the first."""

    def __init__(self, campaign: str | Path, holder: Holder) -> None:
        self.path = lock_path(campaign)
        self.holder = holder
        self._file: IO[str] | None = None

    def __enter__(self) -> CampaignLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self) -> None:
        """Take the lock or raise CampaignBusyError. The file is re-checked after locking: a holder that
        released (and removed the file) in between leaves us a lock on a file no other run sees."""
        while True:
            handle = open(self.path, "a+", encoding="utf-8")  # noqa: SIM115 - held until release
            if not _lock_exclusive(handle):
                handle.seek(0)
                text = handle.read()
                handle.close()
                raise CampaignBusyError(
                    f"campaign {self.path.name.removesuffix('.lock')} is driven by {_holder_text(text)}"
                )
            try:
                same = os.fstat(handle.fileno()).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            handle.close()
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps(asdict(self.holder)))
        handle.flush()
        self._file = handle

    def release(self) -> None:
        """Remove the file, then let go (in that order: a waiting holder never locks a file that stays)."""
        if self._file is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            self._file.close()  # closing the descriptor releases the flock
            self._file = None


def _lock_exclusive(handle: IO[str]) -> bool:
    """Take the exclusive lock without waiting for a holder; a few quick tries, because `current_holder`
    (a page listing the campaigns) holds a shared lock for an instant, which is no holder."""
    for attempt in range(EXCLUSIVE_TRIES):
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if attempt + 1 < EXCLUSIVE_TRIES:
                time.sleep(EXCLUSIVE_RETRY_S)
    return False


def current_holder(campaign: str | Path) -> Holder | None:
    """Who drives the campaign now, None when nobody does (the lock file is absent or not locked)."""
    path = lock_path(campaign)
    try:
        handle = open(path, encoding="utf-8")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        return None
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _holder(handle.read())
        fcntl.flock(handle, fcntl.LOCK_UN)
        return None


def _holder(text: str) -> Holder | None:
    try:
        return Holder(**json.loads(text))
    except (ValueError, TypeError):
        return None


def _holder_text(text: str) -> str:
    holder = _holder(text)
    return "another run (it has not said who yet)" if holder is None else holder.describe()
