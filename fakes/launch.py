"""Start the simulated cell (`python -m fakes.sim`) as a subprocess for tests and `hil demo`: pick a loopback
address, read the ready line with a timeout, hand back the announced addresses and a control client, and
always stop it."""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import random
import select
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

from fakes.control_client import ControlClient

EXIT_ADDRESS_IN_USE = 3  # exit status of `python -m fakes.sim` when its address is taken: try another
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@dataclass
class RunningCell:
    """A live simulated cell process: its announcement, control client and process handle."""

    info: dict
    process: subprocess.Popen
    control: ControlClient
    log_path: str
    args: list[str] = field(default_factory=list)

    @property
    def host(self) -> str:
        return self.info["robot"]["host"]

    def log_tail(self, n: int = 40) -> str:
        with contextlib.suppress(OSError), open(self.log_path, errors="replace") as f:
            return "".join(f.readlines()[-n:])
        return ""


def is_loopback_host(host: str) -> bool:
    """True for an IPv4 address in 127.0.0.0/8 (the only place fakes may listen); names are refused."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    return address.version == 4 and address.is_loopback


def random_loopback_host(rng: random.Random | None = None) -> str:
    """A random address in 127.0.0.0/8 other than 127.0.0.1 (UR's ports are fixed, so one cell per host)."""
    rng = rng or random.Random()
    return f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"


def start_cell(
    robot: str = "ur10",
    personality: str | None = None,
    seed: int = 0,
    time_scale: float = 1.0,
    host: str | None = None,
    extra_args: tuple[str, ...] = (),
    ready_timeout_s: float = 90.0,  # bounds only a failed start: a ready cell returns at once
    attempts: int = 5,
) -> RunningCell:
    """Spawn `python -m fakes.sim ...` and wait for its JSON line; retries other hosts if the address is taken."""
    last_error = ""
    for _ in range(attempts):
        chosen = host or random_loopback_host()
        args = [sys.executable, "-m", "fakes.sim", "--host", chosen, "--robot", robot, "--seed", str(seed)]
        args += ["--time-scale", str(time_scale), *extra_args]
        if personality:
            args += ["--personality", personality]
        env = dict(os.environ)
        env["PYTHONPATH"] = _ROOT + os.pathsep + env.get("PYTHONPATH", "")
        with tempfile.NamedTemporaryFile(prefix="hil-sim-", suffix=".log", delete=False) as log:
            process = subprocess.Popen(
                args, stdout=subprocess.PIPE, stderr=log, env=env, cwd=_ROOT, preexec_fn=_die_with_parent
            )
        line = _read_line(process, ready_timeout_s)
        if line:
            info = json.loads(line)
            return RunningCell(info, process, ControlClient(info["control"]), log.name, args)
        code = exit_status(process)
        stop_process(process)
        with open(log.name, errors="replace") as f:
            last_error = f.read()[-2000:]
        os.remove(log.name)
        if code == EXIT_ADDRESS_IN_USE and host is None:
            continue
        break
    raise RuntimeError(f"the simulated cell did not become ready:\n{last_error}")


def stop_cell(cell: RunningCell) -> None:
    """SIGTERM, wait, SIGKILL if needed, then remove its log. Disconnect robot clients before calling this."""
    cell.control.close()
    stop_process(cell.process)
    with contextlib.suppress(OSError):
        os.remove(cell.log_path)


@contextlib.contextmanager
def sim_cell(**kwargs) -> Iterator[RunningCell]:
    """`with sim_cell(robot="ur10e", time_scale=10) as cell:` ... the process is always stopped."""
    cell = start_cell(**kwargs)
    try:
        yield cell
    finally:
        stop_cell(cell)


def _die_with_parent() -> None:
    """In the child: ignore SIGINT, and ask Linux to SIGTERM it when the parent dies (a crashed or killed
    test run must not leave cells running; elsewhere that part is a no-op and the context manager still
    stops the cell normally). A Ctrl-C in a terminal reaches the whole foreground process group, the cell
    too; but the cell stands for a robot controller and a tracker, which a Ctrl-C on the PC does not switch
    off: the program that started it must still be able to stop the robot and record that it was
    interrupted, then stop the cell itself (or the kernel does, when that program is gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _read_line(process: subprocess.Popen, timeout_s: float) -> str | None:
    deadline = time.monotonic() + timeout_s
    if process.stdout is None:
        raise ValueError("the process was started without stdout=PIPE")
    fd = process.stdout.fileno()
    data = b""
    while b"\n" not in data:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        ready, _, _ = select.select([fd], [], [], min(remaining, 0.2))
        if ready:
            chunk = os.read(fd, 65536)
            if not chunk:
                return None
            data += chunk
        elif process.poll() is not None:
            return None
    return data.split(b"\n", 1)[0].decode()


def exit_status(process: subprocess.Popen, within_s: float = 5.0) -> int | None:
    """The exit status of a child that ended its output without the ready line; None if it still runs after
    `within_s` (a start that hung). Its stdout reaches its end a moment before the kernel reports the exit,
    longer on a busy machine: a poll() in that moment reads None, and the "address in use" status, which
    asks for another address, was lost."""
    try:
        return process.wait(within_s)
    except subprocess.TimeoutExpired:
        return None


def stop_process(process: subprocess.Popen, sig: int = signal.SIGTERM) -> None:
    """Signal a child process, wait up to 5 s, kill it if it lingers, and close its stdout pipe."""
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)
    if process.stdout:
        process.stdout.close()
