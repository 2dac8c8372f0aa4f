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
(after compensation to the same name with '-after').

Path accuracy (the standard's AT and RT): after the pose cycles, the SMR runs `path_runs` times along each of
two paths in the same diagonal plane, with the same tool orientation, at `path_speed_m_s`: the line from P2 to
P4 (one moveL) and a circle about P1 of diameter 0.8 x the side, commanded as a closed polygon of
CIRCLE_VERTICES moveL waypoints (ur-rtde's path form without blending: the arm stops at each vertex, so on
the circle the speed is the commanded one only between vertices). While the robot moves, the tracker samples
the SMR every STREAM_INTERVAL_S in its continuous time mode, each sample stamped with the tracker's clock;
every run's samples are recorded in the campaign as soon as it ends (a resumed run repeats no finished run).
The commanded point of a sample is its foot on the commanded path (tracker frame), searched forward only. The
whole path, densely, is checked reachable and inside the envelope, the speed held over at least half the line,
and the tracker checked able to stream, before anything moves. With `csv` the samples go to '<csv>-paths'
(and '-paths-after') in the columns `hil iso9283 --paths` reads.

Orientation (AP_a/b/c, RP_a/b/c): with `smrs` >= 3, SMRs 1..k sit in tool nests 1..k and the tracker reads
each at every pose (the robot stands still between them); the tool's attained orientation is the rigid fit
of the nests' flange positions (the tool fit's, else the drawing's) to the readings, its commanded one the
held flange orientation seen through the same frame as the positions; the angles are rx, ry, rz about the
fixed tracker axes (R = Rz Ry Rx), written as rx/ry/rz_deg and rx/ry/rz_cmd_deg in the campaign rows. The
model-based compensation corrects positions, not the orientation, so AP_a/b/c stay about the same after it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hil.analysis.standards.iso9283 import (
    POSE_LABELS,
    Iso9283Report,
    PathFigures,
    commanded_along,
    cube_poses,
    path_campaign_figures,
    pose_performance,
    report_table,
)
from hil.compensation.model_based import CompensationOptions, compensate
from hil.data.dataset import orientation_columns
from hil.data.store import campaign_dataset
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import fit_rigid
from hil.model.calibrated_model import CalibratedModel
from hil.runner.cell_config import CellConfig
from hil.runner.clear_joints import plan_clear_joints
from hil.runner.engine import Advance, MeasurePath, Measuring, PathOptions
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import facing_poses, linear_path_joints, plan_joints, workspace_box
from hil.runner.procedure import SHOTS, Parameter, Procedure
from hil.runner.session import Session

NAME = "iso9283"
APPROACH_RAD = np.deg2rad(2.0)  # pre-position below every joint: one approach direction per pose
SIDES_M = (0.5, 0.4, 0.3, 0.25, 0.2, 0.15, 0.1)  # the cube's side, largest first, when none is given
STEPS = ("before", "after")
PATH_NAMES = ("line", "circle")
PATH_ACCEL_M_S2 = 1.2  # the controller's default tool acceleration (ur-rtde's moveL default)
CIRCLE_DIAMETER = 0.8  # the circle's diameter as a fraction of the cube's side
CIRCLE_VERTICES = 24  # the circle as a closed polygon of this many moveL segments
STREAM_INTERVAL_S = 0.01  # the tracker samples the moving SMR at 100 Hz
ENVELOPE_STEP_M = 0.005  # the paths are checked reachable and inside the envelope at this spacing


@dataclass(frozen=True)
class Cube:
    """The test cube: centre and side (base frame, m), its five poses' SMR positions and nominal joints."""

    centre_m: np.ndarray
    side_m: float
    p_base_m: np.ndarray  # (5, 3)
    q_rad: np.ndarray  # (5, 6) nominal IK, the "before" joints
    R_base_flange: np.ndarray  # (3, 3) the tool orientation held at every pose and along the paths


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
        # P1 in its clearest configuration, the others on P1's branch: one arm and wrist configuration for
        # all five poses
        first = plan_clear_joints(
            config.nominal, config.envelope, T[:1], p_nest, config.nests_flange_m, config.q_home_rad
        )
        rest = plan_joints(config.nominal, T[1:], p_nest, q_near=first.q[0] if first.usable[0] else None)
        joints_q = np.vstack([first.q, rest.q])
        reason = np.concatenate([first.reason, rest.reason]).astype(object)  # room for "envelope"
        usable = np.concatenate([first.usable, rest.usable])
        if usable.all():
            outside = config.envelope.outside(config.nominal, joints_q, config.nests_flange_m)
            reason[outside] = "envelope"
            usable &= ~outside
        if usable.all():
            return Cube(centre, float(side), p, joints_q, R[:3, :3])
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
    options = CompensationOptions(threshold_m=1e-6, max_iter=10)
    res = compensate(model, targets, options, q_seed=cube.q_rad, q_near=config.q_home_rad)
    bad = ~np.all(np.isfinite(res.q), axis=1)
    if bad.any():
        raise ValueError(
            f"the model finds no joints for pose(s) {', '.join(POSE_LABELS[i] for i in np.flatnonzero(bad))}; "
            "choose a cube inside the calibrated volume"
        )
    if config.envelope.outside(config.nominal, res.q, config.nests_flange_m).any():
        raise ValueError("the compensated joints leave the envelope; choose a smaller cube")
    return res.q


def path_shapes(cube: Cube) -> dict[str, np.ndarray]:
    """The commanded SMR paths (base frame, (M, 3) polylines) on the cube's diagonal plane: the line P2 -> P4
    and the closed circle about P1 (diameter CIRCLE_DIAMETER x side) starting on the plane's horizontal axis."""
    p = cube.p_base_m
    e1 = (p[2] - p[1]) / np.linalg.norm(p[2] - p[1])  # along the plane, horizontal (P2 -> P3)
    e2 = (p[4] - p[1]) / np.linalg.norm(p[4] - p[1])  # along the plane, vertical (P2 -> P5)
    angle = np.linspace(0.0, 2 * np.pi, CIRCLE_VERTICES + 1)
    radius = 0.5 * CIRCLE_DIAMETER * cube.side_m
    circle = p[0] + radius * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)
    circle[-1] = circle[0]
    return {"line": p[[1, 3]].copy(), "circle": circle}


