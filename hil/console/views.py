"""What the console's pages read, as typed records: the procedures' forms, a checked plan, the measured points'
deviations from the nominal, and the campaigns of the folder. Millimetres and degrees here (the page's
units), SI underneath."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hil.console.station import CheckedRun
from hil.data.campaign_lock import current_holder
from hil.data.store import CampaignError, CampaignStore, Verdict, is_campaign_file
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import transform_points
from hil.runner.cell_config import CellConfig
from hil.runner.procedure import Parameter, Procedure, Role
from hil.runner.registry import publisher

PLAN_ROWS = 30  # poses listed in the plan before "... and N more"
REPORT_SUFFIX = ".report.html"  # the diagnosis report written beside a campaign
MODEL_SUFFIX = ".model.json"  # the model that diagnosis fitted, beside the campaign
COMPENSATED_SUFFIX = ".compensated.csv"  # the compensated joints of the campaign's validation targets


@dataclass(frozen=True)
class Field:
    """One declared parameter as a form field, in the user's unit."""

    keyword: str
    name: str  # the flag's stem, in words: "inlier", "step"
    flag: str
    help: str
    unit: str
    kind: str  # "int", "float", "str", "bool"
    default: Any
    minimum: float | None
    maximum: float | None
    choices: list[Any]
    count: int
    required: bool
    allowed: str


@dataclass(frozen=True)
class Form:
    name: str
    purpose: str
    instruction: str
    fields: list[Field]


def form(procedure: Procedure) -> Form:
    return Form(
        procedure.name, procedure.purpose, procedure.describe(), [_field(p) for p in procedure.parameters]
    )


def _field(p: Parameter) -> Field:
    default = list(p.default) if isinstance(p.default, tuple) else p.default
    return Field(
        p.keyword, p.name.replace("_", " "), p.flag, p.help, p.unit, p.type.__name__, default, p.minimum,
        p.maximum, list(p.choices), p.count, p.required, p.allowed(),
    )  # fmt: skip


@dataclass(frozen=True)
class PosePlanned:
    number: int
    point_id: str
    step: str
    location: str
    joints_deg: list[float]


@dataclass(frozen=True)
class PlanView:
    """The dry run: what `hil run --dry-run` prints, and its figures for the page."""

    procedure: str
    campaign: str
    poses: int
    operator_steps: int
    estimated_s: float
    detours: int
    unreachable: list[str]
    envelope: str
    text: str
    first_poses: list[PosePlanned]


def plan_view(checked: CheckedRun, config: CellConfig) -> PlanView:
    plan = checked.plan
    detours, impossible = plan.path_check()
    collisions = "and collision " if config.envelope.bodies is not None else ""
    envelope = f"every pose passed the envelope {collisions}check"
    if config.envelope.bodies is None:
        envelope += " (collisions are not checked: [envelope] collisions = false)"
    shown = plan.poses[:PLAN_ROWS]
    q = np.array([p.q_rad for p in shown]).reshape(-1, 6)
    # as the pendant shows them: the controller's joints of a robot that couples its joints
    q = q if config.coupling is None else config.coupling.to_controller(q)
    rows = [
        PosePlanned(k, p.point_id, p.step, p.location, np.rad2deg(q[k - 1]).round(2).tolist())
        for k, p in enumerate(shown, start=1)
    ]
    return PlanView(
        plan.procedure, checked.campaign.name, len(plan.poses), plan.operator_steps,
        plan.estimated_duration_s(), detours, impossible, envelope, _summary(plan.describe(max_rows=0)), rows,
    )  # fmt: skip


def _summary(described: str) -> str:
    """The dry run's summary lines, without its pose table (the page lists the poses itself)."""
    lines = described.splitlines()
    table = next((k for k, line in enumerate(lines) if "joints (deg)" in line), len(lines))
    return "\n".join(lines[:table])


@dataclass(frozen=True)
class PointDeviations:
    """The measured points of a campaign in order, and how far each lies from where the nominal model and the
    campaign's registration put it (mm; none before the campaign has a registration); a reference pose of
    the drift monitor (step `reference`, `r1-003`: pose r1, round 3) also which pose it is (`r1`) and how far
    it moved since its first round (mm, tracker frame: the drift of the cell)."""

    registered: bool
    point_id: list[str]
    procedure: list[str]
    t_s: list[float]  # since the campaign's first point (the instrument's clock)
    temperature_c: list[float | None]
    deviation_mm: list[float | None]
    drift_mm: list[float | None]
    reference_pose: list[str | None]  # the drift monitor's pose a point re-measures, None for other points


