"""Pseudo-target loop: put the SMR on targets, measured (PT paper; docs/loop/papers.md).

Shop-floor instruction: the cell is registered (`hil run registration`) and, best, a calibrated model
exists (`hil calibrate`). With one SMR, put SMR 1 in tool nest 1: the loop corrects the position. With
three SMRs, put SMRs 1, 2, 3 in tool nests 1, 2, 3: the tracker measures each nest in turn, the known
nest layout gives the tool's pose, and the loop corrects the orientation too.

For each target (tracker frame: where SMR 1 in nest 1 should be, and for three SMRs the flange
orientation) the robot goes to the model-based compensated joints (nominal IK without a model), settles
and is measured. What the measurement missed moves a pseudo target (the chosen generator); its IK, seeded
with the joints just used, gives the next joints. This repeats until the error is below the threshold,
the iteration cap is reached, or `patience` corrections in a row have not beaten the best error so far by
more than the measurement noise (the loop has reached the tracker's noise floor); the best joints measured
are kept. Each target's status says why it ended: ok (below the threshold), max_iter, no_improvement, or
why it was not (or no longer) visited: unreachable, singular, envelope, no_ik_solution, ... Every
iteration is its own point in the campaign (`t007/i2`, with nests `t007/i2/n1`..`n3`), committed before
the next motion: re-running the same command replays what is recorded and measures only what is missing
(the stop rules decide again from the recorded points, so a resumed target ends where it did). Targets
the arm cannot reach, near a singularity or outside the envelope are reported with the reason, not visited.

Without --model the loop starts from the nominal model (no calibration). `--pt-paper` runs the PT paper's
measured experiment: nominal start, three SMRs (the pose from three points), the ZYZ triple-angle generator,
two measured corrections per target whatever their gain. `--targets circle:N` puts N targets on a circle
(the paper's trajectory; the paper's simulation used 2 000 points). `--generator ensemble` runs the
generators named by `--ensemble` at every correction, measures each proposal and keeps the best.
`--approach-deg A` reaches every measured pose through A below it on every joint, so each joint arrives from
the same side every time: on an arm with backlash the plain loop stalls where each correction lands on
another side of the gap (about 0.1 mm on the simulated UR10 with backlash).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from hil.analysis.calibration.noise_floor import tracker_sigma_m
from hil.compensation.model_based import (
    ENSEMBLE,
    CompensationOptions,
    PosePredictor,
    PseudoTargetIK,
    TargetConditions,
    compensate,
    ensemble_names,
    outside_fitted_temperatures,
    pose_cost,
)
from hil.compensation.target_update import GENERATORS, update_pseudo_position, update_pseudo_target
from hil.data.campaigns import open_campaign
from hil.data.dataset import ORIENTATION_COLUMNS, orientations
from hil.data.pg_url import is_campaign_url
from hil.data.store import CampaignError, MeasurementRecord
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import fit_rigid
from hil.model.calibrated_model import CalibratedModel
from hil.runner.cell_config import CellConfig
from hil.runner.clear_joints import plan_clear_joints
from hil.runner.engine import Advance, CampaignStopped, MeasurePose, Measuring
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import (
    SINGULAR_SIGMA_M,
    facing_poses,
    position_sigma_min_m,
    random_points,
    workspace_box,
)
from hil.runner.procedure import SHOTS, Parameter, ParameterError, Procedure, Role
from hil.runner.registry import publisher
from hil.runner.session import Session

NAME = "pseudo_target"
STEP = "loop"
LENGTH_SCALE_M = 0.1  # pose error measure: sqrt(dp^2 + (L * angle)^2), as hil.compensation.model_based
USABLE_START = ("ok", "max_iter", "stalled")  # compensation statuses whose joints are worth measuring
SMR_MODES = (1, 3)
CIRCLE_RADIUS_M = 0.1  # the circle trajectory's radius, in a plane facing the tracker
# The PT paper's measured experiment (--pt-paper): smrs, generator, corrections, patience, threshold (m).
PT_PAPER: tuple[int, str, int, int, float] = (3, "zyz", 2, 0, 0.0005e-3)
PATIENCE = 2  # corrections without a gain beyond the noise margin before a target stops (0: never)
# Noise margin: a correction counts as a gain when it beats the best error so far by more than
# GAIN_SIGMAS x the per-axis 1-sigma noise of the measured point: the larger of the tracker's noise model
# (hil.analysis.calibration.noise_floor.tracker_sigma_m) and the recorded shot spread, each / sqrt(shots).
GAIN_SIGMAS = 1.0


@dataclass
class TargetResult:
    """One target: measured error per iteration (m, rad), the best joints and why the loop ended."""

    target_id: str
    status: str  # ok (below threshold), max_iter, no_improvement, or why it was not (or no longer) visited
    errors_m: list[float] = field(default_factory=list)
    rotation_errors_rad: list[float] = field(default_factory=list)
    q_rad: np.ndarray | None = None  # best joints measured
    best_iteration: int = -1
    uncompensated_error_m: float = np.nan
    uncompensated_rotation_rad: float = np.nan
    noise_m: list[float] = field(default_factory=list)  # per-axis 1-sigma of each measurement
    # The kept joints (`q_rad`) measured once more after the loop: (position m, rotation rad). The reported
    # error; the loop's own minimum (`error_m`) is the best of several noisy readings, partly selection.
    fresh: tuple[float, float] | None = None

    @property
    def iterations(self) -> int:
        """Corrections made (measurements - 1)."""
        return max(len(self.errors_m) - 1, 0)

    @property
    def error_m(self) -> float:
        return self.errors_m[self.best_iteration] if self.errors_m else np.nan

    @property
    def rotation_error_rad(self) -> float:
        return self.rotation_errors_rad[self.best_iteration] if self.rotation_errors_rad else np.nan

    def to_dict(self) -> dict:
        return {
            "target": self.target_id,
            "status": self.status,
            "iterations": self.iterations,
            "errors_mm": [e * 1e3 for e in self.errors_m],
            "rotation_errors_deg": [float(np.rad2deg(r)) for r in self.rotation_errors_rad],
            "error_mm": self.error_m * 1e3,
            "rotation_error_deg": float(np.rad2deg(self.rotation_error_rad)),
            "uncompensated_error_mm": self.uncompensated_error_m * 1e3,
            "noise_sigma_mm": [s * 1e3 for s in self.noise_m],
            "best_iteration": self.best_iteration,
            "fresh_error_mm": None if self.fresh is None else self.fresh[0] * 1e3,
            "fresh_rotation_error_deg": None if self.fresh is None else float(np.rad2deg(self.fresh[1])),
            "q_rad": None if self.q_rad is None else np.round(self.q_rad, 9).tolist(),
        }


def _fresh(t: TargetResult) -> tuple[float, float]:
    """The kept joints' fresh measurement (position m, rotation rad); NaN where none was taken."""
    return t.fresh if t.fresh is not None else (np.nan, np.nan)