def flange_waypoints(R_base_flange: np.ndarray, p_smr_base_m: np.ndarray, p_nest_m: np.ndarray) -> np.ndarray:
    """Flange poses (M, 4, 4) that put the nest's SMR on the points (M, 3) with the flange orientation R."""
    T = np.tile(np.eye(4), (len(p_smr_base_m), 1, 1))
    T[:, :3, :3] = R_base_flange
    T[:, :3, 3] = p_smr_base_m - R_base_flange @ p_nest_m
    return T


def check_path(
    config: CellConfig, T_base_flange: np.ndarray, nest: int, q_near: np.ndarray, label: str
) -> np.ndarray:
    """The joints at the path's start, after checking that the nominal IK reaches every point of the flange
    path (straight between waypoints, every ENVELOPE_STEP_M) away from singularities and inside the envelope."""
    p_nest = config.nests_flange_m[nest - 1]
    points, joints = linear_path_joints(config.nominal, T_base_flange, p_nest, q_near, ENVELOPE_STEP_M)
    if not joints.usable.all():
        k = int(np.flatnonzero(~joints.usable)[0])
        raise ValueError(
            f"the {label} path is not reachable at {np.round(points[k] * 1e3, 1).tolist()} mm "
            f"({joints.reason[k]}); choose a smaller --side-mm or another --centre-mm"
        )
    outside = config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"the {label} path leaves the envelope at {np.round(points[k] * 1e3, 1).tolist()} mm (SMR, base "
            "frame); nothing moved: choose a smaller --side-mm or another --centre-mm"
        )
    return joints.q[0]


