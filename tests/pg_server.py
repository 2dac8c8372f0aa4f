"""A real PostgreSQL server for the tests of the shared campaign store, from the distribution's binaries.

`PgServer` makes a cluster in a temporary folder (initdb, password authentication on TCP), runs `postgres` on
127.0.0.1 and a free port as a child of the test process, and can stop it the way a machine loses it (an
immediate shutdown: every connection dropped at once) and start it again on the same data and port. The
server refuses to run as root: as root (CI) the cluster belongs to `nobody` and the server runs as that user.
Readiness is a connect loop with a deadline, never a fixed sleep. `tools/system-deps` installs the package.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import psycopg

SUPERUSER = "hil"
PASSWORD = "pg-test-secret-7f3a"  # a test cluster's only; the tests pass it through PGPASSWORD
READY_DEADLINE_S = 30.0
UNPRIVILEGED = "nobody"


def postgres_bin() -> Path:
    """The folder of the newest installed server's programs (Debian: /usr/lib/postgresql/N/bin)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/postgres"), key=lambda p: int(Path(p).parts[-3]))
    if not found:
        raise RuntimeError("no PostgreSQL server installed: run tools/system-deps (make does) first")
    return Path(found[-1]).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgServer:
    """One throw-away cluster; `url(database)` names a database on it without the password."""

    def __init__(self) -> None:
        self.bin = postgres_bin()
        self.root = Path(tempfile.mkdtemp(prefix="hil-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.process: subprocess.Popen | None = None
        self._user = UNPRIVILEGED if os.geteuid() == 0 else None
        if self._user is not None:  # the cluster's folder must be the server user's own
            entry = pwd.getpwnam(self._user)
            os.chmod(self.root, 0o755)
            os.chown(self.root, entry.pw_uid, entry.pw_gid)
        pwfile = self.root / "pwfile"
        pwfile.write_text(PASSWORD + "\n")
        if self._user is not None:
            os.chown(pwfile, pwd.getpwnam(self._user).pw_uid, -1)
        subprocess.run(
            [
                str(self.bin / "initdb"), "-D", str(self.data), "-U", SUPERUSER, f"--pwfile={pwfile}",
                "--auth-host=scram-sha-256", "--auth-local=scram-sha-256", "-E", "UTF8", "--no-instructions",
            ],
            check=True, capture_output=True, user=self._user, cwd=self.root,
        )  # fmt: skip
        pwfile.unlink()

    def url(self, database: str = "postgres", user: str = SUPERUSER) -> str:
        return f"postgresql://{user}@127.0.0.1:{self.port}/{database}"

    def start(self) -> None:
        """Run the server and return once it accepts a password login."""
        self.log = open(self.root / "server.log", "ab")  # noqa: SIM115 - kept open while the server runs
        self.process = subprocess.Popen(
            [
                str(self.bin / "postgres"), "-D", str(self.data), "-p", str(self.port),
                "-c", "listen_addresses=127.0.0.1", "-c", "unix_socket_directories=",
                # a test cluster: the OS page cache outlives every server crash the tests cause
                "-c", "fsync=off", "-c", "full_page_writes=off", "-c", "max_connections=60",
            ],
            stdout=self.log, stderr=subprocess.STDOUT, user=self._user, cwd=self.root,
        )  # fmt: skip
        deadline = time.monotonic() + READY_DEADLINE_S
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"postgres exited ({self.process.returncode}): {self.log_text()[-2000:]}")
            try:
                psycopg.connect(self.url(), password=PASSWORD, connect_timeout=2).close()
                return
            except psycopg.OperationalError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"postgres not ready after {READY_DEADLINE_S} s") from None
                time.sleep(0.05)  # polling a state with a deadline (the server is starting up)

    def lose(self) -> None:
        """The server gone at once (an immediate shutdown): every client's connection drops mid-statement."""
        self._signal_and_wait(signal.SIGQUIT)

    def stop(self) -> None:
        self._signal_and_wait(signal.SIGINT)  # a fast shutdown

    def _signal_and_wait(self, signum: int) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signum)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.log.close()

    def create_database(self, name: str) -> str:
        with psycopg.connect(self.url(), password=PASSWORD, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def log_text(self) -> str:
        path = self.root / "server.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def remove(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)
