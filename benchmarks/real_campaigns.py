"""Diagnosis across two public UR10 + Leica campaigns (christianlandgraf/ipa-robot-accuracy, series B and C):
trained on one campaign, validated on the other, both ways; then what `--propose` asks for on each.

Run:  PYTHONPATH=. python benchmarks/real_campaigns.py DATA_DIR [--reregister base] [--propose 100]
      (or set HIL_REAL_DATA=DATA_DIR). DATA_DIR is a checkout of the repository (Series_B/..., Series_C/...)
      or a bare git directory of it (read with `git show HEAD:...`). Without data the script says so and exits 0.

Per direction: the plain (geometric) calibration's RMS on the other campaign against the final diagnosed
model's (goal: final <= plain), the effects named, the links' thermal growth against the robot file's
material, each joint's stiffness under the link masses' gravity, and the open questions with the plan's
groups.
The data is never copied into this repository.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from hil.geometry.urdf_write import UR_JOINTS

CAMPAIGNS = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
    "C": "Series_C/measurements_random_poses.csv",
}
JOINT_NAMES = UR_JOINTS  # the UR ROS description's joint names, the CSV headers


def read_raw(data_dir: Path, series: str) -> pd.DataFrame:
    """One series' measurement table as published (semicolons, decimal commas), from a checkout or a bare
    git directory."""
    rel = CAMPAIGNS[series]
    if (data_dir / rel).is_file():
        return pd.read_csv(data_dir / rel, sep=";", decimal=",")
    text = subprocess.run(
        ["git", "-C", str(data_dir), "show", f"HEAD:{rel}"], check=True, capture_output=True, text=True
    ).stdout
    return pd.read_csv(io.StringIO(text), sep=";", decimal=",")


def to_contract(raw: pd.DataFrame, orientation: bool = True) -> pd.DataFrame:
    """The published table in hil's dataset contract: joints (rad), the T-Mac's position (mm, tracker frame),
    the temperature and, with `orientation`, the probe's angles re-expressed from the export's intrinsic
    x-y-z Euler angles in hil's own convention. The timestamp (a number rounded to 6 digits) is dropped:
    it cannot order or time the rows."""
    from hil.data.dataset import convert_orientation_convention, joint_columns, validate_dataset

    out = pd.DataFrame(
        {c: raw[name].to_numpy(float) for c, name in zip(joint_columns(6), JOINT_NAMES, strict=True)}
    )
    for ax in "xyz":
        out[f"{ax}_mm"] = raw[f"measurement_{ax}"].to_numpy(float)
    out["temperature_c"] = raw["measurement_temperature"].to_numpy(float)
    if orientation:
        for ax in "xyz":
            out[f"r{ax}_deg"] = raw[f"measurement_r{ax}"].to_numpy(float)
        out = convert_orientation_convention(out, "xyz-intrinsic")
    return validate_dataset(out, source="public campaign")


def _rms(stages: list[dict], on: str) -> tuple[float, float]:
    """(plain calibration, final model) RMS mm on the validation rows of `on`: the plain calibration is the
    "kinematic" stage (the first validation stage without re-registration is the uncompensated nominal model)."""
    rows = [s for s in stages if s["on"] == on]
    return next(s["rms_mm"] for s in rows if s["stage"] == "kinematic"), rows[-1]["rms_mm"]


def run(
    data_dir: Path, reregister: str, propose_n: int, orientation: bool, angle_noise_deg: float | None = None
) -> int:
    """Both directions; returns 1 when a final model is worse than plain calibration on the other campaign."""
    from hil.analysis.design.plan import propose
    from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis

    data = {s: to_contract(read_raw(data_dir, s), orientation) for s in ("B", "C")}
    if angle_noise_deg is not None:  # as `hil diagnose --probe-angle-noise-deg` passes it
        for df in data.values():
            df.attrs["probe_angle_noise_rad"] = float(np.deg2rad(angle_noise_deg))
    worse = 0
    on = "validate" if reregister == "none" else "validate, base re-registered"
    print(
        f"{'train':<6}{'val':<5}{'rows':>6}{'plain mm':>10}{'final mm':>10}  effects  (reregister {reregister})"
    )
    for train, val in (("C", "B"), ("B", "C")):
        t0 = time.perf_counter()
        report = run_diagnosis(
            data[train],
            "ur10",
            df_validate=data[val],
            options=DiagnosisOptions(reregister_validation=reregister),
        )
        plain, final = _rms(report.stages, on)
        worse += final > plain * 1.0001
        named = ", ".join(
            f"{e['name']} j{e['joint']}" if e["joint"] else e["name"]
            for e in report.to_dict()["effects_added"]
        )
        print(
            f"{train:<6}{val:<5}{len(data[train]):>6}{plain:>10.3f}{final:>10.3f}  {named or 'none'}  ({time.perf_counter() - t0:.0f} s)"
        )
        if report.thermal:  # the links' growth against the robot file's material
            th = report.thermal
            print(
                f"      growth {th['fitted_per_k'] * 1e6:.1f} +- {th['std_per_k'] * 1e6:.1f} ppm/K (material "
                f"{th['material_per_k'] * 1e6:.1f}) over {th['span_k']:.2f} K, data share {th['data_share']:.2f}"
            )
        for g in report.gravity:  # each joint's yield under the link masses' gravity
            k, dk = g["stiffness_knm_per_rad"], g["stiffness_std_knm_per_rad"]
            size = f"{k:.0f} +- {dk:.0f} kN m/rad" if k is not None else "no positive compliance"
            size += " (held rigid)" if "held_negative_compliance" in g else ""
            print(
                f"      gravity j{g['joint']}: {size}, data share {g['data_share']:.2f}, found {g['found']}"
            )
        if propose_n:
            sigma = float(np.sqrt(np.mean(report.noise.sigma_axis_m**2)))
            plan = propose(data[train], report.model, report.undecided, propose_n, sigma)
            kinds = ", ".join(sorted({q.kind.value for q in report.undecided})) or "none"
            print(f"      open questions: {kinds}")
            for g in plan.groups:
                extra = (
                    f", evidence z {g['evidence_z_before']:.2g} -> {g['evidence_z_after']:.2g}"
                    if "evidence_z_after" in g
                    else ""
                )
                print(f"      plan {g['purpose']}: {g['rows']} rows{extra}")
            for g in plan.not_planned:
                qu = g["question"].to_dict()
                about = qu.get("effect") or qu.get("parameters")
                print(f"      not planned {qu['kind']} {about}: {g['why']}")
            print(f"      plan rows: {len(plan.purpose)} of at most {propose_n}")
    return 1 if worse else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "data", nargs="?", default=os.environ.get("HIL_REAL_DATA"), help="the data repository"
    )
    parser.add_argument("--reregister", default="base", choices=("none", "base", "base+tool"))
    parser.add_argument("--propose", type=int, default=100, help="plan size to ask for (0: no plan)")
    parser.add_argument("--positions-only", action="store_true", help="ignore the probe's orientation")
    parser.add_argument(
        "--probe-angle-noise-deg", type=float, default=None, help="the probe's angle noise (default: hil's)"
    )
    args = parser.parse_args()
    if not args.data or not Path(args.data).exists():
        print(
            "real_campaigns: no data (give the ipa-robot-accuracy repository as DATA_DIR or HIL_REAL_DATA); skipped"
        )
        return 0
    return run(
        Path(args.data), args.reregister, args.propose, not args.positions_only, args.probe_angle_noise_deg
    )


if __name__ == "__main__":
    sys.exit(main())