def check_speed(speed_m_s: float, line_m: float) -> None:
    """Refuse a speed the line cannot hold over at least half its length (ramps at PATH_ACCEL_M_S2)."""
    ramps_m = speed_m_s**2 / PATH_ACCEL_M_S2  # accelerating and braking, both ends
    if ramps_m > 0.5 * line_m:
        top = np.sqrt(0.5 * line_m * PATH_ACCEL_M_S2)
        raise ValueError(
            f"--path-speed-m-s {speed_m_s:g}: at {PATH_ACCEL_M_S2:g} m/s^2 the arm would spend {ramps_m * 1e3:.0f} mm "
            f"of the {line_m * 1e3:.0f} mm line getting to and from that speed; give at most {top:.3f} m/s "
            "or a larger cube"
        )


@dataclass(frozen=True)
class PathRun:
    """One path as one step runs it: the flange waypoints sent, the start joints, and the commanded SMR
    path (base frame) the figures are taken against."""

    name: str
    T_base_flange: np.ndarray  # (K, 4, 4)
    q_start: np.ndarray  # (6,)
    p_commanded_base_m: np.ndarray  # (M, 3)


def plan_paths(
    config: CellConfig, cube: Cube, nest: int, model: CalibratedModel | None, speed_m_s: float
) -> dict[str, list[PathRun]]:
    """Each step's paths (before; after compensation with a model), every one checked before any motion."""
    shapes = path_shapes(cube)
    check_speed(speed_m_s, float(np.linalg.norm(shapes["line"][1] - shapes["line"][0])))
    p_nest = config.nests_flange_m[nest - 1]
    out: dict[str, list[PathRun]] = {"before": []}
    if model is not None:
        out["after"] = []
    for name, p in shapes.items():
        T = flange_waypoints(cube.R_base_flange, p, p_nest)
        q0 = check_path(config, T, nest, cube.q_rad[0], name)
        out["before"].append(PathRun(name, T, q0, p))
        if model is None:
            continue
        q_nominal = plan_joints(config.nominal, T @ _translation(p_nest), p_nest, q_near=q0).q
        M = model.T_tracker_base
        options = CompensationOptions(threshold_m=1e-6, max_iter=10)
        res = compensate(model, p @ M[:3, :3].T + M[:3, 3], options, q_seed=q_nominal, q_near=q0)
        if not np.all(np.isfinite(res.q)):
            raise ValueError(
                f"the model finds no joints along the {name} path; choose a cube inside the calibrated volume"
            )
        T_after = forward_kinematics(config.nominal, res.q)
        q0_after = check_path(config, T_after, nest, res.q[0], f"compensated {name}")
        out["after"].append(PathRun(name, T_after, q0_after, p))
    return out


