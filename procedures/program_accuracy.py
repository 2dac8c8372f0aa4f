"""Program accuracy: how close does a URScript program put the TCP to the poses it names, measured?

Shop-floor instruction: the cell is registered and calibrated (`hil diagnose ... -o model.json`); the
program's TCP is the SMR in nest 1 (set_tcp to the nest's offset), so where the TCP stands is what the
tracker measures. Put SMR 1 in tool nest 1. The robot walks the program's motions in their order and stops
at each of its waypoints, where the tracker measures the SMR: first the original program, then, when given,
the compensated one (`hil compensate model.json PROGRAM.script -o OUT.script`), waypoint for waypoint.

Each waypoint's error is the measured SMR centre against where the program meant the TCP: its pose in the
robot's base frame placed by the model (`T_tracker_base`), the TCP in force there, the model's SMR point
in the flange. The original program's waypoints are visited at the joints the controller's own inverse
kinematics gives them (the nominal model, on the branch nearest get_inverse_kin's qnear or the previous
motion, as a controller chooses); the compensated program's at the joints it names. A taught joint
position (a motion to a joint list) is visited in its place in the order and not judged; targets the
program computes at run time are listed and not visited. Blends and movec's arc do not change where a
waypoint is: the robot stops at each.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.compensation.urscript import JointTarget, PoseTarget, ProgramMotions, read_program
from hil.geometry.ik import branches_along_path, default_home
from hil.model.calibrated_model import CalibratedModel
from hil.report.program_page import WaypointRow, program_page
from hil.runner.cell_config import CellConfig
from hil.runner.engine import CampaignStopped
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.procedure import Parameter, ParameterError, Procedure
from hil.runner.session import Session

NAME = "program_accuracy"
ORIGINAL, COMPENSATED = "original", "compensated"


@dataclass(frozen=True)
class ProgramAccuracyOptions:
    """The declared parameters: the program, its compensated version, the model, the page to write."""

    program: str
    compensated: str | None
    model: str
    html: str | None


@dataclass(frozen=True)
class Waypoint:
    """One stop of the program: its point id, line, whether it is judged, and where the SMR was meant to be."""

    point_id: str
    line: int
    command: str
    judged: bool  # False for a taught joint position
    meant_tracker_m: np.ndarray  # (3,) NaN when not judged
    q_original: np.ndarray
    q_compensated: np.ndarray | None


@dataclass(frozen=True)
class ProgramAccuracy:
    """Per judged waypoint its measured errors; the RMS per run; targets not visited (run-time poses)."""

    program: str
    waypoints: list[WaypointRow]  # error_m per run (original, compensated): |measured - meant|
    runtime_lines: list[int]

    def rms_m(self, run: str) -> float:
        e = np.array([w.error_m[run] for w in self.waypoints if run in w.error_m])
        return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")

    def runs(self) -> list[str]:
        return [r for r in (ORIGINAL, COMPENSATED) if any(r in w.error_m for w in self.waypoints)]


def waypoints(
    model: CalibratedModel, original: ProgramMotions, compensated: ProgramMotions | None
) -> list[Waypoint]:
    """The program's stops in order (movec's via is passed, not a stop), each with its joints in both runs."""
    stops = [m for m in original.motions if not (isinstance(m, PoseTarget) and m.role == "via")]
    other = None
    if compensated is not None:
        other = [m for m in compensated.motions if not (isinstance(m, JointTarget) and m.role == "via")]
        if [(m.line, m.command) for m in other] != [(m.line, m.command) for m in stops]:
            raise ParameterError(
                "the compensated program's motions are not the original's, line for line: give the program "
                "hil compensate wrote from this one"
            )
    p_smr = np.asarray(model.tools[sorted(model.tools)[0]], float)
    q_prev = default_home(model.nominal)
    out = []
    for k, m in enumerate(stops):
        q_comp = None
        if other is not None:
            if not isinstance(other[k], JointTarget):
                raise ParameterError(f"line {m.line}: the compensated program has no joints there")
            q_comp = np.asarray(other[k].q, float)  # type: ignore[union-attr]
        if isinstance(m, JointTarget):
            q_prev = m.q
            out.append(Waypoint(f"w{k + 1:03d}", m.line, m.command, False, np.full(3, np.nan), m.q, q_comp))
            continue
        ref = q_prev if m.q_near is None else m.q_near
        q_prev = branches_along_path(model.nominal, m.T_base_flange[None], ref)[0]
        T = m.T_base_flange
        meant = model.T_tracker_base[:3, :3] @ (T[:3, :3] @ p_smr + T[:3, 3]) + model.T_tracker_base[:3, 3]
        out.append(Waypoint(f"w{k + 1:03d}", m.line, m.command, True, meant, q_prev, q_comp))
    return out


def _read(path: str | None) -> ProgramMotions | None:
    if path is None:
        return None
    try:
        return read_program(Path(path).read_text(encoding="utf-8", errors="replace"), path)
    except OSError as exc:
        raise ParameterError(f"cannot read the program {path}: {exc}") from exc


def _setup(
    config: CellConfig, program: str, compensated: str | None, model: str
) -> tuple[list[Waypoint], ProgramMotions]:
    try:
        calibrated = CalibratedModel.load(model)
    except (OSError, ValueError, KeyError) as exc:
        raise ParameterError(f"cannot read the model {model}: {exc}") from exc
    original = _read(program)
    assert original is not None
    return waypoints(calibrated, original, _read(compensated)), original


def plan(config: CellConfig, options: ProgramAccuracyOptions) -> Plan:
    """The original program's stops, then the compensated program's, each with SMR 1 in nest 1."""
    if config.coupling is not None:  # a program's joints are its controller's: not read as such yet
        raise ParameterError(
            f"{config.robot_model} couples its joints ({config.coupling.describe()}); program_accuracy reads a "
            "URScript program's joints as the kinematic ones and does not run on such a robot yet: measure the "
            "arm with grid_sampling and judge the model on its validation poses (hil diagnose)"
        )
    stops, _ = _setup(config, options.program, options.compensated, options.model)
    place = OperatorStep("Put SMR 1 in tool nest 1.", "place_smr", smr=1, location="nest1")
    poses = [PlannedPose(w.point_id, NAME, ORIGINAL, w.q_original, "nest1", setup=(place,)) for w in stops]
    poses += [
        PlannedPose(w.point_id, NAME, COMPENSATED, w.q_compensated, "nest1", setup=(place,))
        for w in stops
        if w.q_compensated is not None
    ]
    return Plan(NAME, poses, config, operator_steps=1)


def measure(session: Session, options: ProgramAccuracyOptions, the_plan: Plan) -> ProgramAccuracy:
    """Visit every stop of the plan, then judge each waypoint's measured SMR centre against the meant one."""
    program, html = options.program, options.html
    stops, original = _setup(session.config, program, options.compensated, options.model)
    session.engine.visit(the_plan)
    errors: list[WaypointRow] = []
    measured = {}
    for run in (ORIGINAL, COMPENSATED):
        rec = session.recorded_points(NAME, run)
        measured[run] = dict(zip(rec.point_id, rec.p_tracker_m, strict=True))
    for w in stops:
        if not w.judged:
            continue
        e = {
            run: float(np.linalg.norm(measured[run][w.point_id] - w.meant_tracker_m))
            for run in measured
            if w.point_id in measured[run]
        }
        if ORIGINAL not in e:
            raise CampaignStopped(
                f"waypoint {w.point_id} (line {w.line}) has no measurement", "run the procedure again"
            )
        errors.append(WaypointRow(w.point_id, w.line, w.command, e))
    result = ProgramAccuracy(program, errors, [r.line for r in original.runtime])
    if html is not None:
        notes = [
            f"not visited: a target computed at run time on line {line}" for line in result.runtime_lines
        ]
        page = program_page(f"Program accuracy: {Path(program).name}", errors, result.runs(), notes)
        Path(html).write_text(page, encoding="utf-8")
    return result


