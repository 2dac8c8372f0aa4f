"""A diagnosis as a JSON file: every record of the report with its conclusion and cautions in words."""

from __future__ import annotations

import json
import math
from pathlib import Path

from hil.analysis.diagnosis.pipeline import DiagnosisReport
from hil.data.jsonable import to_jsonable
from hil.data.store import OutcomeRecord
from hil.report.text import caution_text, conclusion, gravity_text, thermal_text, tracker_air_text


def report_dict(report: DiagnosisReport) -> dict:
    """The report's data with the conclusion and each caution's words added (what the JSON holds)."""
    out = {}
    for key, value in report.to_dict().items():
        if key == "verdict":
            out["conclusion"] = conclusion(report)
            cautions = report.verdict["cautions"]
            value = {**value, "cautions": [{**c.to_dict(), "text": caution_text(c)} for c in cautions]}
        if key == "thermal" and value is not None:
            value = {**value, "text": thermal_text(value)}
        if key == "tracker_air" and value is not None:
            value = {**value, "text": tracker_air_text(value)}
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


def outcomes_section(outcomes: list[OutcomeRecord]) -> list[dict]:
    """The judged measurements as last judged, for report.json: value and limit in mm or degrees (the
    edges' units, named in `unit`), the bounded side and the outcome (pass, fail, not judged)."""
    latest = {(o.procedure, o.measurement): o for o in outcomes}
    scale = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg")}
    section = []
    for o in latest.values():
        factor, unit = scale.get(o.unit, (1.0, o.unit))
        section.append(
            {
                "procedure": o.procedure,
                "measurement": o.measurement,
                "value": None if o.value is None else o.value * factor,
                "limit": None if o.limit_value is None else o.limit_value * factor,
                "unit": unit,
                "bound": o.bound,
                "outcome": o.verdict.value,
                "note": o.note,
            }
        )
    return section