def _translation(p_m: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p_m
    return T


@dataclass(frozen=True)
class IsoOptions:
    """The declared parameters, SI (None: absent, the procedure picks)."""

    centre_m: tuple[float, float, float] | None
    side_m: float | None
    cycles: int
    nest: int
    smrs: int
    model: str | None
    path_runs: int
    path_speed_m_s: float
    csv: str | None
    shots: int | None


def plan(config: CellConfig, options: IsoOptions) -> Plan:
    """Every cycle's five poses (and their approach poses), before and, with a model, after compensation,
    each read in `nest` or, with `smrs` > 1, in nests 1..smrs; with path runs, the paths are checked here too
    (reach, envelope, speed), so a refusal comes before motion."""
    centre_m, side_m, cycles, nest, model = (
        options.centre_m, options.side_m, options.cycles, options.nest, options.model
    )  # fmt: skip
    path_runs, path_speed_m_s, smrs = options.path_runs, options.path_speed_m_s, options.smrs
    nests = pose_nests(config, nest, smrs)
    cube = choose_cube(config, centre_m, side_m, nest)
    runs = [("before", cube.q_rad)]
    the_model = load_model(model)
    if the_model is not None:
        runs.append(("after", compensated_joints(config, the_model, cube)))
    if path_runs > 0:
        plan_paths(config, cube, nest, the_model, path_speed_m_s)
    setup = tuple(
        OperatorStep(f"Put SMR {j} in tool nest {j}.", "place_smr", smr=j, location=f"nest{j}") for j in nests
    )
    poses = [
        PlannedPose(
            f"c{c:02d}/{label}" + (f"/n{j}" if len(nests) > 1 else ""),
            NAME,
            step,
            q[k],
            f"nest{j}",
            smr=j,
            approach_q_rad=q[k] - APPROACH_RAD if i == 0 else None,  # the other nests: read where it stands
            setup=setup,
        )  # fmt: skip
        for step, q in runs
        for c in range(1, cycles + 1)
        for k, label in enumerate(POSE_LABELS)
        for i, j in enumerate(nests)
    ]
    return Plan(NAME, poses, config, operator_steps=len(nests))


def pose_nests(config: CellConfig, nest: int, smrs: int) -> tuple[int, ...]:
    """The nests read at every pose: `nest` alone, or nests 1..smrs (which must include `nest`)."""
    available = len(config.nests_flange_m)
    if smrs == 1:
        return (nest,)
    if not 2 <= smrs <= available:
        raise ValueError(f"--smrs {smrs}: the tool has {available} nest(s); give 1..{available}")
    if nest > smrs:
        raise ValueError(
            f"--nest {nest} is not among the nests 1..{smrs} read at each pose; give --nest 1..{smrs}"
        )
    return tuple(range(1, smrs + 1))


@dataclass
class IsoResult:
    """The cube and each run's report (before, and after compensation when a model was given)."""

    cube: Cube
    reports: dict[str, Iso9283Report]
    csv: dict[str, str]
    paths: dict[str, dict[str, PathFigures]] | None = None  # per step, per path
    path_speed_m_s: float | None = None

    def table(self) -> str:
        c = self.cube
        head = (
            f"ISO 9283 pose test: cube of {c.side_m * 1e3:.0f} mm at {np.round(c.centre_m * 1e3, 1).tolist()} mm "
            f"(base frame), SMR facing the tracker, figures in the tracker frame"
        )
        titles = {"before": "before compensation", "after": "after compensation"}
        lines = [head, report_table({titles[k]: v for k, v in self.reports.items()})]
        for step, figures in (self.paths or {}).items():
            lines.append(f"\npath accuracy {titles[step]} at {self.path_speed_m_s:g} m/s (tracker frame)")
            lines.append(f"{'path':<8}{'runs':>5}{'AT_P':>9}{'RT_P':>9}  mm")
            lines += [
                f"{name:<8}{f.runs:>5}{f.AT_m * 1e3:9.4f}{f.RT_m * 1e3:9.4f}" for name, f in figures.items()
            ]
        lines += [f"campaign rows ({step}) written to {path}" for step, path in self.csv.items()]
        return "\n".join(lines)


def campaign_rows(
    session: Session, step: str, p_cmd_tracker_m: np.ndarray, R_cmd_tracker_flange: np.ndarray | None = None
) -> pd.DataFrame:
    """A run's measurements with the standard's columns: pose, cycle and the commanded position. With three
    or more nests read at each pose and the commanded flange orientation (tracker frame), also the tool's
    attained orientation (`tool_orientations`) and the commanded one as rx/ry/rz_deg and rx/ry/rz_cmd_deg."""
    df = campaign_dataset(session.store, NAME, step)
    parts = [p.split("/") for p in df["point_id"]]
    df["pose"] = [p[1] for p in parts]
    df["cycle"] = [int(p[0][1:]) for p in parts]
    index = np.array([POSE_LABELS.index(p[1]) for p in parts])
    for k, ax in enumerate("xyz"):
        df[f"{ax}_cmd_mm"] = p_cmd_tracker_m[index, k] * 1e3
    if R_cmd_tracker_flange is not None and df["smr"].nunique() >= 3:
        nests_m = {int(j): session.nest_flange_m(int(j)) for j in np.unique(df["smr"])}
        R = tool_orientations(df, nests_m)
        for col, values in orientation_columns(R).items():
            df[col] = values
        for col, value in orientation_columns(np.asarray(R_cmd_tracker_flange)[None]).items():
            df[col.replace("_deg", "_cmd_deg")] = float(value[0])
    return df


def tool_orientations(df: pd.DataFrame, nests_flange_m: dict[int, np.ndarray]) -> np.ndarray:
    """R_tracker_flange (N, 3, 3) for every row: the rigid fit of the nests' flange positions to where the
    tracker read them in the same pose and cycle (three or more nests, not on one line)."""
    R = np.empty((len(df), 3, 3))
    for _, rows in df.groupby(["pose", "cycle"], sort=False).indices.items():
        smr = df["smr"].to_numpy(int)[rows]
        measured = df[["x_mm", "y_mm", "z_mm"]].to_numpy(float)[rows] / 1e3
        T, _ = fit_rigid(np.array([nests_flange_m[j] for j in smr]), measured)
        R[rows] = T[:3, :3]
    return R


def path_step(step: str, path: str, run: int) -> str:
    """The campaign step holding one path run's samples."""
    return f"path/{step}/{path}/r{run:02d}"


def path_rows(results: list[tuple[str, int, dict]], commanded: dict[str, np.ndarray]) -> pd.DataFrame:
    """The samples of every run in `hil iso9283 --paths` columns: path, run, t_s, attained x/y/z_mm and the
    commanded point it stands at x/y/z_cmd_mm (its foot on the commanded path, tracker frame)."""
    frames = []
    for name, run, result in results:
        x_m = np.asarray(result["p_tracker_mm"], float).reshape(-1, 3) / 1e3
        c_m = commanded_along(commanded[name], x_m)
        df = pd.DataFrame({"path": name, "run": run, "t_s": np.asarray(result["t_s"], float)})
        for k, ax in enumerate("xyz"):
            df[f"{ax}_mm"] = x_m[:, k] * 1e3
        for k, ax in enumerate("xyz"):
            df[f"{ax}_cmd_mm"] = c_m[:, k] * 1e3
        frames.append(df)
    # to the nanometre, as the CSV export writes them: the figures computed here and by `hil iso9283 --paths`
    # from the file then see the same numbers (the commanded points of samples at rest are nanometres apart)
    out = pd.concat(frames, ignore_index=True)
    mm = [f"{ax}{kind}_mm" for kind in ("", "_cmd") for ax in "xyz"]
    out[mm] = out[mm].round(6)
    return out


def run_paths(
    session: Session,
    step: str,
    paths: list[PathRun],
    *,
    runs: int,
    speed_m_s: float,
    nest: int,
    T_tracker_base: np.ndarray,
) -> pd.DataFrame:
    """`runs` runs of each path, through the engine (recorded ones are read back, not repeated), as `path_rows`."""
    p_flange = session.nest_flange_m(nest)
    requests = [
        MeasurePath(
            NAME, path_step(step, path.name, r), path.q_start, path.T_base_flange,
            PathOptions(
                speed_m_s=speed_m_s, accel_m_s2=PATH_ACCEL_M_S2, interval_s=STREAM_INTERVAL_S,
                p_flange_m=p_flange, approach_q_rad=path.q_start - APPROACH_RAD,
            ),
        )
        for path in paths
        for r in range(1, runs + 1)
    ]  # fmt: skip
    results = session.engine.run(_path_runs(f"iso9283 paths {step}", requests))
    names_runs = [(path.name, r) for path in paths for r in range(1, runs + 1)]
    T = T_tracker_base
    commanded = {p.name: p.p_commanded_base_m @ T[:3, :3].T + T[:3, 3] for p in paths}
    return path_rows([(n, r, res) for (n, r), res in zip(names_runs, results, strict=True)], commanded)


def _path_runs(phase: str, requests: list[MeasurePath]) -> Measuring[list[dict]]:
    """The engine measures each path run in turn; progress counts the runs."""
    results = []
    for k, request in enumerate(requests):
        yield Advance(phase, k, len(requests))
        result = yield request
        assert isinstance(result, dict)
        results.append(result)
    yield Advance(phase, len(requests), len(requests))
    return results


def _named(csv: str, suffix: str) -> Path:
    return Path(csv).with_name(f"{Path(csv).stem}{suffix}{Path(csv).suffix}")


def assess(session: Session, options: IsoOptions, the_plan: Plan) -> IsoResult:
    """Run the cycles and the path runs (resumable), then compute each step's figures and record them."""
    reg = session.require_registration()
    centre_m, side_m, nest, model, csv = (
        options.centre_m,
        options.side_m,
        options.nest,
        options.model,
        options.csv,
    )
    path_runs, path_speed_m_s, smrs, shots = (
        options.path_runs,
        options.path_speed_m_s,
        options.smrs,
        options.shots,
    )
    cube = choose_cube(session.config, centre_m, side_m, nest)
    the_model = load_model(model)
    paths = plan_paths(session.config, cube, nest, the_model, path_speed_m_s) if path_runs > 0 else {}
    if paths:
        session.streaming_tracker(STREAM_INTERVAL_S)  # refuse a tracker that cannot stream before any motion
    session.engine.visit(the_plan, shots=shots, pin=True)
    frames = {"before": reg.T_tracker_base}
    if the_model is not None:
        frames["after"] = the_model.T_tracker_base
    samples = {
        step: run_paths(
            session, step, paths[step], runs=path_runs, speed_m_s=path_speed_m_s, nest=nest, T_tracker_base=T
        )
        for step, T in frames.items()
        if paths
    }
    reports, written, path_figures = {}, {}, {}
    for step, T in frames.items():
        R_cmd = T[:3, :3] @ cube.R_base_flange if smrs >= 3 else None
        df = campaign_rows(session, step, cube.p_base_m @ T[:3, :3].T + T[:3, 3], R_cmd)
        reports[step] = pose_performance(df, source=f"{NAME} {step}", smr=nest)
        result = reports[step].to_dict()
        if step in samples:
            path_figures[step] = path_campaign_figures(samples[step], source=f"{NAME} {step} paths")
            result["paths"] = {k: v.to_dict() for k, v in path_figures[step].items()}
            result["path_speed_m_s"] = path_speed_m_s
        session.finish_step(NAME, step, result)
        if csv:
            path = Path(csv) if step == "before" else _named(csv, "-after")
            df.drop(columns=["point_id", "step_id"]).to_csv(path, index=False, float_format="%.10g")
            written[step] = str(path)
            if step in samples:
                path = _named(csv, "-paths" if step == "before" else "-paths-after")
                samples[step].to_csv(path, index=False, float_format="%.12g")
                written[f"{step} paths"] = str(path)
    return IsoResult(cube, reports, written, path_figures or None, path_speed_m_s if paths else None)


def summary(result: IsoResult) -> str:
    return result.table()


PROCEDURE = Procedure(
    name=NAME,
    purpose="ISO 9283 pose accuracy and repeatability and path accuracy on the standard's cube, before and "
    "after compensation",
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
            "smrs",
            "SMRs in tool nests 1..k read at every pose; 3 or more also give the tool's orientation AP_a/b/c, "
            "RP_a/b/c (default: the one in --nest)",
            1,
            int,
            minimum=1,
        ),  # fmt: skip
        Parameter(
            "model", "calibrated model (model.json): also run the test on compensated joints", None, str
        ),
        Parameter(
            "path_runs",
            "runs of each path, the line and the circle (the standard: 10); 0 leaves path accuracy out",
            10,
            int,
            minimum=0,
            maximum=100,
        ),  # fmt: skip
        Parameter(
            "path_speed_m_s",
            "path speed in m/s (the standard: 100, 50 and 10 per cent of the rated speed; UR: 1.0, 0.5, 0.1)",
            0.25,
            float,
            minimum=0.005,
            maximum=1.0,
        ),  # fmt: skip
        Parameter(
            "csv", "write the campaign rows for `hil iso9283` here (CSV; paths to <name>-paths)", None, str
        ),
        SHOTS,
    ),
    plan=plan,
    body=assess,
    steps=STEPS,
    summary=summary,
    options=IsoOptions,
)
