"""Targets of `hil compensate` read from a campaign file: where the campaign meant the SMR to be, per point id.

- `grid` / `validation` (grid_sampling): the SMR centre the commanded joints aimed at, tracker frame: the
  robot's nominal kinematics (the campaign's cell config) at the commanded joints, the measurement's nest
  (tool fit when the campaign has one, else the drawing) and the campaign's registration; one SMR, so
  point targets. Each keeps its point id, its nest and the time / temperature it was measured at, and the
  commanded joints seed its compensation (same posture and branch, the SMR still facing the tracker).
- `loop` (pseudo_target): the loop's own targets (SMR 1 in nest 1), poses when it ran with three SMRs; their
  orientation is written as rx_deg, ry_deg, rz_deg in the dataset's convention (hil.data.dataset).

The nominal robot is rebuilt from the campaign's station snapshot: the robot file's text it keeps (hil.runner.cell_config
`CellConfig.snapshot`), else a built-in name; never from the current directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hil.commands.errors import CliError
from hil.data.campaigns import open_campaign
from hil.data.dataset import orientation_columns
from hil.data.store import Campaign, CampaignError
from hil.geometry.coupling import JointConvention
from hil.geometry.kinematics import KinematicModel, forward_kinematics
from hil.geometry.robots import (
    get_robot,
    is_robot_file,
    robot_coupling,
    robot_file_path,
    robot_from_text,
    with_file_path,
)
from hil.runner.procedure import Role
from hil.runner.registry import publisher

# --step NAME -> (procedure, step) in the campaign, a role's publisher; the default is the first of
# DEFAULT_ORDER it holds
SOURCES: dict[str, tuple[str, str] | Role] = {
    "loop": ("pseudo_target", "targets"),
    "validation": Role.VALIDATION,
    "grid": Role.GRID,
}
DEFAULT_ORDER: tuple[str, ...] = ("loop", "validation", "grid")


@dataclass
class CampaignTargets:
    """Targets (tracker frame, m): points (N, 3) or poses (N, 4, 4); `frame` holds the columns the output
    starts with (point_id, step_id, smr, x_mm.. [rx_deg..] [t_s, temperature_c]); `smr` the nest per target;
    `robot` the name of the campaign's nominal robot."""

    step: str
    targets: np.ndarray
    frame: pd.DataFrame
    smr: np.ndarray
    robot: str
    q_seed: np.ndarray | None = None  # (N, 6) joints to start each target's IK from (the commanded ones)


def _source(name: str) -> tuple[str, str]:
    """(procedure, step) of a --step name: named here, or the registered publisher of its role."""
    source = SOURCES[name]
    return publisher(source) if isinstance(source, Role) else source


def available_steps(store: Campaign) -> dict[str, int]:
    """Target sources the campaign holds (--step names) and how many targets each has."""
    out: dict[str, int] = {}
    for name in SOURCES:
        procedure, step = _source(name)
        if procedure == "pseudo_target":
            pinned = store.step_result(procedure, step)
            n = len(pinned.get("targets_m", [])) if pinned is not None else 0
        else:  # measurements with the SMR in a nest (a face or hole probe is no target)
            n = int((store.measurement_columns(["smr"], procedure, step)["smr"] > 0).sum())
        if n:
            out[name] = n
    return out


def read_campaign_targets(
    path: str | Path, step: str | None = None, orientation_convention: str = "xyz-extrinsic"
) -> CampaignTargets:
    """The targets of one step of a campaign (default: loop, else validation, else grid); pose targets get
    rx_deg, ry_deg, rz_deg in `orientation_convention` (hil.data.dataset's names). CliError on bad input."""
    if step is not None and step not in SOURCES:
        raise CliError(f"--step {step!r} is not a target source", f"give --step {' | '.join(SOURCES)}")
    try:
        store = open_campaign(path, create=False)
    except CampaignError as exc:
        raise CliError.from_text(str(exc)) from exc
    with store:
        have = available_steps(store)
        if not have:
            held = ", ".join(
                f"{r.procedure}/{r.step} ({r.points})" for r in store.point_counts().itertuples()
            )
            raise CliError(
                f"campaign {path} holds no targets (it holds: {held or 'no measurements'})",
                "run `hil run grid_sampling` or `hil run pseudo_target` on it first, or give a targets CSV",
            )
        if step is None:
            step = next(s for s in DEFAULT_ORDER if s in have)
        elif step not in have:
            listing = ", ".join(f"{s} ({n})" for s, n in have.items())
            raise CliError(
                f"campaign {path} has no {step} targets; it has: {listing}",
                f"give --step {' | '.join(have)}",
            )
        if step == "loop":
            return _loop_targets(store, campaign_robot(store, path).name, orientation_convention)
        return _commanded_points(store, path, step, campaign_robot(store, path))


def campaign_robot(store: Campaign, path: str | Path) -> KinematicModel:
    """The campaign's nominal robot from its newest station snapshot naming one: the robot file's text the
    snapshot keeps, else the built-in name; an older snapshot's robot file is looked for beside its cell file."""
    name, text = _campaign_robot_definition(store, path)
    try:
        return get_robot(name) if text is None else robot_from_text(text, name)
    except ValueError as exc:
        raise CliError(
            f"campaign {path}: its robot cannot be rebuilt: {exc}",
            "give the targets as a CSV (hil campaign export, then x_mm, y_mm, z_mm)",
        ) from exc


def campaign_kinematic_joints(store: Campaign, path: str | Path, q: np.ndarray) -> np.ndarray:
    """Joints (N, n) read from the campaign as the model's: a session records the controller's joints
    (`joint_convention` of its snapshot), converted here when the campaign's robot couples its joints."""
    recorded = [
        s["joint_convention"] for s in store.snapshots() if isinstance(s, dict) and "joint_convention" in s
    ]
    if not recorded or recorded[-1] != str(JointConvention.CONTROLLER):
        return q
    name, text = _campaign_robot_definition(store, path)
    coupling = robot_coupling(name, text)
    return q if coupling is None else coupling.to_kinematic(q)


