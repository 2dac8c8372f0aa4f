"""Each robot's standing in the fleet, from its calibrations and diagnoses over time (hil.data.fleet_source).

Two flags, each stated with its rule:
- moved: the robot's own parameters (not its base frame or tool points, which move with the cell) changed
  between its last two results by more than their uncertainties. The statistic is the sum over the k
  parameters both results hold of z^2 = (delta_last - delta_before)^2 / (std_last^2 + std_before^2), which is
  chi-square with k degrees of freedom when nothing moved (the parameters taken as independent: their
  correlations are not stored). A robot is flagged above the chi-square quantile 1 - alpha / N for the N
  robots compared, so the chance that any robot of the fleet is flagged while none moved is at most alpha
  (Bonferroni): the fleet's false-alarm rate.
- error: its latest error after calibration (the validation rows' when it had them) above the stated limit.
Robots are sorted by attention: the larger of the statistic over its threshold and the error over its limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.stats import chi2

from hil.data.fleet_source import FleetHistory

DEFAULT_FALSE_ALARM = 0.05
DEFAULT_ERROR_LIMIT_M = 0.5e-3


@dataclass(frozen=True)
class FleetOptions:
    """The fleet's false-alarm rate for the moved flag, and the error limit."""

    false_alarm: float = DEFAULT_FALSE_ALARM
    error_limit_m: float = DEFAULT_ERROR_LIMIT_M


@dataclass(frozen=True)
class FleetStatus:
    """One row per robot, sorted by attention (most first): results, latest time and error, the moved
    statistic (chi2 over dof, threshold, the parameter that moved most, in sigmas), the two flags."""

    robots: pd.DataFrame
    options: FleetOptions
    compared: int  # robots with two results to compare (the N of the Bonferroni threshold)


def fleet_status(history: FleetHistory, options: FleetOptions = FleetOptions()) -> FleetStatus:
    results, params = history.results, history.parameters
    if results.empty:
        return FleetStatus(pd.DataFrame(columns=_COLUMNS), options, 0)
    order = results.assign(result=np.arange(len(results)))
    order["rank_from_last"] = order.groupby("robot", sort=False).cumcount(ascending=False)
    latest = order[order["rank_from_last"] == 0].set_index("robot")
    before = order[order["rank_from_last"] == 1].set_index("robot")
    error = latest["validation_rms_m"].where(latest["validation_rms_m"].notna(), latest["rms_after_m"])
    robots = pd.DataFrame(
        {
            "robot_model": latest["robot_model"],
            "cell_name": latest["cell_name"],
            "results": order.groupby("robot", sort=False).size(),
            "latest_time_s": latest["time_s"],
            "latest_error_m": error,
            "temperature_c": latest["temperature_c"],
        }
    )
    moved = _moved(params, latest["result"], before["result"])
    robots = robots.join(moved)
    compared = int(robots["dof"].fillna(0).gt(0).sum())
    per_robot = options.false_alarm / max(compared, 1)
    dof = robots["dof"].fillna(0).to_numpy(int)
    threshold = np.where(dof > 0, chi2.ppf(1.0 - per_robot, np.maximum(dof, 1)), np.nan)
    robots["threshold"] = threshold
    robots["moved"] = robots["chi2"].to_numpy(float) > threshold
    robots["error_flag"] = robots["latest_error_m"].to_numpy(float) > options.error_limit_m
    robots["attention"] = np.fmax(
        robots["chi2"].to_numpy(float) / threshold,
        robots["latest_error_m"].to_numpy(float) / options.error_limit_m,
    )
    robots = robots.sort_values("attention", ascending=False, na_position="last", kind="stable")
    return FleetStatus(robots.reset_index(names="robot")[_COLUMNS], options, compared)


_COLUMNS = [
    "robot", "robot_model", "cell_name", "results", "latest_time_s", "latest_error_m", "temperature_c",
    "chi2", "dof", "threshold", "most_moved", "most_moved_sigmas", "moved", "error_flag", "attention",
]  # fmt: skip


def _moved(params: pd.DataFrame, latest: pd.Series, before: pd.Series) -> pd.DataFrame:
    """Per robot with two results: the chi-square of its own parameters' change, its dof, and the parameter
    that moved most (in combined sigmas)."""
    own = params[params["own"] & params["std"].gt(0) & params["delta"].notna()]
    last = own.merge(latest.rename("result").reset_index(), on="result")
    prev = own.merge(before.rename("result").reset_index(), on="result")
    pair = last.merge(prev, on=["robot", "name"], suffixes=("", "_before"))
    if pair.empty:
        return pd.DataFrame(columns=["chi2", "dof", "most_moved", "most_moved_sigmas"], dtype=float)
    z = (pair["delta"] - pair["delta_before"]) / np.hypot(pair["std"], pair["std_before"])
    pair = pair.assign(z=z, z2=z**2, abs_z=z.abs())
    grouped = pair.groupby("robot", sort=False)
    most = pair.loc[grouped["abs_z"].idxmax(), ["robot", "name", "z"]].set_index("robot")
    return pd.DataFrame(
        {
            "chi2": grouped["z2"].sum(),
            "dof": grouped.size(),
            "most_moved": most["name"],
            "most_moved_sigmas": most["z"],
        }
    )
