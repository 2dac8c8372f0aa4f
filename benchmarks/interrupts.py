"""How fast `hil demo` is gone after Ctrl-C, over many trials (a rare hang needs many to show).

Each trial starts `hil demo` in its own process group, waits until a varying number of points is recorded,
sends SIGINT to the whole group (as a terminal does) and times the exit. A trial that does not exit within
--hang-s is a hang: its threads are dumped with gdb when gdb is installed and it is killed. The table gives
exit codes and the exit-time spread; the last session measured 1 hang in 40 trials before the settle check
stopped calling ur-rtde's isSteady() and 0 in 30 after.

Run: PYTHONPATH=. python benchmarks/interrupts.py [--trials 20] [--hang-s 30]
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.data.store import CampaignStore  # noqa: E402


def recorded(campaign: Path) -> int:
    if not campaign.exists():
        return 0
    try:
        with CampaignStore(campaign) as store:
            return len(store.measurements())
    except Exception:  # noqa: BLE001 - the file may be being created
        return 0


def trial(k: int, folder: Path, hang_s: float) -> tuple[int | None, float]:
    """One interrupted demo: (exit code or None for a hang, seconds from SIGINT to exit)."""
    out = folder / f"demo{k}"
    log = open(folder / f"demo{k}.log", "w")  # noqa: SIM115 - the child writes it until it exits
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", "demo", "--out", str(out), "--step-mm", "200", "--validate", "10"],
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    wanted = 3 + k % 7  # interrupt at different moments: registration, tool fit, grid
    while recorded(out / "campaign.sqlite") < wanted:
        if process.poll() is not None:
            raise RuntimeError(f"hil demo ended before it was interrupted; see {log.name}")
        time.sleep(0.1)
    os.killpg(process.pid, signal.SIGINT)
    started = time.monotonic()
    try:
        code = process.wait(hang_s)
        return code, time.monotonic() - started
    except subprocess.TimeoutExpired:
        if shutil.which("gdb"):
            with open(folder / f"demo{k}.gdb.txt", "w") as dump:
                subprocess.run(
                    ["gdb", "-p", str(process.pid), "-batch", "-ex", "thread apply all bt"],
                    stdout=dump,
                    stderr=subprocess.STDOUT,
                )
        os.killpg(process.pid, signal.SIGKILL)
        print(f"trial {k}: no exit within {hang_s:.0f} s; log and stacks in {folder}", flush=True)
        return None, float("inf")
    finally:
        log.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--hang-s", type=float, default=30.0)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="hil-interrupts-"))
    results = [trial(k, folder, args.hang_s) for k in range(args.trials)]
    codes = Counter("hang" if c is None else str(c) for c, _ in results)
    times = np.array([t for c, t in results if c is not None])
    print("\n| trials | exit codes | exit after Ctrl-C: min / median / max (s) |\n|---|---|---|")
    spread = f"{times.min():.2f} / {np.median(times):.2f} / {times.max():.2f}" if times.size else "-"
    print(f"| {args.trials} | {', '.join(f'{k}: {v}' for k, v in sorted(codes.items()))} | {spread} |")
    if "hang" not in codes:
        shutil.rmtree(folder)


if __name__ == "__main__":
    main()
