"""Diagnosis report in words: the conclusion for the terminal, JSON (machine-readable) and one
self-contained HTML page with embedded plots. The diagnosis returns its verdict as data; the wording is here."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from hil.analysis.calibration.solve import USER_UNITS, in_user_units
from hil.analysis.diagnosis.drift_monitor import drift_text
from hil.analysis.diagnosis.pipeline import DiagnosisReport
from hil.analysis.diagnosis.screening import effect_label
from hil.report.json_report import report_dict
from hil.report.png import png_img
from hil.report.text import (
    final_orientation_text,
    gravity_text,
    intervals_text,
    plan_text,
    thermal_text,
    tracker_air_text,
    undecided_text,
)


def _plots(report: DiagnosisReport) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    for step in report.steps:
        p = step.plot
        if not p:
            continue
        fig, ax = plt.subplots(figsize=(6.5, 3.6))
        x = np.asarray(p["driver"], float)
        if len(np.unique(x)) <= 3:  # a sign: spread the points sideways to show their distribution
            x = x + np.random.default_rng(0).uniform(-0.15, 0.15, len(x))
        ax.scatter(x, p["residual_before_mm"], s=9, alpha=0.6, label="before (held-out)")
        ax.scatter(x, p["residual_after_mm"], s=9, alpha=0.6, label="after (held-out)")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(p["driver_label"])
        ax.set_ylabel("residual along the effect (mm)")
        ax.set_title(step.title())
        ax.legend(fontsize=8)
        out.append((f"Residual against the driver of {step.title()}", png_img(fig)))
    held = [(k, v) for k, v in report.histograms.items() if not k.endswith("[validate]")]
    if len(held) >= 2:
        fig, ax = plt.subplots(figsize=(6.5, 3.6))
        first, last = held[1] if len(held) > 2 else held[0], held[-1]
        bins = np.linspace(0, max(np.percentile(first[1], 99), np.percentile(last[1], 99)), 40)
        for label, values in (first, last):
            ax.hist(values, bins=bins.tolist(), alpha=0.55, label=label)
        ax.axvline(report.noise_floor_mm, color="k", ls="--", lw=1, label="noise floor (RMS)")
        ax.set_xlabel("held-out 3-D error (mm)")
        ax.set_ylabel("points")
        ax.legend(fontsize=8)
        out.append(("Held-out error before and after", png_img(fig)))
    return out


FOLD_ROWS = 12  # a table longer than this is folded below its first rows (the summary line says how many)


def cell_text(value: object, fmt: str = ".4g") -> str:
    """A value as a person reads it: numbers formatted, yes/no for a flag, 'none' for nothing, lists joined."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "-" if value != value else format(value, fmt)
    if isinstance(value, list | tuple):
        return ", ".join(cell_text(v, fmt) for v in value) or "none"
    if isinstance(value, dict):
        return "; ".join(f"{k} {cell_text(v, fmt)}" for k, v in value.items()) or "none"
    return str(value)


def _table(rows: list[dict], columns: list[str], fmt: dict | None = None) -> str:
    """An HTML table of `rows` (values in words: yes/no, none); one longer than FOLD_ROWS shows its first
    rows and folds the rest below."""
    fmt = fmt or {}
    head = "".join(f"<th>{html.escape(c.replace('_', ' '))}</th>" for c in columns)
    body = [
        "<tr>"
        + "".join(f"<td>{html.escape(cell_text(r.get(c), fmt.get(c, '.4g')))}</td>" for c in columns)
        + "</tr>"
        for r in rows
    ]
    if len(body) <= FOLD_ROWS:
        return f"<table><tr>{head}</tr>{''.join(body)}</table>"
    return (
        f"<table><tr>{head}</tr>{''.join(body[:FOLD_ROWS])}</table>"
        f"<details><summary>all {len(body)} rows</summary><table><tr>{head}</tr>{''.join(body)}</table></details>"
    )