def scalar_error_stats(values: np.ndarray) -> dict[str, float]:
    """mean / RMS / max / 95th percentile of errors (NaN rows ignored), in the input's unit."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": np.nan, "rms": np.nan, "max": np.nan, "p95": np.nan, "n": 0}
    return {"mean": float(v.mean()), "rms": float(np.sqrt(np.mean(v**2))), "max": float(v.max()),
            "p95": float(np.percentile(v, 95)), "n": int(v.size)}  # fmt: skip


@dataclass
class LoopResult:
    """All targets and the before / after statistics (mm, deg) of the visited ones."""

    targets: list[TargetResult]
    smrs: int
    generator: str
    model_based: bool

    @property
    def visited(self) -> list[TargetResult]:
        return [t for t in self.targets if t.errors_m]

    def summary(self) -> dict:
        v = self.visited
        out: dict = {
            "targets": len(self.targets),
            "visited": len(v),
            "smrs": self.smrs,
            "generator": self.generator,
            "start": "model-based" if self.model_based else "nominal IK",
            "statuses": {
                s: sum(t.status == s for t in self.targets) for s in sorted({t.status for t in self.targets})
            },
            "iterations_mean": float(np.mean([t.iterations for t in v])) if v else np.nan,
            "position_mm": {
                "uncompensated": scalar_error_stats(np.array([t.uncompensated_error_m for t in v]) * 1e3),
                "start": scalar_error_stats(np.array([t.errors_m[0] for t in v]) * 1e3),
                "best_of_iterations": scalar_error_stats(np.array([t.error_m for t in v]) * 1e3),
                "final": scalar_error_stats(np.array([_fresh(t)[0] for t in v]) * 1e3),
            },
        }
        if self.smrs == 3:
            out["orientation_deg"] = {
                "uncompensated": scalar_error_stats(np.rad2deg([t.uncompensated_rotation_rad for t in v])),
                "start": scalar_error_stats(np.rad2deg([t.rotation_errors_rad[0] for t in v])),
                "best_of_iterations": scalar_error_stats(np.rad2deg([t.rotation_error_rad for t in v])),
                "final": scalar_error_stats(np.rad2deg([_fresh(t)[1] for t in v])),
            }
        return out

    def stage_table(self) -> str:
        """The before / after table alone (uncompensated -> start -> measured loop)."""
        return stage_table(self.summary())

    def table(self) -> str:
        """Per-target lines and the before / after table, for the console."""
        lines = [f"pseudo-target loop ({self.smrs} SMR{'s' if self.smrs > 1 else ''}, generator {self.generator}, "
                 f"{'model-based' if self.model_based else 'nominal IK'} start):"]  # fmt: skip
        for t in self.targets:
            if not t.errors_m:
                lines.append(f"  {t.target_id}: {t.status} (not measured)")
                continue
            errs = " -> ".join(f"{e * 1e3:.4f}" for e in t.errors_m)
            rot = f"; {np.rad2deg(t.rotation_error_rad):.4f} deg" if self.smrs == 3 else ""
            lines.append(f"  {t.target_id}: {errs} mm ({t.iterations} it, {t.status}){rot}")
        s = self.summary()
        lines.append("")
        lines.append(stage_table(s))
        return "\n".join(lines)


def stage_table(summary: dict) -> str:
    """The before / after table: uncompensated (when measured) -> start -> the loop's best reading of each
    target (the minimum over its iterations) -> measured loop (the kept joints measured once more: the
    figure to quote)."""
    start = "model-based" if summary["start"] == "model-based" else "nominal IK"
    rows = [("uncompensated", "uncompensated"), (start, "start"), ("loop, best read", "best_of_iterations"),
            ("measured loop", "final")]  # fmt: skip
    head = f"  {'stage':<16}{'mean':>9}{'RMS':>9}{'max':>9}{'p95':>9}  (mm)"
    if "orientation_deg" in summary:
        head += f"{'mean':>10}{'max':>9}  (deg)"
    lines = [head]
    for label, key in rows:
        p = summary["position_mm"][key]
        if not p["n"]:
            continue
        line = f"  {label:<16}{p['mean']:9.4f}{p['rms']:9.4f}{p['max']:9.4f}{p['p95']:9.4f}      "
        if "orientation_deg" in summary:
            o = summary["orientation_deg"][key]
            line += f"{o['mean']:10.4f}{o['max']:9.4f}" if o["n"] else ""
        lines.append(line.rstrip())
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ targets
def load_model(model: CalibratedModel | str | Path | None) -> CalibratedModel | None:
    if model is None or isinstance(model, CalibratedModel):
        return model
    if not Path(model).is_file():
        raise ValueError(
            f"--model {model}: no such file; give a model written by `hil calibrate` or `hil diagnose`"
        )
    return CalibratedModel.load(model)


def nominal_model(config: CellConfig, T_tracker_base: np.ndarray, p_nest1_m: np.ndarray) -> CalibratedModel:
    """The controller's view without calibration: nominal geometry, the registration, the tool drawing / fit."""
    nominal = config.nominal
    return CalibratedModel(
        nominal.name, nominal, nominal, np.asarray(T_tracker_base, float), {1: np.asarray(p_nest1_m, float)}
    )


