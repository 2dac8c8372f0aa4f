"""What calibrate and diagnose record in the campaign they read: the model and its summary, as a ResultRecord.

The summary holds what a plant compares across a robot's campaigns (hil fleet): the error before (the nominal
geometry with only the base frame and the tool registered) and after, on which rows they were taken, every free
parameter's change from the nominal with its standard error, the effects the data found and those held on their
prior, and the temperatures measured. SI units, the unit in each key's name or beside the value.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import CalibrationResult
from hil.analysis.diagnosis.pipeline import DiagnosisReport
from hil.data.store import ResultRecord


def _rms_m(error_mm: float) -> float:
    return float(error_mm) / 1000.0


def _parameters(table: list[dict]) -> list[dict]:
    """Every free parameter's change from the nominal and its standard error (SI), as the fit gave them."""
    return [
        {"name": p["name"], "delta": p["delta"], "std": p["std"], "unit": p["unit"]}
        for p in table
        if p.get("delta") is not None
    ]


def _temperatures(df: pd.DataFrame) -> dict:
    """The arm's (or the air's) temperature over the rows used: mean, min, max in degC; {} without one."""
    if "temperature_c" not in df:
        return {}
    t = pd.to_numeric(df["temperature_c"], errors="coerce").to_numpy(float)
    t = t[np.isfinite(t)]
    if not len(t):
        return {}
    return {
        "temperature_mean_c": float(t.mean()),
        "temperature_min_c": float(t.min()),
        "temperature_max_c": float(t.max()),
    }


def calibration_result(
    result: CalibrationResult, df: pd.DataFrame, rms_before_m: float, robot: str
) -> ResultRecord:
    """hil calibrate's model and summary; before and after are in-sample, on the same training rows."""
    summary = {
        "robot": robot,
        "solver": result.solver,
        "rows": len(df),
        "errors_on": "training rows (in-sample)",
        "rms_before_m": rms_before_m,
        "rms_after_m": _rms_m(result.rms_mm),
        "parameters": _parameters(result.parameter_table()),
        "effects_found": [],
        "effects_assumed": [],
        **_temperatures(df),
    }
    return ResultRecord("calibration", summary, result.model.to_dict())


def diagnosis_result(report: DiagnosisReport, df: pd.DataFrame, robot: str) -> ResultRecord:
    """hil diagnose's model and summary: the held-out error of the uncompensated and of the final model (and on
    the validation rows when given), the geometric fit's parameters, the effects found and assumed."""
    held = [s for s in report.stages if s["on"] == "heldout"]
    validated = [s for s in report.stages if s["on"] == "validate"]
    geometric = report.calibration.get("ridge_igg3", {})
    summary = {
        "robot": robot,
        "rows": len(df),
        "errors_on": "held-out folds of the training rows",
        "rms_before_m": _rms_m(held[0]["rms_mm"]) if held else None,
        "rms_after_m": _rms_m(held[-1]["rms_mm"]) if held else None,
        "validation_rms_m": _rms_m(validated[-1]["rms_mm"]) if validated else None,
        "parameters": _parameters(geometric.get("parameters", [])),
        "effects_found": report.effects_added,
        "effects_assumed": report.effects_assumed,
        "verdict": report.verdict.get("residual"),
        **_temperatures(df),
    }
    return ResultRecord("diagnosis", summary, report.model.to_dict())