def render_html(
    report: DiagnosisReport,
    compensation: dict | None = None,
    active: str | None = None,
    tool_fit: dict | None = None,
    outcomes: list[dict] | None = None,
) -> str:
    """The report page; `compensation` (procedures.pseudo_target's summary) adds the measured loop's table,
    `active` the active loop's rounds (an HTML section, hil.report.rounds.rounds_html), `tool_fit`
    (the campaign's tool_fit step result) the tool fit's checks and its validation figure, `outcomes`
    (hil.report.json_report.outcomes_section) the declared measurements as the engine judged them."""
    d = report_dict(report)
    parts = [*_head_html(report, d)]
    if compensation:  # the deliverable: what the robot does on held-out targets, right after the verdict
        parts.append(_compensation_html(compensation))
    parts += [
        *_effects_html(report),
        *_thermal_html(report.thermal),
        *_gravity_html(report.gravity),
        *_tracker_air_html(report.tracker_air),
        *_drift_html(report.drift),
        *_residual_html(report, d),
        _undecided_html(report),
    ]
    if active:
        parts.append(active)
    if tool_fit:
        parts.append(tool_fit_html(tool_fit))
    if outcomes:
        parts.append(outcomes_html(outcomes))
    parts += [*_calibration_html(d), _run_html(report.run)]
    parts.append("</body></html>")
    return "\n".join(parts)


def _head_html(report: DiagnosisReport, d: dict) -> list[str]:
    """Page head, the conclusion, the noise floor, the error at each stage and the run record."""
    return [
        "<!doctype html><html><head><meta charset='utf-8'><title>hil calibration report</title>",
        "<style>body{font-family:sans-serif;max-width:1180px;margin:2em auto;padding:0 1em}"
        "p,li,pre{overflow-wrap:anywhere;white-space:pre-wrap}table{border-collapse:collapse;margin:0.5em 0;"
        "display:block;max-width:100%;overflow-x:auto}td,th{border:1px solid #bbb;padding:2px 8px;"
        "text-align:right}th{background:#eee}img{max-width:100%;height:auto}"
        "h2{border-bottom:1px solid #888}</style></head><body>",
        "<h1>Calibration and diagnosis</h1>",
        _provenance_html(report.run),
        "<p><b>" + "<br>".join(html.escape(line) for line in d["conclusion"].splitlines()) + "</b></p>",
        f"<p>Noise floor: {report.noise_floor_mm:.4f} mm RMS ({html.escape(report.noise.method)}).</p>",
        "<h2>Error at each stage (mm)</h2>",
        _table(
            d["stages"],
            ["stage", "on", "mean_mm", "rms_mm", "max_mm", "p95_mm"],
            dict.fromkeys(["mean_mm", "rms_mm", "max_mm", "p95_mm"], ".4f"),
        ),
        "<p>held-out = k-fold cross-validation on the training campaign; validate = a separate campaign "
        "never used for fitting.</p>",
        f"<p>{html.escape(intervals_text(report.intervals) or '')}</p>",
    ]


def in_report_units(row: dict) -> dict:
    """An effect coefficient's row with its value and standard error in the report's units (deg, mm, ppm)."""
    si = row.get("unit", "")
    if si not in USER_UNITS:
        return row
    scaled = {
        k: in_user_units(row[k], si) if isinstance(row.get(k), float) else row.get(k)
        for k in ("value", "std")
    }
    return {**row, **scaled, "unit": USER_UNITS[si][0]}


