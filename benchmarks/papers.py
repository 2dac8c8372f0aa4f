"""The four source papers' experiments through the runner, side by side with the papers' own figures.

Run:  PYTHONPATH=. python benchmarks/papers.py [--quick] [--only grid,svr,tool,pt]

Each paper's experiment runs on the simulated cell through ur-rtde, emScon and the procedures (its own script,
benchmarks/paper_<name>.py, runs it alone and says how). The simulated cell carries effects no paper's model
family holds (gravity compliance, gear errors, thermal growth), so the figures are ours, not a replay of the
paper's. Where a paper's column labelled RMS cannot be one, max and mean are compared.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from paper_cell import print_rows  # noqa: E402

PAPERS = {"grid": "paper_grid", "svr": "paper_svr", "tool": "paper_tool", "pt": "paper_pt"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="each paper's quick setting (minutes, not an hour)"
    )
    parser.add_argument("--only", default=",".join(PAPERS), help="papers to run: " + ",".join(PAPERS))
    args = parser.parse_args()
    chosen = [name.strip() for name in args.only.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in PAPERS]
    if unknown:
        parser.error(f"unknown paper {', '.join(unknown)}; choose from {', '.join(PAPERS)}")
    for name in chosen:
        started = time.monotonic()
        rows = importlib.import_module(PAPERS[name]).rows(args.quick)
        print(f"\n== {name} paper ({time.monotonic() - started:.0f} s)")
        print_rows(rows)


if __name__ == "__main__":
    main()