def random_targets(config: CellConfig, model: CalibratedModel, count: int, seed: int = 0, full_pose: bool = False,
                   tilt_deg: float = 15.0) -> np.ndarray:  # fmt: skip
    """`count` held-out targets in the sampled volume (tracker frame): where the model says the robot really
    puts SMR 1 (and the flange) for random reachable, non-singular poses facing the tracker inside the
    envelope. Points (count, 3), or poses (count, 4, 4) T_tracker_tool for full_pose."""
    if count < 1:
        raise ValueError("--targets must be at least 1")
    rng = np.random.default_rng(seed)
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    p_nest = config.nests_flange_m[0]
    found: list[np.ndarray] = []
    for _ in range(20):
        T = facing_poses(random_points(box, 3 * count, rng), config.p_base_tracker_m, rng, tilt_deg=tilt_deg)
        joints = plan_clear_joints(
            config.nominal, config.envelope, T, p_nest, config.nests_flange_m, config.q_home_rad
        )
        found.append(joints.q[joints.usable])
        if sum(len(f) for f in found) >= count:
            break
    q_all = np.vstack(found)[:count]
    if len(q_all) < count:
        raise ValueError(
            f"found only {len(q_all)} usable target poses in the sampled volume; widen [envelope] or ask for fewer"
        )
    T_actual = PosePredictor(model, smr=1)(q_all)
    return T_actual if full_pose else T_actual[:, :3, 3]


def _circle_count(text: str) -> int:
    """'circle' -> 2000 (the paper's trajectory), 'circle:N' -> N (at least 3)."""
    _, _, count = text.strip().partition(":")
    if count and not count.isdigit() or (count and int(count) < 3):
        raise ValueError(f"--targets {text}: give circle or circle:N with N >= 3 points")
    return int(count) if count else 2000


def circle_targets(config: CellConfig, model: CalibratedModel, count: int, full_pose: bool = False,
                   radius_m: float = CIRCLE_RADIUS_M) -> np.ndarray:  # fmt: skip
    """`count` targets on a circle (tracker frame) around the sampled volume's centre, in the plane facing the
    tracker, the tool's orientation held at the centre's facing pose (the PT paper's circle trajectory).
    Points (count, 3) of SMR 1, or poses (count, 4, 4) T_tracker_tool: SMR 1 and the flange orientation."""
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    T_face = facing_poses(
        box.centre_m[None], config.p_base_tracker_m, np.random.default_rng(0), tilt_deg=0.0
    )[0]
    u, v = T_face[:3, 0], T_face[:3, 1]  # the facing tool's x and y: the plane across the line of sight
    a = 2 * np.pi * np.arange(count) / count
    p_base = box.centre_m + radius_m * (np.outer(np.cos(a), u) + np.outer(np.sin(a), v))
    T_base = np.tile(T_face, (count, 1, 1))
    T_base[:, :3, 3] = p_base
    T_tracker = model.T_tracker_base @ T_base
    return T_tracker if full_pose else T_tracker[:, :3, 3]


def read_targets_csv(path: str | Path) -> np.ndarray:
    """Targets from a CSV: x_mm, y_mm, z_mm (SMR 1 in the tracker frame), optionally rx_deg, ry_deg, rz_deg
    (flange orientation in the tracker frame, the dataset's convention: hil.data.dataset.orientations) for full-pose
    targets."""
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read targets {path}: {exc}") from exc
    pos = ["x_mm", "y_mm", "z_mm"]
    rot = [c for c in ("rx_deg", "ry_deg", "rz_deg") if c in df.columns]
    if any(c not in df.columns for c in pos) or len(rot) not in (0, 3) or len(df) == 0:
        raise ValueError(
            f"{path}: targets need columns x_mm, y_mm, z_mm (optionally all of rx_deg, ry_deg, rz_deg) and a row"
        )
    values = df[pos + rot].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    if not np.all(np.isfinite(values)):
        raise ValueError(
            f"{path}: row {int(np.flatnonzero(~np.all(np.isfinite(values), axis=1))[0]) + 1} has a missing or non-numeric value"
        )
    if not rot:
        return values / 1e3
    T = np.tile(np.eye(4), (len(values), 1, 1))
    T[:, :3, :3] = orientations(pd.DataFrame(values[:, 3:], columns=list(ORIENTATION_COLUMNS)))
    T[:, :3, 3] = values[:, :3] / 1e3
    return T