def _effects_html(report: DiagnosisReport) -> list[str]:
    """Each effect added (or removed) with its gain, parameters and the candidates of its round."""
    parts = ["<h2>Effects added</h2>"]
    if not report.steps:
        found = report.effects_added
        if found:  # physics terms the data found: the verdict names them, so say where they are
            names = ", ".join(effect_label(e["name"], e["joint"]) for e in found)
            parts.append(
                f"<p>{html.escape(names)}: physics terms the data found (their sections below); no candidate "
                "effect beside them improved the held-out error significantly.</p>"
            )
        else:
            beside = " beside the physics terms (below)" if report.gravity or report.thermal else ""
            parts.append(
                f"<p>None{beside}: no candidate effect improved the held-out error significantly.</p>"
            )
    for step in report.steps:
        parts.append(f"<h3>{html.escape(step.title())}</h3>")
        parts.append(
            f"<p>held-out RMS {step.heldout_before['rms_mm']:.4f} &rarr; {step.heldout_after['rms_mm']:.4f} mm, "
            f"max {step.heldout_before['max_mm']:.4f} &rarr; {step.heldout_after['max_mm']:.4f} mm</p>"
        )
        if step.summary:
            parts.append(
                "<p>" + html.escape(", ".join(f"{k} = {v:.4g}" for k, v in step.summary.items())) + "</p>"
            )
        parts.append(
            _table(
                [in_report_units(row) for row in step.parameters], ["name", "value", "std", "unit", "free"]
            )
        )
        if step.merged:
            parts.append(
                "<p>Merged (not separable from the geometry): "
                + html.escape(", ".join(m["name"] for m in step.merged))
                + "</p>"
            )
        if step.correlations:
            parts.append(_table(step.correlations, ["coefficient", "parameter", "correlation"]))
        cands = [c.to_dict() for c in step.candidates]
        parts.append("<details><summary>candidates tested in this round</summary>")
        parts.append(
            _table(
                cands,
                ["name", "joint", "n_params", "cv_rms_mm", "gain_mm2", "p_cv", "p_chi2", "passed", "note"],
            )
        )
        parts.append("</details>")
    if report.final_round:
        parts.append("<h3>Last round (nothing passed)</h3>")
        parts.append(
            _table(
                [c.to_dict() for c in report.final_round],
                ["name", "joint", "n_params", "cv_rms_mm", "gain_mm2", "p_cv", "p_chi2", "note"],
            )
        )
    return parts


def _gravity_html(gravity: list[dict]) -> list[str]:
    """The joints' gravity yield from the link masses: compliance, stiffness, data share per joint."""
    if not gravity:
        return []
    keys = ["joint", "stiffness_knm_per_rad", "stiffness_std_knm_per_rad", "compliance_rad_per_nm"]
    keys += ["std_rad_per_nm", "torque_min_nm", "torque_max_nm", "data_share", "standing"]
    return [
        "<h2>Gravity yield of the joints (physics from the link masses: found, assumed or rejected)</h2>",
        f"<p>{html.escape(gravity_text(gravity) or '')}</p>",
        _table(gravity, keys, dict.fromkeys(keys[1:-1], ".3g")),
    ]


def _thermal_html(thermal: dict | None) -> list[str]:
    """The material's thermal growth: fitted against the material's coefficient, with the prior's share."""
    if not thermal:
        return []
    row = {
        "material_ppm_per_K": thermal["material_per_k"] * 1e6,
        "fitted_ppm_per_K": thermal["fitted_per_k"] * 1e6,
        "std_ppm_per_K": thermal["std_per_k"] * 1e6,
        "prior_std_ppm_per_K": thermal["prior_std_per_k"] * 1e6,
        "span_K": thermal["span_k"],
        "data_share": thermal["data_share"],
    }
    return [
        "<h2>Thermal growth of the links (physics: found, assumed or rejected)</h2>",
        f"<p>{html.escape(thermal_text(thermal) or '')}</p>",
        _table([row], list(row), dict.fromkeys(row, ".3g")),
    ]


