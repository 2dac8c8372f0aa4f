"""Diagnosis report in words: the conclusion for the terminal, JSON (machine-readable) and one
self-contained HTML page with embedded plots. The diagnosis returns its verdict as data; the wording is here."""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from hil.analysis.calibration import USER_UNITS, in_user_units
from hil.analysis.diagnosis import DiagnosisReport
from hil.analysis.drift_monitor import drift_text
from hil.analysis.residual_maps import MAP_MODES
from hil.analysis.screening import effect_label
from hil.data.jsonable import to_jsonable


def _effect(e: dict) -> str:
    return effect_label(e["name"], e["joint"])


def caution_text(c: dict) -> str:
    """One caution of the verdict (`hil.analysis.diagnosis_baseline.caution`) in words."""
    kind = c["kind"]
    if kind == "calibration_note":
        return c["text"]
    if kind == "first_choice_set_aside":
        return (
            f"a first choice of {_effect(c['effect'])} led to a worse final model ({c['heldout_rms_mm']:.4f} vs "
            f"{c['heldout_rms_without_mm']:.4f} mm held-out); it was set aside"
        )
    if kind == "previous_effects_kept":
        return (
            f"a selection that started from the earlier diagnosis' effects ({', '.join(_effect(e) for e in c['effects'])}) "
            f"predicted held-out points better ({c['heldout_rms_kept_mm']:.4f} mm, p = {c['p_value']:.2g}) than one that "
            f"dropped {', '.join(_effect(e) for e in c['dropped'])} ({c['heldout_rms_mm']:.4f} mm); it was kept"
        )
    if kind == "stage_worse_than_previous":
        return f"stage '{c['stage']}' predicts held-out points worse than the stage before it ({c['rms_mm']:.4f} mm)"
    if kind == "ambiguous_effects":
        return (
            f"on this data {_effect(c['chosen'])} and {_effect(c['confounded_with'])} explain the same residual; "
            "the choice between them is not reliable (measure poses or approach directions that separate them, "
            "e.g. a random visiting order)."
        )
    if kind == "validation_unrepresented":
        v, h = c["validate_rms_mm"], c["heldout_rms_mm"]
        return (
            f"the validation campaign's RMS ({v:.4f} mm) is {v / h:.1f}x the held-out one: the training campaign "
            "does not represent it (poses, visiting order, time, tracker placement), so an effect may be hidden "
            "in the training data by another one; measure a campaign in a random order"
            + ("" if c["reregistered"] else ", or re-register the base on it")
        )
    if kind == "validation_worse_than_geometric":
        return (
            f"on the validation campaign the final model ({c['final_rms_mm']:.4f} mm) predicts worse than the "
            f"geometric one ({c['geometric_rms_mm']:.4f} mm): use the geometric model there"
        )
    if kind == "validation_temperatures_outside":
        (vlo, vhi), (lo, hi) = c["validate_c"], c["training_c"]
        return (
            f"validation temperatures {vlo:.1f}..{vhi:.1f} C lie outside the training's {lo:.1f}..{hi:.1f} C: "
            "the model extrapolates thermal effects (measure the training over the working temperatures)"
        )
    if kind == "thermal_growth_held":
        return (
            f"the temperature's term came out at {c['fitted_per_k'] * 1e6:.1f} ppm/K, far from the links' material "
            f"({c['material_per_k'] * 1e6:.1f} ppm/K): on this campaign the recorded temperature follows something "
            "else (a drift in time, the air's temperature rather than the arm's), so the growth is held at the "
            "material's value; if the arm is of another material, give its expansion_per_k in the robot file"
        )
    if kind == "validation_joints_outside":
        return (
            f"validation joint(s) {', '.join(map(str, c['joints']))} leave the training's range by more than "
            f"{c['margin_deg']:g} deg: the model extrapolates there"
        )
    raise ValueError(f"no wording for the caution kind '{kind}'")


def conclusion(report: DiagnosisReport) -> str:
    """The verdict in words: what was added, what is left, then one caution a line."""
    return conclusion_text(report.verdict, report.effects_added)