def _campaign_robot_definition(store: Campaign, path: str | Path) -> tuple[str, str | None]:
    """(name, robot file text or None for a built-in) of the robot of the campaign's newest snapshot naming one."""
    for snapshot in reversed(store.snapshots()):
        definition = snapshot.get("robot_definition")
        cell_robot = snapshot.get("cell", {}).get("robot", {})
        if isinstance(definition, dict) and isinstance(definition.get("file_text"), str):
            return str(definition.get("file", "robot file")), definition["file_text"]
        model = definition.get("model") if isinstance(definition, dict) else cell_robot.get("model")
        if not isinstance(model, str):
            continue
        if not is_robot_file(model):
            return model, None
        file = _robot_file_beside_cell(model, snapshot.get("source"), path)
        return with_file_path(model, file), file.read_text()
    raise CliError(
        f"campaign {path} has no station snapshot naming the robot ([robot] model)",
        "give the targets as a CSV (hil campaign export, then x_mm, y_mm, z_mm)",
    )


def _robot_file_beside_cell(model: str, cell_source: object, path: str | Path) -> Path:
    """A robot file named by a snapshot that keeps no copy of it (older campaigns): the path as written in the
    cell file, relative to that file's folder."""
    file = robot_file_path(model)
    if not file.is_absolute() and isinstance(cell_source, str):
        file = Path(cell_source).parent / file
    if not file.is_file():
        raise CliError(
            f"campaign {path} names the robot file {model!r} but keeps no copy of it, and it is not at {file}",
            f"put the robot file back at {file}, or give the targets as a CSV (hil campaign export)",
        )
    return file


def _drawing_nests_m(store: Campaign) -> dict[int, np.ndarray]:
    for snapshot in reversed(store.snapshots()):
        nests = snapshot.get("cell", {}).get("tool", {}).get("nests_flange_mm")
        if isinstance(nests, list):
            return {k + 1: np.asarray(v, float) / 1e3 for k, v in enumerate(nests)}
    return {}


def _commanded_points(store: Campaign, path: str | Path, step: str, robot: KinematicModel) -> CampaignTargets:
    """SMR centres the commanded joints aimed at, by nominal kinematics + nest + registration (tracker frame)."""
    procedure, step_name = _source(step)
    reg = store.step_result(*publisher(Role.REGISTRATION))
    if reg is None:
        raise CliError(
            f"campaign {path} has no registration: its commanded points have no place in the tracker frame",
            "run `hil run registration` on the campaign, or give the targets as a CSV",
        )
    T_tracker_base = np.asarray(reg["T_tracker_base"], float)
    nests = _drawing_nests_m(store)
    fit = store.step_result(*publisher(Role.TOOL)) or {}
    nests.update({int(k): np.asarray(v, float) / 1e3 for k, v in fit.get("nests_flange_mm", {}).items()})
    m = store.measurements(procedure, step_name)
    m = m[m["smr"] > 0]
    if m.empty:
        raise CliError(f"campaign {path}: no {step} point was measured in a tool nest", "give another --step")
    smr = m["smr"].to_numpy(int)
    unknown = sorted(set(smr) - set(nests))
    if unknown:
        raise CliError(
            f"campaign {path}: nest(s) {', '.join(map(str, unknown))} have no position in the flange (no tool fit, "
            "not in the cell config)",
            "run `hil run tool_fit` on the campaign, or give the targets as a CSV",
        )
    q = campaign_kinematic_joints(store, path, np.stack(m["q_target_rad"].to_numpy()).astype(float))
    T = forward_kinematics(robot, q)
    p_flange = np.array([nests[s] for s in smr])
    p_base = np.einsum("nij,nj->ni", T[:, :3, :3], p_flange) + T[:, :3, 3]
    p = p_base @ T_tracker_base[:3, :3].T + T_tracker_base[:3, 3]
    frame = pd.DataFrame({"point_id": m["point_id"].astype(str).to_numpy(), "step_id": step, "smr": smr})
    for i, axis in enumerate("xyz"):
        frame[f"{axis}_mm"] = p[:, i] * 1e3
    frame["t_s"] = m["timestamp_s"].to_numpy(float) - store.started_s
    frame["temperature_c"] = m["temperature_c"].to_numpy(float)  # NaN where no sensor read it
    return CampaignTargets(step, p, frame, smr, robot.name, q_seed=q)


def _loop_targets(store: Campaign, robot: str, orientation_convention: str) -> CampaignTargets:
    """The pseudo-target loop's targets (SMR 1 in nest 1): points, or poses when it ran with three SMRs (no
    time or temperature: the loop pinned where, not when)."""
    pinned = store.step_result(*_source("loop"))
    assert pinned is not None  # available_steps found it
    targets = np.asarray(pinned["targets_m"], float)
    ids = [f"t{k + 1:03d}" for k in range(len(targets))]
    frame = pd.DataFrame({"point_id": ids, "step_id": "loop", "smr": 1})
    p = targets[:, :3, 3] if targets.ndim == 3 else targets
    for i, axis in enumerate("xyz"):
        frame[f"{axis}_mm"] = p[:, i] * 1e3
    if targets.ndim == 3:  # the targeted frame's orientation in the tracker frame, as the dataset writes it
        for col, values in orientation_columns(targets[:, :3, :3], orientation_convention).items():
            frame[col] = values
    return CampaignTargets("loop", targets, frame, np.ones(len(targets), int), robot)