def _tracker_air_html(tracker_air: dict | None) -> list[str]:
    """The tracker's scale from a stuck air reading: fitted against its prior, with the data's own value."""
    if not tracker_air:
        return []

    def ppm(key: str) -> float | None:
        value = tracker_air[key]
        return None if value is None else value * 1e6

    row = {
        "air_read_degC": tracker_air["air_c"],
        "span_K": tracker_air["span_k"],
        "prior_ppm_per_K": ppm("prior_per_k"),
        "prior_std_ppm_per_K": ppm("prior_std_per_k"),
        "fitted_ppm_per_K": ppm("fitted_per_k"),
        "std_ppm_per_K": ppm("std_per_k"),
        "data_ppm_per_K": ppm("data_per_k"),
        "data_std_ppm_per_K": ppm("data_std_per_k"),
        "data_share": tracker_air["data_share"],
        "standing": tracker_air["standing"],
    }
    return [
        "<h2>Tracker scale from a stuck air reading (physics: found, assumed or rejected)</h2>",
        f"<p>{html.escape(tracker_air_text(tracker_air) or '')}</p>",
        _table([row], list(row), dict.fromkeys(list(row)[:-1], ".3g")),
    ]


def _drift_html(drift: dict | None) -> list[str]:
    """The drift monitor's reference poses: distance from the first visit against time and temperature."""
    if not drift:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.4), sharey=True)
    for s in drift["poses"]:
        label = f"pose {s['pose']}" + (f" nest {s['smr']}" if s["smr"] > 1 else "")
        axes[0].plot(np.asarray(s["t_s"]) / 60.0, s["norm_mm"], "o-", ms=3, label=label)
        axes[1].plot(s["temperature_c"], s["norm_mm"], "o-", ms=3, label=label)
    axes[0].set_xlabel("time since the campaign started (min)")
    axes[1].set_xlabel("temperature (degC)")
    axes[0].set_ylabel("distance from the first visit (mm)")
    axes[0].legend(fontsize=7)
    return [
        "<h2>Drift monitor: reference poses re-measured</h2>",
        f"<p>{html.escape(drift_text(drift) or '')} Growth and the tracker's scale follow the temperature, a "
        "drift of the stand or the floor the time.</p>",
        png_img(fig),
    ]


def _residual_html(report: DiagnosisReport, d: dict) -> list[str]:
    """What is left: residual against noise, the residual maps tried, the plots, the final orientation."""
    rm = d.get("residual_map") or {}
    parts = ["<h2>Residual left</h2>"]
    parts.append(
        f"<p>residual sigma / noise sigma = {rm.get('excess_ratio', float('nan')):.3f}; "
        + (
            "structure the model does not explain: yes"
            if report.unexplained_structure
            else "no structure the model does not explain"
        )
        + "</p>"
    )
    tables = [("spatial", rm), ("random", rm.get("interpolation") or {})]
    rows = [
        {"map": k, "folds": folds, **v}
        for folds, part in tables
        for k, v in [("none", {"rms_mm": part.get("no_map_rms_mm")}), *part.get("candidates", {}).items()]
        if part.get("candidates")
    ]
    if rows:  # spatial folds decide whether a map is added; random folds only whether structure is local
        parts.append(_table(rows, ["map", "folds", "rms_mm", "max_mm", "p95_mm", "p_value", "mode", "error"]))
    parts.append("<h2>Plots</h2>")
    for title, img in _plots(report):
        parts.append(f"<h3>{html.escape(title)}</h3>{img}")
    final_orientation = final_orientation_text(report)
    if final_orientation:
        parts.append(f"<p>{html.escape(final_orientation)}</p>")
    return parts


def _calibration_html(d: dict) -> list[str]:
    """Both solvers' geometric calibration: fit quality, identifiability and parameters."""
    parts = ["<h2>Geometric calibration: both solvers</h2>"]
    for name, cal in d["calibration"].items():
        parts.append(
            f"<h3>{html.escape(name)}</h3><p>sigma0 {cal['sigma0_mm']:.4f} mm, RMS {cal['rms_mm']:.4f} mm, "
            + (f"orientation RMS {cal['orientation_rms_deg']:.4f} deg (6-DoF probe), "
               if cal.get("orientation_rms_deg") is not None else "")
            + f"outlier rows: {html.escape(cell_text(cal['outlier_rows']))}</p>"
        )  # fmt: skip
        ident = cal.get("identifiability") or {}
        if ident:
            parts.append(
                f"<p>condition number {ident['condition_before']:.3g} &rarr; {ident['condition_after']:.3g}; "
                "dropped: "
                + html.escape(
                    "; ".join(
                        f"{x['name']}"
                        + (
                            f" (~ {' '.join(f'{c:+.3g}*{n}' for n, c in x['merged_into'])})"
                            if x["merged_into"]
                            else ""
                        )
                        for x in ident["dropped"]
                    )
                )
                + "</p>"
            )
        parts.append("<details><summary>parameters</summary>")
        parts.append(_table(cal["parameters"], ["name", "value", "delta", "std", "unit"]))
        parts.append("</details>")
    return parts


