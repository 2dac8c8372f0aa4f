"""ISO 9283 pose performance test: the standard's cube, its five poses, n cycles, before and after
compensation, reported in the standard's terms (iso9283_and_axes.md; ISO 9283:1998).

Shop-floor instruction: the cell is registered (`hil run registration`); put SMR 1 in tool nest 1 (the SMR
is the measured point). The test cube stands in the working volume (default: centred in the sampled volume
in front of the tracker, as large as fits, up to 500 mm); its five poses lie on the diagonal plane through
two opposite vertical edges: P1 at the centre, P2..P5 a tenth of the diagonal in from the corners (P2 and P4
opposite). The tool orientation is held at all five (the SMR facing the tracker from the cube's centre).
Each cycle visits P1..P5 in order, each approached from below on every joint (so backlash does not enter
the repeatability); `cycles` cycles (the standard asks 30). The commanded position of a pose is the cube point
in the robot's base frame as the tracker sees it: through the registration before compensation, through the
calibrated model's base after it. With `model` (model.json from `hil calibrate` / `hil diagnose`) the whole
test runs a second time on the model-compensated joints (step `after`), and one table gives both. Per pose:
AP (and its x, y, z parts) and RP; between P2 and P4: AD and RD. `csv` writes the campaign rows (dataset
columns, pose, cycle, x_cmd_mm..) that `hil iso9283` reads, so the figures can be recomputed anywhere
(after compensation to the same name with '-after'). Orientation figures need a 6-DoF probe (not here);
path accuracy is computed by `hil iso9283 --paths` from recorded path samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hil.analysis.calibrated_model import CalibratedModel
from hil.analysis.iso9283 import POSE_LABELS, Iso9283Report, cube_poses, pose_performance, report_table
from hil.compensation.model_based import compensate
from hil.data.store import campaign_dataset
from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import facing_poses, plan_joints, workspace_box
from hil.runner.procedure import SHOTS, Parameter, Procedure
from hil.runner.session import Session

NAME = "iso9283"
APPROACH_RAD = np.deg2rad(2.0)  # pre-position below every joint: one approach direction per pose
SIDES_M = (0.5, 0.4, 0.3, 0.25, 0.2, 0.15, 0.1)  # the cube's side, largest first, when none is given
STEPS = ("before", "after")


@dataclass(frozen=True)
class Cube:
    """The test cube: centre and side (base frame, m), its five poses' SMR positions and nominal joints."""

    centre_m: np.ndarray
    side_m: float
    p_base_m: np.ndarray  # (5, 3)
    q_rad: np.ndarray  # (5, 6) nominal IK, the "before" joints


def choose_cube(
    config: CellConfig, centre_m: tuple[float, ...] | None, side_m: float | None, nest: int
) -> Cube:
    """The cube to test: the one given, else the largest of SIDES_M centred in the sampled volume whose five
    poses are reachable, away from singularities and inside the envelope."""
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"--nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    centre = (
        workspace_box(config.nominal, config.p_base_tracker_m).centre_m
        if centre_m is None
        else np.asarray(centre_m)
    )
    p_nest = config.nests_flange_m[nest - 1]
    R = facing_poses(
        centre[None], config.p_base_tracker_m, np.random.default_rng(0), tilt_deg=0.0, roll_deg=0.0
    )[0]
    reasons: dict[str, int] = {}
    for side in (side_m,) if side_m is not None else SIDES_M:
        p = cube_poses(centre, side)
        T = np.tile(R, (5, 1, 1))
        T[:, :3, 3] = p
        # P1 near home, the others on P1's branch: one arm and wrist configuration for all five poses
        first = plan_joints(config.nominal, T[:1], p_nest, q_near=config.q_home_rad)
        rest = plan_joints(config.nominal, T[1:], p_nest, q_near=first.q[0] if first.usable[0] else None)
        joints_q = np.vstack([first.q, rest.q])
        reason = np.concatenate([first.reason, rest.reason])
        usable = np.concatenate([first.usable, rest.usable])
        if usable.all():
            outside = config.envelope.outside(config.nominal, joints_q, config.nests_flange_m)
            reason[outside] = "envelope"
            usable &= ~outside
        if usable.all():
            return Cube(centre, float(side), p, joints_q)
        for r in reason[~usable]:
            reasons[str(r)] = reasons.get(str(r), 0) + 1
    why = ", ".join(f"{n} {r}" for r, n in sorted(reasons.items()))
    raise ValueError(
        f"no test cube fits at centre {np.round(centre * 1e3, 1).tolist()} mm (poses left out: {why}); give a "
        "smaller --side-mm or another --centre-mm (robot base frame)"
    )


def load_model(model: str | None) -> CalibratedModel | None:
    if model is None:
        return None
    if not Path(model).is_file():
        raise ValueError(
            f"--model {model}: no such file; give a model written by `hil calibrate` or `hil diagnose`"
        )
    return CalibratedModel.load(model)


def compensated_joints(config: CellConfig, model: CalibratedModel, cube: Cube) -> np.ndarray:
    """Joints that make the model put the SMR on the cube's points (its base frame seen by the tracker)."""
    T = model.T_tracker_base
    targets = cube.p_base_m @ T[:3, :3].T + T[:3, 3]
    res = compensate(
        model, targets, q_seed=cube.q_rad, q_near=config.q_home_rad, threshold_m=1e-6, max_iter=10
    )
    bad = ~np.all(np.isfinite(res.q), axis=1)
    if bad.any():
        raise ValueError(
            f"the model finds no joints for pose(s) {', '.join(POSE_LABELS[i] for i in np.flatnonzero(bad))}; "
            "choose a cube inside the calibrated volume"
        )
    if config.envelope.outside(config.nominal, res.q, config.nests_flange_m).any():
        raise ValueError("the compensated joints leave the envelope; choose a smaller cube")
    return res.q


