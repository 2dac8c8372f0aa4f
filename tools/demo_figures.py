"""Write docs/demo-run.txt, the transcript of one `hil demo` run that the docs quote, from that run's output.

    hil demo --out demo-out | tee demo.log
    python tools/demo_figures.py demo.log            # writes docs/demo-run.txt

Run it whenever the demo's figures change (a change to the procedures, the simulated cell or the analysis), then
copy the changed figures into the pages that quote them: tests/test_docs_figures.py fails on any figure a page
quotes from the demo that is not in this transcript. What changes from run to run without changing a figure is
left out: progress lines (with their elapsed times), the cell's loopback addresses and the output folder.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRANSCRIPT = ROOT / "docs" / "demo-run.txt"
PROGRESS = re.compile(r"^[\w -]+: \d+/\d+ \(\d+%\), .*(elapsed|done)")
ADDRESS = re.compile(r"\b127\.\d+\.\d+\.\d+\b")
ELAPSED = re.compile(r"\bin \d+ s\b")
CONTROL_PORT = re.compile(r"--control-port \d+")


def transcript(log: str, out_dir: str | None) -> str:
    """The run's lines without progress, with addresses, elapsed seconds and the output folder made neutral."""
    lines = []
    for line in log.splitlines():
        if PROGRESS.match(line):
            continue
        line = ADDRESS.sub("127.x.x.x", line)
        line = ELAPSED.sub("in N s", line)
        line = CONTROL_PORT.sub("--control-port N", line)
        if out_dir:
            line = line.replace(out_dir.rstrip("/") + "/", "demo-out/").replace(
                out_dir.rstrip("/"), "demo-out"
            )
        lines.append(line.rstrip())
    return "\n".join(lines).strip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", help="what `hil demo` printed (hil demo | tee demo.log)")
    ap.add_argument(
        "--out-dir", help="the run's --out folder, written as demo-out (default: read from the log)"
    )
    ap.add_argument(
        "-o", "--output", default=str(TRANSCRIPT), help="the transcript to write (default docs/demo-run.txt)"
    )
    args = ap.parse_args(argv)
    log = Path(args.log).read_text()
    out_dir = args.out_dir
    if out_dir is None:
        found = re.search(r"campaign (\S+)/campaign\.sqlite", log)
        out_dir = found.group(1) if found else None
    Path(args.output).write_text(transcript(log, out_dir))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