def _compensation_html(summary: dict) -> str:
    """Uncompensated -> model-based (or nominal IK) -> measured loop on held-out targets, mm (and deg)."""
    names = {
        "uncompensated": "uncompensated",
        "start": summary.get("start", "start"),
        "best_of_iterations": "loop, kept joints as read in the loop",
        "final": "measured loop (kept joints, measured again)",
    }
    rows = []
    for key, label in names.items():
        p = summary["position_mm"].get(key)
        if not p or not p["n"]:  # a summary of before the fresh measurement has no best_of_iterations
            continue
        row = {"stage": label, "targets": p["n"], **{f"{k}_mm": p[k] for k in ("mean", "rms", "max", "p95")}}
        if "orientation_deg" in summary:
            row.update({f"{k}_deg": summary["orientation_deg"][key][k] for k in ("mean", "max")})
        rows.append(row)
    columns = ["stage", "targets", "mean_mm", "rms_mm", "max_mm", "p95_mm"]
    if "orientation_deg" in summary:
        columns += ["mean_deg", "max_deg"]
    return (
        "<h2>Measured pseudo-target loop (held-out targets)</h2>"
        f"<p>{summary['visited']} of {summary['targets']} targets visited, {summary['smrs']} SMR(s), generator "
        f"{html.escape(str(summary['generator']))}, {summary['iterations_mean']:.1f} corrections per target on "
        "average; errors measured by the tracker.</p>"
        + _table(rows, columns, dict.fromkeys(columns[2:], ".4f"))
    )


def _provenance_html(run: dict) -> str:
    """One line under the title: what the report was made from (each input's name and the start of its
    SHA-256), the robot, the instruments the campaign recorded, the software and the date."""
    if not run:
        return ""
    inputs = "; ".join(
        f"{role} {i.get('file') or 'data given in Python'} (sha256 {(i.get('sha256') or '?')[:12]}..., "
        f"{i['rows_used']} rows)"
        for role, i in run["inputs"].items()
    )
    station = run.get("station") or {}
    instruments = "; ".join(f"{k} {cell_text(v)}" for k, v in station.items())
    return (
        f"<p><small>Made from {html.escape(inputs)}. Robot {html.escape(run['robot'])}"
        + (f"; instruments: {html.escape(instruments)}" if instruments else "")
        + f". {html.escape(run['software'])}, {html.escape(run['date_utc'])}. The full record is under Run at "
        "the end.</small></p>"
    )


def _run_html(run: dict) -> str:
    """The run: robot, inputs with hash and row counts (data rows from 1), date, software version."""
    if not run:
        return ""
    rows = [
        {
            "input": role,
            "file": i.get("file") or "data given in Python",
            "sha256": i.get("sha256") or "",
            "rows_in_file": i["rows_in_file"],
            "rows_used": i["rows_used"],
            "duplicate_rows": ", ".join(map(str, i["duplicate_rows"][:10])) or "none",
        }
        for role, i in run["inputs"].items()
    ]
    return (
        f"<h2>Run</h2><p>robot {html.escape(run['robot'])}; {html.escape(run['software'])}; "
        f"{html.escape(run['date_utc'])}</p>"
        + _table(rows, ["input", "file", "sha256", "rows_in_file", "rows_used", "duplicate_rows"])
    )