def plan(
    config: CellConfig,
    *,
    centre_m: tuple[float, ...] | None,
    side_m: float | None,
    cycles: int,
    nest: int,
    model: str | None,
) -> Plan:
    """Every cycle's five poses (and their approach poses), before and, with a model, after compensation."""
    cube = choose_cube(config, centre_m, side_m, nest)
    runs = [("before", cube.q_rad)]
    the_model = load_model(model)
    if the_model is not None:
        runs.append(("after", compensated_joints(config, the_model, cube)))
    location = f"nest{nest}"
    setup = (OperatorStep(f"Put SMR {nest} in tool nest {nest}.", "place_smr", smr=nest, location=location),)
    poses = [
        PlannedPose(
            f"c{c:02d}/{label}",
            NAME,
            step,
            q[k],
            location,
            smr=nest,
            approach_q_rad=q[k] - APPROACH_RAD,
            setup=setup,
        )  # fmt: skip
        for step, q in runs
        for c in range(1, cycles + 1)
        for k, label in enumerate(POSE_LABELS)
    ]
    return Plan(NAME, poses, config, operator_steps=1)


@dataclass
class IsoResult:
    """The cube and each run's report (before, and after compensation when a model was given)."""

    cube: Cube
    reports: dict[str, Iso9283Report]
    csv: dict[str, str]

    def table(self) -> str:
        c = self.cube
        head = (
            f"ISO 9283 pose test: cube of {c.side_m * 1e3:.0f} mm at {np.round(c.centre_m * 1e3, 1).tolist()} mm "
            f"(base frame), SMR facing the tracker, figures in the tracker frame"
        )
        titles = {"before": "before compensation", "after": "after compensation"}
        lines = [head, report_table({titles[k]: v for k, v in self.reports.items()})]
        lines += [f"campaign rows ({step}) written to {path}" for step, path in self.csv.items()]
        return "\n".join(lines)


def campaign_rows(session: Session, step: str, p_cmd_tracker_m: np.ndarray) -> pd.DataFrame:
    """A run's measurements with the standard's columns: pose, cycle and the commanded position."""
    df = campaign_dataset(session.store, NAME, step)
    cycle, pose = zip(*(p.split("/") for p in df["point_id"]), strict=True)
    df["pose"] = list(pose)
    df["cycle"] = [int(c[1:]) for c in cycle]
    index = np.array([POSE_LABELS.index(p) for p in pose])
    for k, ax in enumerate("xyz"):
        df[f"{ax}_cmd_mm"] = p_cmd_tracker_m[index, k] * 1e3
    return df


def assess(
    session: Session,
    *,
    centre_m: tuple[float, ...] | None,
    side_m: float | None,
    cycles: int,
    nest: int,
    model: str | None,
    csv: str | None,
    shots: int | None,
) -> IsoResult:
    """Run the cycles (resumable), then compute each run's figures and record them as the step's result."""
    reg = session.require_registration()
    the_plan = plan(session.config, centre_m=centre_m, side_m=side_m, cycles=cycles, nest=nest, model=model)
    session.visit(the_plan, shots=shots, pin=True)
    cube = choose_cube(session.config, centre_m, side_m, nest)
    the_model = load_model(model)
    frames = {"before": reg.T_tracker_base}
    if the_model is not None:
        frames["after"] = the_model.T_tracker_base
    reports, written = {}, {}
    for step, T in frames.items():
        df = campaign_rows(session, step, cube.p_base_m @ T[:3, :3].T + T[:3, 3])
        reports[step] = pose_performance(df, source=f"{NAME} {step}", smr=nest)
        session.finish_step(NAME, step, reports[step].to_dict())
        if csv:
            path = (
                Path(csv)
                if step == "before"
                else Path(csv).with_name(f"{Path(csv).stem}-after{Path(csv).suffix}")
            )
            df.drop(columns=["point_id", "step_id"]).to_csv(path, index=False, float_format="%.10g")
            written[step] = str(path)
    return IsoResult(cube, reports, written)


def summary(result: IsoResult) -> str:
    return result.table()


PROCEDURE = Procedure(
    name=NAME,
    purpose="ISO 9283 pose accuracy and repeatability on the standard's cube, before and after compensation",
    instruction=__doc__ or "",
    parameters=(
        Parameter(
            "centre",
            "the cube's centre x y z, base frame (default: the sampled volume's)",
            None,
            float,
            unit="mm",
            count=3,
        ),  # fmt: skip
        Parameter(
            "side",
            "the cube's side (default: as large as fits, up to 500)",
            None,
            float,
            unit="mm",
            minimum=20.0,
            maximum=2000.0,
        ),  # fmt: skip
        Parameter("cycles", "cycles through P1..P5 (the standard: 30)", 30, int, minimum=2, maximum=1000),
        Parameter("nest", "tool nest holding the SMR", 1, int, minimum=1),
        Parameter(
            "model", "calibrated model (model.json): also run the test on compensated joints", None, str
        ),
        Parameter("csv", "write the campaign rows for `hil iso9283` here (CSV)", None, str),
        SHOTS,
    ),
    plan=plan,
    body=assess,
    steps=STEPS,
    summary=summary,
)
