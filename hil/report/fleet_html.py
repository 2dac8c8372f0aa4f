"""The fleet view as one HTML page: the table of robots sorted by attention, then per robot its calibrations
and diagnoses over time (the error before and after, its own parameters' change with their uncertainties, the
effects found, the temperature). Plots are inline SVG drawn from the numbers (a page for hundreds of robots in
well under a second, no plotting library)."""

from __future__ import annotations

import html
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd

from hil.analysis.fleet.status import FleetStatus
from hil.data.fleet_source import FleetHistory

WIDTH, HEIGHT, MARGIN = 420, 150, 34


def _date(t_s: float) -> str:
    return "-" if not np.isfinite(t_s) else datetime.fromtimestamp(t_s, UTC).strftime("%Y-%m-%d")


def _mm(value_m: float) -> str:
    return "-" if not np.isfinite(value_m) else f"{value_m * 1e3:.3f}"


def _scale(values: np.ndarray, lo: float, hi: float, out_lo: float, out_hi: float) -> np.ndarray:
    span = hi - lo if hi > lo else 1.0
    return out_lo + (values - lo) / span * (out_hi - out_lo)


def _axes(title: str, y_label: str, lo: float, hi: float) -> list[str]:
    return [
        f'<svg width="{WIDTH}" height="{HEIGHT}" role="img" aria-label="{html.escape(title)}">',
        f'<text x="{MARGIN}" y="12" font-size="11">{html.escape(title)}</text>',
        f'<line x1="{MARGIN}" y1="{HEIGHT - MARGIN}" x2="{WIDTH - 8}" y2="{HEIGHT - MARGIN}" stroke="#999"/>',
        f'<line x1="{MARGIN}" y1="20" x2="{MARGIN}" y2="{HEIGHT - MARGIN}" stroke="#999"/>',
        f'<text x="2" y="26" font-size="9">{hi:.3g}</text>',
        f'<text x="2" y="{HEIGHT - MARGIN}" font-size="9">{lo:.3g}</text>',
        f'<text x="2" y="{HEIGHT - 4}" font-size="9">{html.escape(y_label)}</text>',
    ]


def _errors_svg(rows: pd.DataFrame) -> str:
    """Error before and after (mm) against time."""
    t = rows["time_s"].to_numpy(float)
    before, after = rows["rms_before_m"].to_numpy(float) * 1e3, rows["rms_after_m"].to_numpy(float) * 1e3
    finite = np.concatenate([before[np.isfinite(before)], after[np.isfinite(after)], [0.0]])
    lo, hi = 0.0, float(finite.max()) * 1.1 or 1.0
    x = _scale(t, t.min(), t.max(), MARGIN + 6, WIDTH - 14)
    parts = _axes("error before (grey) and after (blue) calibration", "RMS mm", lo, hi)
    for values, colour in ((before, "#999"), (after, "#1f5fbf")):
        ok = np.isfinite(values)
        y = _scale(values[ok], lo, hi, HEIGHT - MARGIN, 20)
        points = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(x[ok], y, strict=True))
        parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}"/>')
        parts += [
            f'<circle cx="{a:.1f}" cy="{b:.1f}" r="2.5" fill="{colour}"/>'
            for a, b in zip(x[ok], y, strict=True)
        ]
    parts.append(f'<text x="{MARGIN}" y="{HEIGHT - 20}" font-size="9">{_date(t.min())}</text>')
    parts.append(f'<text x="{WIDTH - 70}" y="{HEIGHT - 20}" font-size="9">{_date(t.max())}</text>')
    return "".join(parts) + "</svg>"


def parameter_moves(history: FleetHistory) -> pd.DataFrame:
    """Every own parameter of every result, as its change from the robot's first result in units of the two
    results' combined uncertainty (`z`), with this result's own +-1 sigma in the same units (`half`): mm and
    degrees on one axis, a move beyond the whiskers a move beyond the noise. All robots at once."""
    params = history.parameters
    own = params[params["own"] & params["std"].gt(0)].copy()
    own["robot"] = history.results["robot"].to_numpy()[own["result"].to_numpy(int)]
    own["time_s"] = history.results["time_s"].to_numpy(float)[own["result"].to_numpy(int)]
    own = own.sort_values("result", kind="stable")
    first = own.groupby(["robot", "name"], sort=False)[["delta", "std"]].transform("first")
    sigma = np.hypot(own["std"], first["std"])
    own["z"] = (own["delta"] - first["delta"]) / sigma
    own["half"] = own["std"] / sigma
    return own[["robot", "name", "time_s", "z", "half"]]