def write_html(
    report: DiagnosisReport,
    path: str | Path,
    compensation: dict | None = None,
    active: str | None = None,
    tool_fit: dict | None = None,
    outcomes: list[dict] | None = None,
) -> None:
    """Write the self-contained HTML report (tables + PNG plots embedded as base64)."""
    Path(path).write_text(render_html(report, compensation, active, tool_fit, outcomes))


def outcomes_html(outcomes: list[dict]) -> str:
    """The declared measurements against their limits, each with its outcome (pass, fail, not judged)."""
    rows = [{**o, "limit": "" if o["limit"] is None else f"{o['bound']} {o['limit']:.4g}"} for o in outcomes]
    columns = ["procedure", "measurement", "value", "limit", "unit", "outcome"]
    return "<h2>Judged measurements</h2>" + _table(rows, columns, {"value": ".4g"})


def tool_fit_html(fit: dict) -> str:
    """The tool fit (procedures.tool_fit's step result): nests, the checks' figures, and the validation
    figure: each validation pose's error for the flange-hole nest and the distance method's (tool paper, Fig. 10)."""
    rows = [
        {
            "nest": j,
            "x_mm": p[0],
            "y_mm": p[1],
            "z_mm": p[2],
            "sigma_mm": fit.get("uncertainty_mm", {}).get(j),
        }
        for j, p in fit.get("nests_flange_mm", {}).items()
    ]
    parts = ["<h2>Tool fit (flange frame)</h2>", _table(rows, ["nest", "x_mm", "y_mm", "z_mm", "sigma_mm"], {
        k: ".4f" for k in ("x_mm", "y_mm", "z_mm", "sigma_mm")})]  # fmt: skip
    flange, check = fit.get("flange", {}), fit.get("distance_check", {})
    turn, val = fit.get("tool_orientation", {}), fit.get("validation", {})
    figures = [
        ("hole balls off their circle, RMS", flange.get("circle_residual_mm"), "mm"),
        ("face ball height (expected)", flange.get("face_height_mm"), f"mm ({flange.get('face_height_expected_mm', 0):.4f})"),
        ("hole 7 off the 3-4 bisector", flange.get("bisector_error_deg"), "deg"),
        ("tool turned against its drawing", turn.get("rotation_deg"), "deg"),
        ("two methods' nest 1 apart (gate)", check.get("disagreement_mm"), f"mm ({check.get('gate_mm', 0):.2f})"),
        ("validation RMS, flange-hole nest", val.get("rms_mm"), "mm"),
        ("validation RMS, distance-method nest", val.get("distance_method_rms_mm"), "mm"),
    ]  # fmt: skip
    shown = [
        {"check": name, "value": value, "unit": unit} for name, value, unit in figures if value is not None
    ]
    parts.append(_table(shown, ["check", "value", "unit"], {"value": ".4f"}))
    if val.get("errors_mm"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.5, 3.2))
        k = np.arange(1, len(val["errors_mm"]) + 1)
        ax.bar(k - 0.2, val["errors_mm"], width=0.4, label=f"flange holes (RMS {val['rms_mm']:.3f} mm)")
        ax.bar(k + 0.2, val["distance_method_errors_mm"], width=0.4,
               label=f"distance constraint (RMS {val['distance_method_rms_mm']:.3f} mm)")  # fmt: skip
        # poses are counted, not measured: whole numbers on the axis
        ax.set_xticks(k if len(k) <= 25 else k[:: int(np.ceil(len(k) / 25))])
        ax.set_xlabel("validation pose")
        ax.set_ylabel("error after common-point fit (mm)")
        ax.legend(fontsize=8)
        parts.append(f"<h3>Validation on {val['poses']} poses</h3>" + png_img(fig))
    return "\n".join(parts)


def _undecided_html(report: DiagnosisReport) -> str:
    """The open questions and, when one was made, the plan that decides them."""
    parts = [
        "<h2>What this campaign leaves undecided</h2>",
        "<pre>" + html.escape(undecided_text(report)) + "</pre>",
    ]
    if report.plan is not None:
        parts.append("<pre>" + html.escape(plan_text(report.plan)) + "</pre>")
    return "\n".join(parts)
