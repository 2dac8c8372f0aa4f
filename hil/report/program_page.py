"""One HTML page of a program's measured accuracy: every waypoint's error in each run, as a table and a plot.

The runs are the original program and the compensated one (`procedures/program_accuracy.py` measures
them); the page shows what compensation buys for this program, waypoint by waypoint, beside each run's RMS.
"""

from __future__ import annotations

import html
from dataclasses import dataclass

import numpy as np

from hil.report.png import png_img


@dataclass(frozen=True)
class WaypointRow:
    """One waypoint of the page: its name, program line and motion, and its error per run (m)."""

    name: str
    line: int
    command: str
    error_m: dict[str, float]


def program_page(title: str, rows: list[WaypointRow], runs: list[str], notes: list[str]) -> str:
    """The self-contained page (the plot embedded as PNG): a table (mm), the RMS per run, a bar plot."""
    head = "".join(f"<th>{html.escape(r)} (mm)</th>" for r in runs)
    body = []
    for w in rows:
        cells = "".join(
            f"<td>{w.error_m[r] * 1e3:.4f}</td>" if r in w.error_m else "<td>-</td>" for r in runs
        )
        body.append(f"<tr><td>{html.escape(w.name)}</td><td>{w.line}</td><td>{w.command}</td>{cells}</tr>")
    rms = "".join(f"<td><b>{_rms(rows, r) * 1e3:.4f}</b></td>" for r in runs)
    body.append(f"<tr><td><b>RMS</b></td><td></td><td></td>{rms}</tr>")
    items = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title></head><body>"
        f"<h1>{html.escape(title)}</h1>"
        f"<table border='1' cellpadding='4'><tr><th>waypoint</th><th>line</th><th>motion</th>{head}</tr>"
        + "".join(body)
        + f"</table>{_plot(rows, runs)}<ul>{items}</ul></body></html>"
    )


def _rms(rows: list[WaypointRow], run: str) -> float:
    e = np.array([w.error_m[run] for w in rows if run in w.error_m])
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def _plot(rows: list[WaypointRow], runs: list[str]) -> str:
    """Bars per waypoint, one per run, on a log scale (the runs differ by orders of magnitude)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.5 * len(rows) + 2), 3.5))
    x = np.arange(len(rows))
    width = 0.8 / max(len(runs), 1)
    for k, run in enumerate(runs):
        values = [w.error_m.get(run, np.nan) * 1e3 for w in rows]
        ax.bar(
            x + (k - (len(runs) - 1) / 2) * width,
            values,
            width,
            label=f"{run} (RMS {_rms(rows, run) * 1e3:.3f} mm)",
        )
    ax.set_xticks(x, [f"{w.name}\nline {w.line}" for w in rows], fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("error at the waypoint (mm)")
    ax.legend(fontsize=8)
    return "<p>" + png_img(fig) + "</p>"