def resolve_targets(
    targets: int | str | np.ndarray, config: CellConfig, model: CalibratedModel, seed: int, smrs: int
) -> np.ndarray:
    """Targets as poses (N, 4, 4) for three SMRs or points (N, 3) for one, from a count, a CSV or an array."""
    if smrs not in SMR_MODES:
        raise ValueError(f"--smrs {smrs}: use 1 (position) or 3 (pose: SMRs in nests 1, 2, 3)")
    if smrs == 3 and len(config.nests_flange_m) < 3:
        raise ValueError("--smrs 3 needs a tool with three nests ([tool] nests_flange_mm)")
    if isinstance(targets, str) and targets.strip().startswith("circle"):
        return circle_targets(config, model, _circle_count(targets), full_pose=smrs == 3)
    if isinstance(targets, str):
        targets = int(targets) if targets.strip().isdigit() else read_targets_csv(targets)
    if isinstance(targets, (int, np.integer)):
        return random_targets(config, model, int(targets), seed, full_pose=smrs == 3)
    t = np.asarray(targets, float)
    if t.ndim == 2 and t.shape[1] == 3:
        if smrs == 3:
            raise ValueError(
                "three SMRs correct the orientation too: give targets with rx_deg, ry_deg, rz_deg"
            )
        return t
    if t.ndim == 3 and t.shape[1:] == (4, 4):
        return t if smrs == 3 else t[:, :3, 3]
    raise ValueError(f"targets must be points (N, 3) or poses (N, 4, 4) in metres, got shape {t.shape}")


# ------------------------------------------------------------------------------------------ start joints
@dataclass
class Start:
    q: np.ndarray  # (N, 6) joints of the first measurement (NaN where not usable)
    q_uncompensated: np.ndarray  # (N, 6) plain nominal IK
    status: np.ndarray  # (N,) "ok" or why the target is not visited


def start_joints(config: CellConfig, ik_model: CalibratedModel, model: CalibratedModel | None, T_d: np.ndarray,
                 generator: str, threshold_m: float, ensemble: list[str] | None = None,
                 temperature_c: float | None = None) -> Start:  # fmt: skip
    """Model-based compensated joints (nominal IK without a model), checked for reach, singularity, envelope;
    the model's temperature-driven effects at `temperature_c` (the cell's now; None: at their reference)."""
    full_pose = T_d.ndim == 3
    gen = generator if full_pose else None
    home = config.q_home_rad
    if full_pose:
        plain = compensate(
            ik_model,
            T_d,
            CompensationOptions(generator=gen, generators=ensemble, threshold_m=threshold_m, max_iter=0),
            q_near=home,
        )
        q_plain, status = plain.q, plain.status.astype(object)
        seed = None
    else:  # points: the SMR facing the tracker (no tilt), nominal IK of that pose is the uncompensated start
        T_bt = np.linalg.inv(ik_model.T_tracker_base)
        p_base = T_d @ T_bt[:3, :3].T + T_bt[:3, 3]
        T_face = facing_poses(p_base, config.p_base_tracker_m, np.random.default_rng(0), tilt_deg=0.0)
        joints = plan_clear_joints(
            config.nominal, config.envelope, T_face, ik_model.tools[1], config.nests_flange_m, home
        )
        status = np.where(joints.reason == "ok", "ok", joints.reason).astype(object)
        q_plain = np.where(joints.usable[:, None], joints.q, np.nan)
        seed = np.where(joints.usable[:, None], joints.q, home)
    if model is not None:
        res = compensate(
            model,
            T_d,
            CompensationOptions(
                generator=gen, generators=ensemble, threshold_m=min(threshold_m, 1e-5) / 10, max_iter=10
            ),
            q_seed=seed,
            q_near=home,
            conditions=TargetConditions(
                temperature_c=None if temperature_c is None else np.full(len(T_d), temperature_c)
            ),
        )
        q = res.q
        status = np.where(status == "ok", res.status, status).astype(object)
    else:
        q = q_plain.copy()
    status[np.isin(status, USABLE_START)] = "ok"
    ok = (status == "ok") & np.all(np.isfinite(q), axis=1)
    status[~ok & (status == "ok")] = "no_ik_solution"
    if ok.any():
        sigma = position_sigma_min_m(config.nominal, q[ok], config.nests_flange_m[0])
        status[np.flatnonzero(ok)[sigma < SINGULAR_SIGMA_M]] = "singular"
        ok = status == "ok"
    if ok.any():
        status[np.flatnonzero(ok)[config.envelope.outside(config.nominal, q[ok], config.nests_flange_m)]] = (
            "envelope"
        )
    q = np.where((status == "ok")[:, None], q, np.nan)
    return Start(q, q_plain, status.astype(str))