def conclusion_text(v: dict, effects_added: list[dict]) -> str:
    """`conclusion` from the verdict data and the effects ({name, joint}) the final model holds."""
    added = ", ".join(_effect(e) for e in effects_added) or "nothing"
    if v["residual"] == "structured":
        text = (
            f"Added: {added}. Structured residual remains that no candidate effect explains (residual sigma "
            f"{v['ratio']:.2f}x the noise floor; a {v['map']} residual map predicts it on held-out points), so a "
            f"residual map is used as the fallback ({MAP_MODES.get(v['map'], v['map'])})."
        )
    elif v["residual"] == "local":
        text = (
            f"Added: {added}. Structured residual remains that no candidate effect explains (residual sigma "
            f"{v['ratio']:.2f}x the noise floor), but only locally: a {v['map']} residual map predicts it between "
            "measured points, not in blocks of the volume held out, so no map is added (it would extrapolate "
            "worse than the model alone). Measure densely where the model is to be used to map it there."
        )
    elif v["residual"] == "excess":
        text = (
            f"Added: {added}. The residual is {v['ratio']:.2f}x the noise floor but shows no structure a residual "
            "map can predict: the noise floor is probably underestimated (robot repeatability?)."
        )
    else:
        text = f"Added: {added}. The residual is at the noise floor ({v['ratio']:.2f}x)."
    return "\n".join([text, *(f"Caution: {caution_text(c)}" for c in v["cautions"])])


def final_orientation_text(report: DiagnosisReport) -> str | None:
    """The final model's orientation residual in words, when a 6-DoF probe was fitted and effects were added
    (without effects the geometric fits' figures say it)."""
    final = report.model.info.get("orientation")
    if not final or not report.model.effects:
        return None
    return f"6-DoF probe, final model (effects included): orientation RMS {final['rms_deg']:.4f} deg"


def thermal_text(thermal: dict | None) -> str | None:
    """The links' thermal growth in words: the fitted coefficient beside the material's, and whether the
    campaign's temperature span or the material's prior set it (None without a material term)."""
    if not thermal:
        return None
    share = thermal["data_share"]
    if "held_conflicting_per_k" in thermal:
        who = (
            f"held at the material's value: the data made {thermal['held_conflicting_per_k'] * 1e6:.0f} ppm/K of "
            "it, which is no growth of the links (see the cautions)"
        )
    elif thermal["data_led"]:
        who = "measured by this campaign"
    elif share < 0.05:
        who = "held at the material's value: the campaign spans too little temperature to measure it"
    else:
        who = "mostly the material's value: the campaign spans too little temperature to measure it well"
    return (
        f"Thermal growth of the links: {thermal['fitted_per_k'] * 1e6:.1f} +- {thermal['std_per_k'] * 1e6:.1f} "
        f"ppm/K fitted, material {thermal['material_per_k'] * 1e6:.1f} ppm/K (temperature span "
        f"{thermal['span_k']:.2f} K, the data carry {100 * share:.0f} % of what is known of it; {who})."
    )


def gravity_text(gravity: list[dict]) -> str | None:
    """The joints' yield under the link masses' gravity in words: each joint's stiffness with its standard
    error, and whether the data found it or the prior (a rigid joint) holds it (None without such terms)."""
    if not gravity:
        return None
    parts = []
    for g in gravity:
        k, dk = g["stiffness_knm_per_rad"], g["stiffness_std_knm_per_rad"]
        if "held_negative_compliance" in g:
            what = (
                f"held rigid: the data made its compliance negative "
                f"({g['held_negative_compliance'] * 1e6:.2g} urad/(N m), the joint yielding against gravity), so "
                "the term stood in for something else"
            )
        elif g["found"]:
            size = f"{k:.0f} +- {dk:.0f} kN m/rad" if dk is not None and dk < k else f"{k:.0f} kN m/rad"
            what = f"{size}, found by the data"
        elif g["data_led"]:
            what = f"no yield seen (compliance {g['compliance_rad_per_nm'] * 1e6:.2g} +- {g['std_rad_per_nm'] * 1e6:.2g} urad/(N m))"
        else:
            what = f"the prior holds it (the data carry {100 * g['data_share']:.0f} %)"
        parts.append(f"joint {g['joint']}: {what}")
    return "Gravity yield from the link masses (joint stiffness): " + "; ".join(parts) + "."


def report_dict(report: DiagnosisReport) -> dict:
    """The report's data with the conclusion and each caution's words added (what the JSON holds)."""
    out = {}
    for key, value in report.to_dict().items():
        if key == "verdict":
            out["conclusion"] = conclusion(report)
            value = {**value, "cautions": [{**c, "text": caution_text(c)} for c in value["cautions"]]}
        if key == "thermal" and value is not None:
            value = {**value, "text": thermal_text(value)}
        if key == "gravity":  # one shape whether or not the robot file gives the masses
            value = {"joints": value, "text": gravity_text(value) if value else ""}
        out[key] = value
    return out