def point_deviations(path: Path, config: CellConfig) -> PointDeviations:
    if not is_campaign_file(path):
        return PointDeviations(False, [], [], [], [], [], [], [])
    with CampaignStore(path, create=False) as store:
        df = store.measurements()
        registration = store.step_result(*publisher(Role.REGISTRATION))
    deviation = np.full(len(df), np.nan)
    if registration is not None and len(df):
        T_tracker_base = np.array(registration["T_tracker_base"], float)
        q = np.stack(df["q_rad"].to_list())
        T_base_flange = forward_kinematics(config.nominal, q)
        measured = np.stack(df["p_tracker_m"].to_list())
        for k, nest in enumerate(config.nests_flange_m, start=1):
            rows = (df["location"] == f"nest{k}").to_numpy()
            if rows.any():
                p_base = T_base_flange[rows, :3, :3] @ nest + T_base_flange[rows, :3, 3]
                predicted = transform_points(T_tracker_base, p_base)
                deviation[rows] = np.linalg.norm(measured[rows] - predicted, axis=1) * 1e3
    t = df["timestamp_s"].to_numpy(float)
    return PointDeviations(
        registration is not None,
        df["point_id"].tolist(),
        df["procedure"].tolist(),
        (t - t.min()).round(3).tolist() if len(t) else [],
        _rounded(df["temperature_c"].to_numpy(float), 3),
        _rounded(deviation, 4),
        _rounded(reference_drift_mm(df), 4),
        reference_poses(df).tolist(),
    )


def reference_poses(df: pd.DataFrame) -> np.ndarray:
    """The drift monitor's pose each point re-measures (`r1-003`: `r1`), None for every other point."""
    poses = np.full(len(df), None, dtype=object)
    rows = (df["step"] == "reference").to_numpy()
    if rows.any():
        poses[rows] = df.loc[rows, "point_id"].str.rsplit("-", n=1).str[0].to_numpy()
    return poses


def reference_drift_mm(df: pd.DataFrame) -> np.ndarray:
    """Each reference pose's distance (mm) from its own first measurement; NaN for every other point."""
    drift = np.full(len(df), np.nan)
    rows = (df["step"] == "reference").to_numpy()
    if rows.any():
        measured = np.stack(df.loc[rows, "p_tracker_m"].to_list())
        pose = reference_poses(df)[rows]
        first = {name: measured[k] for k, name in reversed(list(enumerate(pose)))}
        drift[rows] = np.linalg.norm(measured - np.array([first[name] for name in pose]), axis=1) * 1e3
    return drift


def _rounded(values: np.ndarray, digits: int) -> list[float | None]:
    return [None if not np.isfinite(v) else round(float(v), digits) for v in values]


@dataclass(frozen=True)
class ProcedureDone:
    procedure: str
    points: int


@dataclass(frozen=True)
class CampaignEntry:
    """One campaign of the folder: what it holds, how its judged measurements came out, when, who drives it."""

    name: str
    created: str
    last: str
    procedures: list[ProcedureDone]
    passed: int
    failed: int
    not_judged: int
    report: str | None  # the report's file name beside it, when written
    driven_by: str | None
    problem: str = ""
    model: str | None = None  # the diagnosed model's file name beside it, when written
    compensated: str | None = None  # the compensated targets' file name beside it, when written


def history(folder: Path) -> list[CampaignEntry]:
    """Every campaign file in the folder, the newest first."""
    files = [p for p in folder.iterdir() if p.is_file() and is_campaign_file(p)]
    return [_entry(p) for p in sorted(files, key=lambda p: p.stat().st_mtime, reverse=True)]


def _entry(path: Path) -> CampaignEntry:
    holder = current_holder(path)
    driven_by = None if holder is None else holder.describe()
    try:
        with CampaignStore(path, create=False) as store:
            counts = store.point_counts()
            outcomes = store.outcomes()
            created_s = store.created_s
    except CampaignError as exc:
        return CampaignEntry(path.name, "", "", [], 0, 0, 0, None, driven_by, str(exc))
    per_procedure = counts.groupby("procedure", sort=False)["points"].sum()
    verdicts = [o.verdict for o in outcomes]
    last_s = float(counts["last_recorded_s"].max()) if len(counts) else created_s
    return CampaignEntry(
        path.name, _when(created_s), _when(last_s),
        [ProcedureDone(str(name), int(n)) for name, n in per_procedure.items()],
        verdicts.count(Verdict.PASS), verdicts.count(Verdict.FAIL), verdicts.count(Verdict.NOT_JUDGED),
        _beside(path, REPORT_SUFFIX), driven_by,
        model=_beside(path, MODEL_SUFFIX), compensated=_beside(path, COMPENSATED_SUFFIX),
    )  # fmt: skip


def _beside(path: Path, suffix: str) -> str | None:
    """The file name of a result written beside the campaign, None when it is not there."""
    result = path.with_name(path.name + suffix)
    return result.name if result.is_file() else None


def _when(unix_s: float) -> str:
    if not np.isfinite(unix_s):
        return ""
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(unix_s))