def measurement_sigma_m(p_tracker_m: np.ndarray, spread_m: np.ndarray, shots: int) -> float:
    """Per-axis 1-sigma noise of one measured (mean) point: the larger of the tracker's noise model at its
    distance and the RMS spread of its kept shots, each divided by sqrt(shots)."""
    distance = float(np.linalg.norm(p_tracker_m))
    model = float(tracker_sigma_m(distance))
    spread = np.asarray(spread_m, float)
    seen = float(np.sqrt(np.mean(spread**2))) if np.all(np.isfinite(spread)) else 0.0
    return max(model, seen) / np.sqrt(max(int(shots), 1))


def target_ids(count: int) -> list[str]:
    return [f"t{k + 1:03d}" for k in range(count)]


def paper_options(pt_paper: bool, model: object, smrs: int, generator: str, max_iter: int, patience: int,
                  threshold_m: float) -> tuple[int, str, int, int, float]:  # fmt: skip
    """(smrs, generator, max_iter, patience, threshold_m): the PT paper's experiment's with --pt-paper, else as
    given. The paper's experiment starts from the nominal model: --pt-paper with --model is refused."""
    if not pt_paper:
        return smrs, generator, max_iter, patience, threshold_m
    if model is not None:
        raise ParameterError("--pt-paper starts from the nominal model (no calibration): drop --model")
    return PT_PAPER


def ensemble_subset(text: str) -> list[str]:
    """The --ensemble list ('yin,zyz,quaternion') as checked generator names."""
    try:
        return ensemble_names([g.strip() for g in str(text).split(",") if g.strip()])
    except ValueError as exc:
        raise ParameterError(f"--ensemble {text}: {exc}") from exc


def _campaign_model(config: CellConfig, campaign: str | Path | None) -> CalibratedModel:
    """The nominal model on the campaign's registration (and tool fit), for planning a loop without --model."""
    try:
        if campaign is None or not (is_campaign_url(campaign) or Path(campaign).exists()):
            raise CampaignError("no campaign")
        with open_campaign(campaign, create=False, password_file=config.store_password_file) as store:
            reg = store.step_result(*publisher(Role.REGISTRATION))
            fit = store.step_result(*publisher(Role.TOOL)) or {}
    except CampaignError:
        reg = None
    if reg is None:
        raise ValueError(
            "a loop without --model starts from the nominal model on the campaign's registration: "
            "give --campaign with a registration (hil run registration), or --model"
        )
    nest = fit.get("nests_flange_mm", {}).get("1")
    p_nest = np.asarray(nest, float) / 1e3 if nest is not None else config.nests_flange_m[0]
    return nominal_model(config, np.asarray(reg["T_tracker_base"], float), p_nest)


@dataclass(frozen=True)
class PseudoTargetOptions:
    """The declared parameters, SI. `model`: a model.json path or a CalibratedModel; `targets`: a count, a
    circle:N, a CSV path, or an array of targets (tracker frame, m)."""

    model: CalibratedModel | str | None
    targets: int | str | np.ndarray
    generator: str
    ensemble: str
    approach_rad: float
    pt_paper: bool
    threshold_m: float
    max_iter: int
    patience: int
    smrs: int
    seed: int
    shots: int | None
    measure_uncompensated: bool


@dataclass(frozen=True)
class LoopSettings:
    """How the loop runs each target, once --pt-paper has had its say (see paper_options)."""

    generator: str
    threshold_m: float
    max_iter: int
    smrs: int
    shots: int | None
    patience: int
    ensemble: list[str] | None = None
    approach_rad: float = 0.0


def plan(config: CellConfig, options: PseudoTargetOptions, campaign: str | Path | None = None) -> Plan:
    """The first pose of every usable target (model-based start), for --dry-run and the envelope check; the
    plan's bounds say how often each target may be measured again."""
    model, targets, seed, ensemble = options.model, options.targets, options.seed, options.ensemble
    smrs, generator, max_iter, patience, threshold_m = paper_options(
        options.pt_paper, model, options.smrs, options.generator, options.max_iter, options.patience,
        options.threshold_m,
    )  # fmt: skip
    ensemble_subset(ensemble)
    the_model = load_model(model)
    base = the_model if the_model is not None else _campaign_model(config, campaign)
    T_d = resolve_targets(targets, config, base, seed, smrs)
    ik_model = nominal_model(config, base.T_tracker_base, base.tools.get(1, config.nests_flange_m[0]))
    start = start_joints(config, ik_model, the_model, T_d, generator, threshold_m, ensemble_subset(ensemble))
    ids = target_ids(len(T_d))
    poses = [
        PlannedPose(f"{i}/i0", NAME, STEP, q, "nest1")
        for i, q, s in zip(ids, start.q, start.status, strict=True)
        if s == "ok"
    ]
    if not poses:
        raise ValueError("no target is usable (see the statuses): give targets inside the calibrated volume")
    dropped = {str(s): int(np.sum(start.status == s)) for s in np.unique(start.status) if s != "ok"}
    per_point = smrs * (config.settle_s + config.shots_per_point * config.meas_time_s + 0.5) * (max_iter + 1)
    bounds = (
        f"each target's first pose is shown; up to {max_iter} corrections follow, each a pose the "
        f"measurement decides ({smrs} SMR reading(s) a pose), every one checked against the envelope first"
    )
    return Plan(
        NAME, poses, config, operator_steps=smrs, dropped=dropped, per_point_s=per_point, bounds=bounds
    )