def write_json(report: DiagnosisReport, path: str | Path, extra: dict | None = None) -> None:
    """The report's JSON: effects_added, stages, unexplained_structure, noise_floor_mm, the conclusion and
    the details; `extra`: sections a run adds beside the diagnosis (the demo's active loop and measured loop),
    so the JSON holds what the HTML report shows.

    Strict JSON: NaN and infinities (e.g. a candidate that was never cross-validated) become null.
    """
    text = json.dumps(to_jsonable({**report_dict(report), **(extra or {})}), indent=1, allow_nan=False)
    Path(path).write_text(text)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return '<img src="data:image/png;base64,' + base64.b64encode(buf.getvalue()).decode() + '">'


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
        out.append((f"Residual against the driver of {step.title()}", _png(fig)))
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
        out.append(("Held-out error before and after", _png(fig)))
    return out


def _table(rows: list[dict], columns: list[str], fmt: dict | None = None) -> str:
    fmt = fmt or {}
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = []
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c)
            if isinstance(v, float):
                v = format(v, fmt.get(c, ".4g"))
            cells.append(f"<td>{html.escape('' if v is None else str(v))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def render_html(
    report: DiagnosisReport,
    compensation: dict | None = None,
    active: str | None = None,
    tool_fit: dict | None = None,
) -> str:
    """The report page; `compensation` (procedures.pseudo_target's summary) adds the measured loop's table,
    `active` the active loop's rounds (an HTML section, hil.analysis.active_rounds.rounds_html), `tool_fit`
    (the campaign's tool_fit step result) the tool fit's checks and its validation figure."""
    d = report_dict(report)
    parts = [
        *_head_html(report, d),
        *_effects_html(report),
        *_thermal_html(report.thermal),
        *_gravity_html(report.gravity),
        *_drift_html(report.drift),
        *_residual_html(report, d),
        *_calibration_html(d),
        _undecided_html(report),
    ]
    if tool_fit:
        parts.append(tool_fit_html(tool_fit))
    if active:
        parts.append(active)
    if compensation:
        parts.append(_compensation_html(compensation))
    parts.append("</body></html>")
    return "\n".join(parts)