def _parameters_svg(moves: pd.DataFrame, t_lo: float, t_hi: float) -> str:
    """One robot's parameter moves (parameter_moves) against time."""
    if moves.empty:
        return ""
    z, half = moves["z"].to_numpy(float), moves["half"].to_numpy(float)
    bound = float(max(3.0, np.nanmax(np.abs(z) + half)))
    x = _scale(moves["time_s"].to_numpy(float), t_lo, t_hi, MARGIN + 6, WIDTH - 14)
    y, y_lo, y_hi = (_scale(v, -bound, bound, HEIGHT - MARGIN, 20) for v in (z, z - half, z + half))
    parts = _axes("own parameters' change since the first result", "sigmas", -bound, bound)
    zero = _scale(np.array([0.0]), -bound, bound, HEIGHT - MARGIN, 20)[0]
    parts.append(f'<line x1="{MARGIN}" y1="{zero:.1f}" x2="{WIDTH - 8}" y2="{zero:.1f}" stroke="#ccc"/>')
    names = moves["name"].to_numpy(str)
    parts += [
        f'<g><title>{n} {v:+.1f}</title><path d="M{a:.0f} {lo_:.0f}V{hi_:.0f}" stroke="#bbb"/>'
        f'<circle cx="{a:.0f}" cy="{b:.0f}" r="2" fill="#c0392b"/></g>'
        for n, v, a, b, lo_, hi_ in zip(names, z, x, y, y_lo, y_hi, strict=True)
    ]
    return "".join(parts) + "</svg>"


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "-" if not np.isfinite(value) else f"{value:.4g}"
    return html.escape(str(value))


def _table(frame: pd.DataFrame) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in frame.columns)
    body = "".join(
        "<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>"
        for row in frame.itertuples(index=False)
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def attention_table(status: FleetStatus) -> pd.DataFrame:
    """The robots as the page lists them, in the user's units (mm, dates), most attention first."""
    r = status.robots
    flags = np.where(r["moved"], "moved", "") + np.where(r["moved"] & r["error_flag"], ", ", "")
    flags = flags + np.where(r["error_flag"], "error over limit", "")
    return pd.DataFrame(
        {
            "robot": r["robot"],
            "model": r["robot_model"],
            "cell": r["cell_name"],
            "flag": flags,
            "results": r["results"],
            "latest": [_date(t) for t in r["latest_time_s"].to_numpy(float)],
            "error mm": [_mm(v) for v in r["latest_error_m"].to_numpy(float)],
            "chi2 / threshold": [
                "-" if not np.isfinite(c) else f"{c:.1f} / {t:.1f} ({int(d)})"
                for c, t, d in zip(
                    r["chi2"].to_numpy(float), r["threshold"].to_numpy(float), r["dof"].fillna(0), strict=True
                )
            ],
            "moved most": [
                "-" if not isinstance(n, str) else f"{n} {s:+.1f} sigma"
                for n, s in zip(r["most_moved"], r["most_moved_sigmas"].to_numpy(float), strict=True)
            ],
            "temperature C": r["temperature_c"],
        }
    )


def render_fleet_html(history: FleetHistory, status: FleetStatus) -> str:
    o = status.options
    results = history.results.assign(result=np.arange(len(history.results)))
    rule = (
        f"Flags: <b>moved</b> when a robot's own parameters (not its base frame or tool, which move with the "
        f"cell) changed between its last two results by more than their uncertainties: chi-square of the "
        f"changes over their combined standard errors above its 1 - {o.false_alarm:g}/{status.compared} "
        f"quantile, so with nothing moved the chance of any false flag across the {status.compared} robots "
        f"compared is at most {o.false_alarm:.0%} (Bonferroni; parameters taken as independent). <b>error over "
        f"limit</b> when the latest error after calibration (validation rows when measured) exceeds "
        f"{o.error_limit_m * 1e3:g} mm."
    )
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>hil fleet</title><style>"
        "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;font-size:12px}"
        "td,th{border:1px solid #ccc;padding:2px 6px}section{margin-top:1.5em}</style></head><body>",
        f"<h1>Fleet: {results['robot'].nunique()} robots, {len(results)} results</h1>",
        f"<p>Source: {html.escape(history.source)}</p><p>{rule}</p>",
        "<h2>Attention first</h2>",
        _table(attention_table(status)),
    ]
    by_robot = dict(tuple(results.groupby("robot", sort=False)))
    moves = dict(tuple(parameter_moves(history).groupby("robot", sort=False)))
    empty = pd.DataFrame(columns=["name", "time_s", "z", "half"])
    for robot in status.robots["robot"]:
        rows = by_robot[robot]
        t = rows["time_s"].to_numpy(float)
        listing = pd.DataFrame(
            {
                "date": [_date(v) for v in t],
                "kind": rows["kind"],
                "campaign": rows["label"],
                "before mm": [_mm(v) for v in rows["rms_before_m"].to_numpy(float)],
                "after mm": [_mm(v) for v in rows["rms_after_m"].to_numpy(float)],
                "temperature C": rows["temperature_c"],
                "effects found": rows["effects_found"],
                "assumed": rows["effects_assumed"],
            }
        )
        parts += [
            f"<section id='{html.escape(robot)}'><h3>{html.escape(robot)}</h3>",
            _errors_svg(rows),
            _parameters_svg(moves.get(robot, empty), float(t.min()), float(t.max())),
            _table(listing),
            "</section>",
        ]
    return "".join(parts) + "</body></html>"


def write_fleet_html(path: str | Path, history: FleetHistory, status: FleetStatus) -> None:
    Path(path).write_text(render_fleet_html(history, status))