# ------------------------------------------------------------------------------------------ the loop
def close_the_loop(session: Session, options: PseudoTargetOptions) -> LoopResult:
    """Run the measured pseudo-target loop on every target (see the module docstring); resumable.

    `targets`: a count of random held-out targets in the sampled volume, a CSV path, or an array (tracker
    frame, m). `max_iter`: corrections after the first measurement. `patience`: stop a target after this
    many corrections in a row without a gain beyond the noise margin (0: off). `measure_uncompensated` also
    measures each target's plain nominal IK once (`t007/u`), the "uncompensated" row of the before / after table.
    `pt_paper` runs the PT paper's experiment (PT_PAPER); `ensemble` names the generators of --generator ensemble;
    `approach_rad` > 0 makes every measured pose approached from the same side on every joint (backlash).
    """
    model, targets, seed = options.model, options.targets, options.seed
    smrs, generator, max_iter, patience, threshold_m = paper_options(
        options.pt_paper, model, options.smrs, options.generator, options.max_iter, options.patience,
        options.threshold_m,
    )  # fmt: skip
    ensemble = options.ensemble
    subset = ensemble_subset(ensemble) if generator == ENSEMBLE else None
    the_model = load_model(model)
    reg = session.require_registration()
    T_tb = the_model.T_tracker_base if the_model is not None else reg.T_tracker_base
    ik_model = (
        the_model if the_model is not None else nominal_model(session.config, T_tb, session.nest_flange_m(1))
    )
    T_d = resolve_targets(targets, session.config, ik_model, seed, smrs)
    _pin_targets(
        session, T_d, generator, round(threshold_m * 1e3, 12), max_iter, smrs, the_model is not None, patience,
        subset,
    )  # fmt: skip
    nominal_ik = nominal_model(session.config, T_tb, ik_model.tools[1])
    temperature_c = cell_temperature(session, the_model)
    start = start_joints(
        session.config, nominal_ik, the_model, T_d, generator, threshold_m, subset, temperature_c
    )
    settings = LoopSettings(
        generator, threshold_m, max_iter, smrs, options.shots, patience, subset, options.approach_rad
    )
    loop = _Loop(session, ik_model, T_d, settings)
    ids = target_ids(len(T_d))
    results = [TargetResult(i, str(s)) for i, s in zip(ids, start.status, strict=True)]
    todo = [k for k, r in enumerate(results) if r.status == "ok"]
    loop.ask_operator()
    uncompensated = start.q_uncompensated if options.measure_uncompensated else None
    session.engine.run(loop.targets(todo, start.q, uncompensated, results))
    result = LoopResult(results, smrs, generator, the_model is not None)
    session.finish_step(
        NAME, "summary", {"summary": result.summary(), "targets": [r.to_dict() for r in results]}
    )
    return result


def cell_temperature(session: Session, model: CalibratedModel | None) -> float | None:
    """The temperature the model's start is compensated for: the campaign's latest reading (the arm's probe,
    else the robot's joint sensors, else the tracker's air: `CampaignStore.last_temperature_c`), recorded as an event, with a warning event when it lies outside what the model's
    thermal effects were fitted on; None without a model or a reading."""
    if model is None:
        return None
    temperature_c = session.store.last_temperature_c()
    if temperature_c is None:
        return None
    session.event("loop_temperature", f"the start is compensated for {temperature_c:.2f} degC")
    why = outside_fitted_temperatures(model, np.array([temperature_c]))
    if why:
        logging.getLogger(__name__).warning("the cell at %.1f degC: %s", temperature_c, why)
        session.event("temperature_outside_model", f"the cell at {temperature_c:.1f} degC: {why}")
    return temperature_c


def _pin_targets(
    session: Session,
    T_d: np.ndarray,
    generator: str,
    threshold_mm: float,
    max_iter: int,
    smrs: int,
    model_based: bool,
    patience: int,
    ensemble: list[str] | None = None,
) -> None:
    """Record the targets and options on the first run; a resume with other ones would mix two jobs.
    (A loop pinned before `patience` or `ensemble` existed resumes with any of them.)"""
    pinned = session.step_result(NAME, "targets")
    options = {
        "generator": generator,
        "threshold_mm": threshold_mm,
        "max_iter": max_iter,
        "smrs": smrs,
        "model_based": model_based,
        "patience": patience,
        "ensemble": ensemble,
    }
    if pinned is None:
        session.finish_step(NAME, "targets", {"targets_m": np.round(T_d, 12).tolist(), **options})
        return
    same = np.shape(pinned["targets_m"]) == T_d.shape and np.allclose(pinned["targets_m"], T_d, atol=1e-9)
    late = ("patience", "ensemble")  # options added after campaigns were pinned
    if not same or any(pinned.get(k, v if k in late else None) != v for k, v in options.items()):
        raise CampaignStopped(
            "this campaign already holds a pseudo-target loop with other targets or options",
            "re-run with the same options and model to resume it, or use a new --campaign file",
        )


def remeasure_kept(loop: _Loop, k: int, tid: str, out: TargetResult) -> Measuring[None]:
    """Measure target `k`'s kept joints once more (`t007/f`) and record the error as `out.fresh`: the loop keeps
    the iteration whose reading was smallest, so that reading is biased low by the selection; a fresh one is
    not."""
    if out.q_rad is None:
        return
    T_a = (yield from loop.measure(f"{tid}/f", out.q_rad))[None]
    _, dp, dr = pose_cost(T_a, loop.T_d4[k : k + 1], loop.full_pose, LENGTH_SCALE_M)
    out.fresh = (float(dp[0]), float(dr[0]))