def _head_html(report: DiagnosisReport, d: dict) -> list[str]:
    """Page head, the conclusion, the noise floor, the error at each stage and the run record."""
    return [
        "<!doctype html><html><head><meta charset='utf-8'><title>hil calibration report</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto}table{border-collapse:collapse;"
        "margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}th{background:#eee}"
        "h2{border-bottom:1px solid #888}</style></head><body>",
        "<h1>Calibration and diagnosis</h1>",
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
        _run_html(report.run),
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
    keys += ["std_rad_per_nm", "torque_min_nm", "torque_max_nm", "data_share", "found"]
    return [
        "<h2>Gravity yield of the joints (physics from the link masses: always in the model)</h2>",
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
        "<h2>Thermal growth of the links (physics: always in the model)</h2>",
        f"<p>{html.escape(thermal_text(thermal) or '')}</p>",
        _table([row], list(row), dict.fromkeys(row, ".3g")),
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
        _png(fig),
    ]


def _residual_html(report: DiagnosisReport, d: dict) -> list[str]:
    """What is left: residual against noise, the residual maps tried, the plots, the final orientation."""
    rm = d.get("residual_map") or {}
    parts = ["<h2>Residual left</h2>"]
    parts.append(
        f"<p>residual sigma / noise sigma = {rm.get('excess_ratio', float('nan')):.3f}; "
        f"unexplained structure: {report.unexplained_structure}</p>"
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
            + f"outlier rows {cal['outlier_rows']}</p>"
        )  # fmt: skip
        ident = cal.get("identifiability") or {}
        if ident:
            parts.append(
                f"<p>condition number {ident['condition_before']:.3g} &rarr; {ident['condition_after']:.3g}; "
                "dropped: "
                + html.escape(
                    "; ".join(
                        f"{x['name']} (~ {' '.join(f'{c:+.3g}*{n}' for n, c in x['merged_into'])})"
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
        "final": "measured loop",
    }
    rows = []
    for key, label in names.items():
        p = summary["position_mm"][key]
        if not p["n"]:
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


def _run_html(run: dict) -> str:
    """The run: robot, inputs with hash and row counts (data rows from 1), date, software version."""
    if not run:
        return ""
    rows = [
        {
            "input": role,
            "file": i.get("file") or "(in memory)",
            "sha256": (i.get("sha256") or "")[:16],
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
) -> None:
    """Write the self-contained HTML report (tables + PNG plots embedded as base64)."""
    Path(path).write_text(render_html(report, compensation, active, tool_fit))


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
        ax.set_xlabel("validation pose")
        ax.set_ylabel("error after common-point fit (mm)")
        ax.legend(fontsize=8)
        parts.append(f"<h3>Validation on {val['poses']} poses</h3>" + _png(fig))
    return "\n".join(parts)


def question_text(q: dict) -> str:
    """One open question of the diagnosis (hil.analysis.undecided) in words: what is undecided and why."""
    kind = q["kind"]
    eff = q.get("effect") or {}
    if kind == "period_not_covered":
        return (
            f"a once-per-turn error of joint {eff['joint']}: its sampled range covers {q['range_deg']:.0f} deg, "
            f"a test needs {q['needs_deg']:.0f} (over a shorter arc it looks like geometry)"
        )
    if kind == "one_approach_direction":
        return (
            f"backlash of joint {eff['joint']}: {q['rows_up']} rows approached it from below, {q['rows_down']} "
            f"from above; a test needs {q['needs_rows']} each way"
        )
    if kind == "drift_unmonitored":
        return (
            f"drift of the cell over time: {q['revisited_poses']} poses were measured again late in the campaign, "
            f"{q['needs_poses']} are needed"
        )
    if kind == "temperature_not_spanned":
        if not q["recorded"]:
            return "thermal growth: the campaign records no temperature; poses cannot decide it"
        return (
            f"thermal growth: the temperature spans {q['span_k']:.2f} K (needs {q['needs_k']:.0f} K); poses cannot "
            "decide it, a run at another temperature can"
        )
    z = q.get("evidence_z")
    ev = "" if z is None else f" (evidence z {z:.2g}, decided at {q['decisive_z']:.2g})"
    if kind == "marginal":
        return f"{_effect(eff)}: marginal, held-out p = {q['p_cv']:.2g}{ev}"
    if kind == "confounded_with_geometry":
        return f"{_effect(eff)}: the geometry imitates it on these poses{ev}"
    if kind == "ambiguous_effects":
        return f"{_effect(eff)} or {_effect(q['rival'])}: both explain the same residual{ev}"
    if kind == "thermal_rivals":
        return (
            f"the tracker's scale or the links' growth: over {q['span_k']:.2g} K the growth may have taken the "
            f"tracker's stretch (about the tracker, not the base){ev}"
        )
    if kind == "confounded_parameters":
        a, b = q["parameters"]
        return f"{a} and {b} correlate {q['correlation']:+.3f}: each alone is unreliable{ev}"
    return kind


def undecided_text(report: DiagnosisReport) -> str:
    """The open questions in words, one a line (or a line that says nothing is undecided)."""
    if not report.undecided:
        return "undecided: nothing; the campaign decides every question the diagnosis asks"
    lines = ["undecided:"]
    lines += [f"  - {question_text(q)}" for q in report.undecided]
    return "\n".join(lines)


def group_text(group: dict) -> str:
    """What one group of a plan's rows should decide."""
    q = group["question"]
    what = question_text(q).split(":")[0]
    if q["kind"] == "period_not_covered":
        extra = f", joint range {group['range_after_deg']:.0f} deg after" + (
            " (and back down: backlash)" if group.get("also") else ""
        )
    elif "evidence_z_after" in group:
        extra = f", evidence z {group['evidence_z_before']:.2g} -> {group['evidence_z_after']:.2g} (decided at {group['decisive_z']:.2g})"
    else:
        extra = ""
    return f"  {group['purpose']:<28} {group['rows']:>3} rows: decides {what}{extra}"


def plan_text(plan: dict) -> str:
    """The plan's groups in words (terminal and HTML); a line that says so when nothing is to be measured."""
    if plan["rows"] == 0:
        lines = ["plan: nothing undecided that poses can decide; the plan holds the header only"]
    else:
        lines = [f"plan: {plan['rows']} poses, in this order:"]
        lines += [group_text(g) for g in plan["groups"]]
    for skipped in plan["not_planned"]:
        lines.append(f"  not planned: {question_text(skipped['question']).split(':')[0]}: {skipped['why']}")
    return "\n".join(lines)


def _undecided_html(report: DiagnosisReport) -> str:
    """The open questions and, when one was made, the plan that decides them."""
    parts = [
        "<h2>What this campaign leaves undecided</h2>",
        "<pre>" + html.escape(undecided_text(report)) + "</pre>",
    ]
    if report.plan is not None:
        parts.append("<pre>" + html.escape(plan_text(report.plan)) + "</pre>")
    return "\n".join(parts)