def summary(result: ProgramAccuracy) -> str:
    """A table of every judged waypoint's error per run and the RMS of each run."""
    runs = result.runs()
    head = "  waypoint  line  command   " + "  ".join(f"{r:>12}" for r in runs) + "   (mm)"
    rows = [
        f"  {w.name:8}  {w.line:4d}  {w.command:7}   "
        + "  ".join(f"{w.error_m[r] * 1e3:12.4f}" if r in w.error_m else f"{'-':>12}" for r in runs)
        for w in result.waypoints
    ]
    rms = "  RMS                       " + "  ".join(f"{result.rms_m(r) * 1e3:12.4f}" for r in runs)
    lines = [
        f"program accuracy of {result.program}: {len(result.waypoints)} waypoints measured",
        head,
        *rows,
        rms,
    ]
    if result.runtime_lines:
        lines.append(
            f"not visited: targets computed at run time on line(s) {', '.join(map(str, result.runtime_lines))}"
        )
    return "\n".join(lines)


PROCEDURE = Procedure(
    name=NAME,
    purpose="measure a URScript program's waypoints against the poses it names, original and compensated",
    instruction=__doc__ or "",
    parameters=(
        Parameter(
            "program",
            "the URScript program (.script), its poses in the robot's base frame",
            None,
            str,
            required=True,
        ),
        Parameter(
            "compensated", "the program hil compensate wrote from it (absent: the original only)", None, str
        ),
        Parameter(
            "model", "the calibrated model (model.json) that places the base frame", None, str, required=True
        ),
        Parameter(
            "html", "write the table and a plot of every waypoint's errors to this HTML file", None, str
        ),
    ),
    plan=plan,
    body=measure,
    steps=(ORIGINAL, COMPENSATED),
    summary=summary,
    options=ProgramAccuracyOptions,
)