class _Loop:
    """Measure (or recall what is recorded), update the pseudo target, solve its IK: one target at a time."""

    def __init__(
        self, session: Session, ik_model: CalibratedModel, T_d: np.ndarray, settings: LoopSettings
    ) -> None:
        s = settings
        self.session, self.generator, self.threshold_m = session, s.generator, s.threshold_m
        self.approach_rad = s.approach_rad
        self.generators = (s.ensemble or list(GENERATORS)) if s.generator == ENSEMBLE else [s.generator]
        self.max_iter, self.smrs, self.shots, self.patience = s.max_iter, s.smrs, s.shots, s.patience
        smrs = s.smrs
        self.full_pose = smrs == 3
        self.ik = PseudoTargetIK(ik_model, "kinematic", smr=1, full_pose=self.full_pose)
        if self.full_pose:
            self.T_d4 = np.asarray(T_d, float)
        else:
            self.T_d4 = np.tile(np.eye(4), (len(T_d), 1, 1))
            self.T_d4[:, :3, 3] = T_d
        self.nests = np.array([session.nest_flange_m(k) for k in range(1, smrs + 1)])
        self.sigma_m = 0.0  # per-axis noise of the last measure(): the largest of its points'

    def ask_operator(self) -> None:
        for k in range(1, self.smrs + 1):
            self.session.ask(
                OperatorStep(f"Put SMR {k} in tool nest {k}.", "place_smr", smr=k, location=f"nest{k}")
            )

    def targets(
        self,
        todo: list[int],
        q_start: np.ndarray,
        q_uncompensated: np.ndarray | None,
        results: list[TargetResult],
    ) -> Measuring[None]:
        """The loop over the targets `todo` (indices into `results`), as requests to the engine: each target
        from its start joints, after its plain nominal IK (`q_uncompensated`) when that is measured too;
        progress counts the targets."""
        for done, k in enumerate(todo):
            yield Advance("pseudo-target loop", done, len(todo))
            out = results[k]
            if q_uncompensated is not None:
                T_u = yield from self.measure(f"{out.target_id}/u", q_uncompensated[k])
                _, out.uncompensated_error_m, out.uncompensated_rotation_rad = (
                    x[0] for x in pose_cost(T_u[None], self.T_d4[k : k + 1], self.full_pose, LENGTH_SCALE_M)
                )
            yield from self.run_target(k, out.target_id, q_start[k], out)
            yield from remeasure_kept(self, k, out.target_id, out)
        yield Advance("pseudo-target loop", len(todo), len(todo))

    def _point(self, point_id: str, q: np.ndarray, nest: int, approach: bool) -> Measuring[np.ndarray]:
        """One SMR's point at joints q; `approach`: reach q through q - approach on every joint, so each joint
        arrives moving the same way every time (a backlash-free approach; skipped where the envelope refuses)."""
        q = np.asarray(q, float)
        pose = PlannedPose(
            point_id, NAME, STEP, q, f"nest{nest}", smr=nest, p_flange_m=self.nests[nest - 1],
            approach_q_rad=q - self.approach_rad if approach and self.approach_rad > 0 else None,
        )  # fmt: skip
        record = yield MeasurePose(
            pose, shots=self.shots, extra={"target": point_id.split("/")[0]}, approach_optional=True
        )
        assert isinstance(record, MeasurementRecord)
        self.sigma_m = max(
            self.sigma_m, measurement_sigma_m(record.p_tracker_m, record.spread_m, record.shots)
        )
        return np.asarray(record.p_tracker_m, float)

    def measure(self, base_id: str, q: np.ndarray) -> Measuring[np.ndarray]:
        """Measured T_tracker_tool (4, 4): SMR 1's point, and with three SMRs the flange orientation from
        the nest layout fitted to the three measured nests (Kabsch). Sets `sigma_m`, its per-axis noise."""
        self.sigma_m = 0.0
        T = np.eye(4)
        if self.smrs == 1:
            T[:3, 3] = yield from self._point(base_id, q, 1, approach=True)
            return T
        measured = []
        for k in range(1, self.smrs + 1):  # the other nests: read where it stands
            measured.append((yield from self._point(f"{base_id}/n{k}", q, k, approach=k == 1)))
        p = np.array(measured)
        T_tracker_flange, _ = fit_rigid(self.nests, p)
        T[:3, :3] = T_tracker_flange[:3, :3]
        T[:3, 3] = p[0]
        return T

    def run_target(self, k: int, tid: str, q0: np.ndarray, out: TargetResult) -> Measuring[None]:
        q = np.asarray(q0, float)
        T_p = self.ik.from_flange(forward_kinematics(self.ik.kin, q[None]))  # the pseudo target FK(q)
        T_d = self.T_d4[k : k + 1]
        best, stale = np.inf, 0  # best error measure so far; corrections in a row without a real gain
        T_a = (yield from self.measure(f"{tid}/i0", q))[None]
        sigma = self.sigma_m
        for i in range(self.max_iter + 1):
            cost, dp, dr = pose_cost(T_a, T_d, self.full_pose, LENGTH_SCALE_M)
            out.errors_m.append(float(dp[0]))
            out.rotation_errors_rad.append(float(dr[0]))
            out.noise_m.append(sigma)
            gain = i == 0 or cost[0] < best - GAIN_SIGMAS * sigma
            stale = 0 if gain else stale + 1
            if gain:  # kept only on a real gain: a smaller reading within the noise is selection, not a gain
                best, out.best_iteration, out.q_rad = float(cost[0]), i, q.copy()
            if best < self.threshold_m:
                out.status = "ok"
                return
            if self.patience and stale >= self.patience:
                out.status = "no_improvement"
                return
            if i == self.max_iter:
                out.status = "max_iter"
                return
            proposals, reason = self._propose(T_d, T_a, T_p, q)
            if not proposals:
                out.status = reason
                return
            T_a, q, T_p, sigma = yield from self._measure_best(f"{tid}/i{i + 1}", T_d, proposals)

    def _propose(
        self, T_d: np.ndarray, T_a: np.ndarray, T_p: np.ndarray, q: np.ndarray
    ) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], str]:
        """Each generator's next pseudo target and its joints (name, T_p, q), and why the first failed one did."""
        proposals, why = [], ""
        names = self.generators if self.full_pose else self.generators[:1]  # points: one position update
        cfg = self.session.config
        for name in names:
            if self.full_pose:
                T_new = update_pseudo_target(name, T_d, T_a, T_p)
            else:
                T_new = T_p.copy()
                T_new[:, :3, 3] = update_pseudo_position(T_d[:, :3, 3], T_a[:, :3, 3], T_p[:, :3, 3])
            q_new, reason = self.ik.solve(T_new, q[None], project=name == "add")
            if reason[0] != "ok":
                why = why or str(reason[0])
            elif cfg.envelope.outside(cfg.nominal, q_new, cfg.nests_flange_m)[0]:
                why = why or "envelope"
            else:
                proposals.append((name, T_new, q_new[0]))
        return proposals, why

    def _measure_best(
        self, base_id: str, T_d: np.ndarray, proposals: list[tuple[str, np.ndarray, np.ndarray]]
    ) -> Measuring[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        """Measure each proposal (one: `t007/i2`; an ensemble: `t007/i2/zyz`, ...), keep the best: (T_a, q, T_p, noise)."""
        found = []
        for name, T_p, q in proposals:
            point_id = base_id if self.generator != ENSEMBLE else f"{base_id}/{name}"
            T_a = (yield from self.measure(point_id, q))[None]
            cost = pose_cost(T_a, T_d, self.full_pose, LENGTH_SCALE_M)[0][0]
            found.append((float(cost), T_a, q, T_p, self.sigma_m))
        _, T_a, q, T_p, sigma = min(found, key=lambda f: f[0])
        return T_a, q, T_p, sigma


def summary(result: LoopResult) -> str:
    return result.table()


PROCEDURE = Procedure(
    name=NAME,
    purpose="put the SMR on targets, measured: model-based start, then pseudo-target corrections",
    instruction=__doc__ or "",
    parameters=(
        Parameter(
            "model",
            "calibrated model (model.json from hil calibrate / hil diagnose); absent: the nominal model (no calibration)",
            None,
            str,
        ),
        Parameter(
            "targets",
            "N random held-out targets in the sampled volume, circle:N (N points on a circle, the PT paper's trajectory), or a CSV: x_mm, y_mm, z_mm (tracker frame) [, rx_deg, ry_deg, rz_deg]",
            "20",
            str,
        ),
        Parameter("generator", "pseudo-target generator", "yin", str, choices=(*GENERATORS, ENSEMBLE)),
        Parameter(
            "ensemble",
            "generators of --generator ensemble, comma-separated (each proposal is measured, the best kept)",
            ",".join(GENERATORS),
            str,
        ),
        Parameter(
            "approach",
            "reach every measured pose from this far below on every joint, the same side each time (backlash); 0 = straight",
            0.0,
            float,
            unit="deg",
            minimum=0.0,
            maximum=5.0,
        ),
        Parameter(
            "pt_paper",
            "the PT paper's measured experiment: nominal start (no --model), 3 SMRs, ZYZ generator, 2 corrections",
            False,
            bool,
        ),
        Parameter(
            "threshold",
            "stop below this measured error",
            0.01,
            float,
            unit="mm",
            minimum=0.0005,
            maximum=10.0,
        ),
        Parameter("max_iter", "measured corrections per target", 3, int, minimum=0, maximum=20),
        Parameter(
            "patience",
            "stop a target after this many corrections in a row that do not beat its best error by more than the measurement noise (1 sigma of the tracker's noise model or the shot spread, whichever is larger); status no_improvement, best joints kept; 0 = off",
            PATIENCE,
            int,
            minimum=0,
            maximum=20,
        ),
        Parameter(
            "smrs", "1: position (SMR in nest 1); 3: pose (SMRs in nests 1-3)", 1, int, choices=SMR_MODES
        ),
        Parameter("seed", "seed of the random targets", 0, int, minimum=0),
        SHOTS,
        Parameter(
            "measure_uncompensated",
            "also measure each target's plain nominal IK once (the uncompensated row)",
            False,
            bool,
        ),
    ),
    plan=plan,
    body=close_the_loop,
    steps=("targets", "loop", "summary"),
    summary=summary,
    options=PseudoTargetOptions,
)
