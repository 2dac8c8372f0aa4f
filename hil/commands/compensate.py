"""`hil compensate model.json TARGETS -o JOINTS.csv`: joints that put the SMR on the targets, by the model.

TARGETS is a CSV of points / poses or a campaign file (hil.commands.campaign_targets says which targets). A pose's
rx_deg, ry_deg, rz_deg mean what they mean in a dataset (hil.data.dataset): the orientation of the targeted frame (the
flange's axes at the SMR) in the tracker frame, xyz-extrinsic Euler unless --orientation-convention says otherwise.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hil.commands.arg_checks import (
    InputError,
    add_force_option,
    add_joint_convention_option,
    check_paths,
    float_in,
)
from hil.commands.campaign_targets import DEFAULT_ORDER, SOURCES, read_campaign_targets
from hil.commands.compensate_program import is_program, run_program
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.compensation.model_based import (
    ENSEMBLE,
    CompensationOptions,
    CompensationResult,
    TargetConditions,
    compensate,
    compensate_path,
    merge_results,
    outside_fitted_temperatures,
)
from hil.compensation.target_update import GENERATORS
from hil.data.campaigns import is_campaign
from hil.data.dataset import (
    DEFAULT_ORIENTATION_CONVENTION,
    ORIENTATION_COLUMNS,
    ORIENTATION_CONVENTIONS,
    POSITION_COLUMNS,
    joint_columns,
    make_dataset,
    orientations,
)
from hil.geometry.coupling import JointConvention, JointCoupling
from hil.geometry.se3 import transform_points
from hil.model.calibrated_model import CalibratedModel
from hil.model.coupled_model import model_coupling
from hil.model.effects import THERMAL_FAMILIES, material_growth, temperature_driven
from hil.model.intervals import IntervalError
from hil.model.prediction_intervals import prediction_intervals

FRAMES = ("tracker", "base")
TEMPERATURE_RANGE_C = (-20.0, 60.0)  # --temperature-c: a cell's air, not a typo in kelvin or fahrenheit


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "compensate",
        help="joints that make a calibrated model put the SMR on target points or poses (pseudo-target loop)",
        description="Model-based pseudo-target compensation. Targets: x_mm, y_mm, z_mm of the SMR in the "
        "tracker frame, optionally rx_deg, ry_deg, rz_deg for full-pose targets (the orientation of the "
        "targeted frame, i.e. the flange's axes at the SMR, in the tracker frame: Euler angles in degrees "
        "as in a dataset, xyz-extrinsic unless --orientation-convention says otherwise), and "
        "temperature_c (or --temperature-c) / t_s when the model has thermal effects. Or a campaign file "
        "(hil run / hil demo): the targets of one of its steps (--step), each with its point id and SMR "
        "nest. Writes one row per target: q1_rad..q6_rad, the predicted remaining error, the iterations "
        "used and a status; targets that cannot be compensated are kept and marked.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("model", help="model JSON written by 'hil calibrate' or 'hil diagnose -o'")
    p.add_argument(
        "targets",
        help="CSV of targets (see above), a campaign file, or a URScript program (.script: its pose targets are "
        "rewritten as compensated joints into -o)",
    )
    p.add_argument(
        "--step",
        default=None,
        metavar="|".join(SOURCES),
        help="campaign file only: which targets. loop = the pseudo-target loop's targets (poses when it "
        "ran with three SMRs); validation / grid = the SMR centres the grid_sampling step's commanded "
        "joints aimed at (nominal kinematics, the campaign's registration and tool fit), with the nest, "
        "time and temperature of each point. Default: the first the campaign holds of "
        + ", ".join(DEFAULT_ORDER),
    )
    p.add_argument("-o", "--output", required=True, help="CSV to write, one row per target")
    p.add_argument(
        "--generator",
        default=None,
        choices=(*GENERATORS, ENSEMBLE),
        help="pseudo-target generator for full-pose targets (default yin); point targets leave the "
        "orientation free and use the position update every generator shares",
    )
    p.add_argument("--threshold-mm", type=float, default=0.01, help="stop below this predicted error (mm)")
    p.add_argument("--max-iter", type=int, default=10, help="at most this many pseudo-target updates")
    p.add_argument(
        "--length-scale-mm",
        type=float,
        default=100.0,
        help="full-pose error measure: 1 rad of orientation error counts as this many mm (default 100)",
    )
    p.add_argument(
        "--smr",
        type=int,
        default=None,
        help="SMR nest to put on the targets (default: the campaign's nest of each target, for a CSV the "
        "model's lowest id)",
    )
    p.add_argument(
        "--ik-model",
        default="kinematic",
        choices=("kinematic", "nominal"),
        help="geometry the pseudo targets are solved with (default: the calibrated one)",
    )
    p.add_argument(
        "--path",
        action="store_true",
        help="targets are an ordered path of one SMR nest: keep one IK branch, flag branch jumps (UR arms); "
        "targets in several nests are refused (give --smr, or one file per nest)",
    )
    p.add_argument(
        "--orientation-convention",
        default=DEFAULT_ORIENTATION_CONVENTION,
        choices=tuple(ORIENTATION_CONVENTIONS),
        help="convention of the targets' rx_deg, ry_deg, rz_deg (tracker frame), read and written: "
        "xyz-extrinsic = Rz(rz) Ry(ry) Rx(rx) (default), xyz-intrinsic = Rx(rx) Ry(ry) Rz(rz)",
    )
    lo, hi = TEMPERATURE_RANGE_C
    p.add_argument(
        "--temperature-c",
        type=float_in(lo, hi),
        default=None,
        metavar="C",
        help=f"cell temperature to compensate for, degC in [{lo:g}, {hi:g}]: used for every target without "
        "its own temperature_c (loop targets have none) when the model has a temperature-driven thermal "
        "effect (default: none; such targets are refused)",
    )
    p.add_argument(
        "--interval",
        type=float,
        default=0.95,
        metavar="P",
        help="probability of each target's interval_mm: the radius about the model's predicted point at the "
        "compensated joints that holds the measured point with probability P (a model without a prediction "
        "spread, e.g. of format 1, gives none and says so)",
    )
    _add_frame_option(p)
    add_joint_convention_option(p)
    add_force_option(p)
    p.set_defaults(func=run)


def _add_frame_option(p: argparse.ArgumentParser) -> None:
    """--frame: the frame a CSV's targets are given in."""
    p.add_argument(
        "--frame",
        default=None,
        choices=FRAMES,
        help="frame of a CSV's targets: tracker (the SMR in the tracker frame, the default) or base (the robot's "
        "base frame as the model places it, T_tracker_base in model.json: poses from offline programming or "
        "another controller's program). A URScript program's poses are always in the base frame",
    )


def target_intervals(
    model: CalibratedModel, q: np.ndarray, smr: np.ndarray, drivers: dict, probability: float
) -> np.ndarray:
    """interval_mm of each target at its compensated joints (NaN where the IK found none)."""
    radius = np.full(len(q), np.nan)
    ok = np.all(np.isfinite(q), axis=1)
    if not ok.any():
        return radius
    df = make_dataset(q[ok], np.zeros((int(ok.sum()), 3)), smr=smr[ok])
    for name, values in drivers.items():
        df[name] = values[ok]
    iv = prediction_intervals(model, df, probability)
    for note in iv.notes:
        print(f"note: {note}", file=sys.stderr)
    radius[ok] = iv.radius_mm
    return radius


def compensate_per_smr(
    model: CalibratedModel,
    targets: np.ndarray,
    smr: np.ndarray,
    drivers: dict,
    path: bool,
    options: CompensationOptions,
    q_seed: np.ndarray | None = None,
) -> CompensationResult:
    """`compensate` (or `compensate_path`) once per SMR nest of the targets, merged back into target order;
    the per-target arrays (`drivers`, `q_seed`) follow their rows."""
    results: list[tuple[np.ndarray, CompensationResult]] = []
    for nest in np.unique(smr):
        rows = np.flatnonzero(smr == nest)
        d = {k: v[rows] for k, v in drivers.items()}
        conditions = TargetConditions(smr=int(nest), **d)
        if path:
            res = compensate_path(model, targets[rows], options=options, conditions=conditions)
        else:
            seed = None if q_seed is None else q_seed[rows]
            res = compensate(model, targets[rows], options, q_seed=seed, conditions=conditions)
        results.append((rows, res))
    return results[0][1] if len(results) == 1 else merge_results(results, len(smr))


def thermal_drivers(
    model: CalibratedModel, df: pd.DataFrame, temperature_c: float | None, campaign: tuple[str, str] | None
) -> dict[str, np.ndarray]:
    """t_s / temperature_c per target for the model's thermal effects, `temperature_c` (--temperature-c) filling
    the targets without one. CliError when a temperature-driven effect lacks temperatures (names the option),
    or when a time-driven one meets campaign targets (`campaign` = (file, step)): their t_s counts from that
    campaign's start, which the model cannot tie to the start of the data it was calibrated on."""
    n = len(df)
    drivers: dict[str, np.ndarray] = {}
    if "t_s" in df.columns:
        drivers["t_s"] = pd.to_numeric(df["t_s"], errors="coerce").to_numpy(float)
    if "temperature_c" in df.columns:
        temp = pd.to_numeric(df["temperature_c"], errors="coerce").to_numpy(float)
    else:
        temp = np.full(n, np.nan)
    if temperature_c is not None:
        temp = np.where(np.isfinite(temp), temp, temperature_c)
    material = next((e for e in model.effects if material_growth(e)), None)
    only_material = not any(temperature_driven(e) and not material_growth(e) for e in model.effects)
    if material is not None and only_material and not np.all(np.isfinite(temp)):
        reference = float(material.state["reference"])
        print(
            f"warning: {int(np.sum(~np.isfinite(temp)))} of {n} targets have no temperature: they are "
            f"compensated at {reference:.1f} degC, the temperature the model's thermal growth was fitted "
            "around (no growth); give --temperature-c C to compensate for the cell's temperature",
            file=sys.stderr,
        )
        temp = np.where(np.isfinite(temp), temp, reference)
    if np.isfinite(temp).any():
        drivers["temperature_c"] = temp
    for eff in model.effects:
        if eff.family not in THERMAL_FAMILIES:
            continue
        if temperature_driven(eff):
            missing = int(np.sum(~np.isfinite(temp)))
            if missing:
                if campaign is not None and campaign[1] == "loop":
                    why = "the pseudo-target loop's targets carry no temperature"
                elif campaign is not None:
                    why = f"no temperature was read at those points of {campaign[0]}"
                else:
                    why = "TARGETS has no temperature_c value there"
                lo, hi = TEMPERATURE_RANGE_C
                raise CliError(
                    f"the model's {eff.family} effect is driven by the temperature, and {missing} of {n} "
                    f"targets have none ({why})",
                    f"give --temperature-c C, the cell temperature to compensate for ({lo:g} to {hi:g} degC)",
                )
        elif campaign is not None:  # driven by time since the start of the model's training data
            raise CliError(
                f"the model's {eff.family} effect is driven by time (t_s since the start of the data it was "
                f"calibrated on), and the targets of campaign {campaign[0]} are not on that clock: a "
                "campaign's t_s counts from its own start, and the model does not record which campaign "
                "it came from",
                "calibrate on data with temperature_c (a temperature-driven effect takes --temperature-c), "
                "or without the thermal effect, or give the targets as a CSV with t_s on the model's clock",
            )
        elif not np.all(np.isfinite(drivers.get("t_s", np.full(n, np.nan)))):
            raise CliError(
                f"the model's {eff.family} effect is driven by time: every target needs t_s, seconds since "
                "the start of the data the model was calibrated on",
                "add a t_s column to TARGETS, or calibrate without the time-driven effect",
            )
    if "temperature_c" in drivers and any(temperature_driven(e) for e in model.effects):
        warn_outside_fitted_temperatures(model, drivers["temperature_c"])
    if temperature_c is not None and not any(temperature_driven(e) for e in model.effects):
        print(
            "warning: --temperature-c changes nothing: the model has no temperature-driven effect",
            file=sys.stderr,
        )
    return drivers


def warn_outside_fitted_temperatures(model: CalibratedModel, temperature_c: np.ndarray) -> None:
    """Warn when targets' temperatures lie outside the range the model's thermal effect was fitted on (recorded
    in the model's run record by calibrate and diagnose; older models have none and get no warning)."""
    why = outside_fitted_temperatures(model, temperature_c)
    if why:
        print(f"warning: {why}; measure a few of them to check", file=sys.stderr)


def read_targets(
    path: str, orientation_convention: str = DEFAULT_ORIENTATION_CONVENTION
) -> tuple[np.ndarray, pd.DataFrame]:
    """Targets (N, 3) points or (N, 4, 4) poses T_tracker_tool in metres from a CSV, rx/ry/rz_deg read as in a
    dataset (hil.data.dataset, in `orientation_convention`); ValueError says what to fix."""
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read targets '{path}': {exc}") from exc
    missing = [c for c in POSITION_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(
            f"{path}: missing column(s) {', '.join(missing)}; targets need x_mm, y_mm, z_mm "
            "(SMR in the tracker frame), optionally rx_deg, ry_deg, rz_deg"
        )
    if len(df) == 0:
        raise ValueError(f"{path}: no targets")
    have_rot = [c for c in ORIENTATION_COLUMNS if c in df.columns]
    if have_rot and len(have_rot) != 3:
        raise ValueError(f"{path}: give all of rx_deg, ry_deg, rz_deg for full-pose targets, or none")
    cols = list(POSITION_COLUMNS) + have_rot
    numeric = df[cols].apply(pd.to_numeric, errors="coerce")
    values = numeric.to_numpy(float)
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if bad.size:
        raise ValueError(f"{path}: row {bad[0] + 1} has a missing or non-numeric value in {', '.join(cols)}")
    p = values[:, :3] / 1000.0
    R = orientations(numeric, orientation_convention)
    if R is None:
        return p, df
    T = np.zeros((len(df), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T, df


def run(args: argparse.Namespace) -> int:
    _check_options(args)
    if is_program(args.targets):
        return run_program(args, thermal_drivers)
    campaign = is_campaign(args.targets)
    if args.frame == "base" and campaign:
        raise CliError(
            "--frame base is for a CSV of base-frame targets; a campaign's targets are in the tracker frame",
            "drop --frame",
        )
    if args.step is not None and not campaign:
        raise CliError(
            f"--step picks the targets of a campaign file; {args.targets} is a CSV",
            "drop --step, or give a campaign file",
        )
    try:
        model = CalibratedModel.load(args.model)
        coupling = model_coupling(model)
        if coupling is not None and args.joint_convention is None:
            raise CliError(
                f"the model's robot couples its joints ({coupling.describe()}): say which joints to write",
                "give --joint-convention controller (for the controller and pendant) or --joint-convention "
                "kinematic (the model's joints)",
            )
        chosen = _campaign_targets(args, model) if campaign else _csv_targets(args, model)
        nests = sorted(set(chosen.smr.tolist()))
        if args.path and len(nests) > 1:
            raise CliError(
                f"--path keeps one IK branch along the targets of one SMR nest; these are in nests {nests}",
                f"give --smr {nests[0]} to put one nest on every target, or one path per nest "
                "(split the targets by their smr column)",
            )
        drivers = thermal_drivers(
            model, chosen.frame, args.temperature_c, (args.targets, chosen.step) if chosen.step else None
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = compensate_per_smr(
                model, chosen.targets, chosen.smr, drivers, args.path, _options(args), _q_seed(args, chosen)
            )
    except (ValueError, OSError, KeyError) as exc:
        raise CliError.from_text(str(exc)) from exc
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    out = _output_frame(args, chosen, campaign, drivers, res)
    if coupling is not None and args.joint_convention == JointConvention.CONTROLLER:
        _to_controller_joints(out, coupling)
    try:
        out["interval_mm"] = target_intervals(model, res.q, chosen.smr, drivers, args.interval)
    except IntervalError as exc:
        print(f"warning: no intervals: {exc}", file=sys.stderr)
    out.to_csv(args.output, index=False, float_format="%.10g")
    _print_summary(args, res)
    if "interval_mm" in out.columns and np.isfinite(out["interval_mm"]).any():
        print(
            f"remaining error at the targets: the measured point within error_mm + interval_mm of the target "
            f"with probability {args.interval:g} (median interval {np.nanmedian(out['interval_mm']):.4f} mm)"
        )
    return 0


def in_tracker_frame(model: CalibratedModel, targets_base: np.ndarray) -> np.ndarray:
    """Base-frame targets (points (N, 3) or poses (N, 4, 4)) in the tracker frame the model places the base in."""
    T_tb = np.asarray(model.T_tracker_base, float)
    if targets_base.ndim == 2:
        return transform_points(T_tb, targets_base)
    return T_tb @ targets_base


@dataclass(frozen=True)
class _Targets:
    """The targets to compensate, their rows as read, seeds (campaign only) and SMR nest per target."""

    targets: np.ndarray  # (N, 3) points or (N, 4, 4) poses, tracker frame, m
    frame: pd.DataFrame
    q_seed: np.ndarray | None
    smr: np.ndarray  # (N,) int
    step: str | None  # the campaign step they come from (None: a CSV)


def _check_options(args: argparse.Namespace) -> None:
    """Option ranges and paths, before anything is read."""
    if not 0.0 < args.interval < 1.0:
        raise CliError(
            f"--interval {args.interval}: a probability", "give a value between 0 and 1, e.g. 0.95"
        )
    if args.threshold_mm <= 0 or args.max_iter < 0 or args.length_scale_mm <= 0:
        raise CliError(
            "--threshold-mm and --length-scale-mm must be > 0, --max-iter >= 0", "give values in range"
        )
    try:
        check_paths(
            {"MODEL": args.model, "TARGETS": args.targets}, {"--output": args.output}, overwrite=args.force
        )
    except InputError as exc:
        raise CliError.from_text(str(exc)) from exc


def _campaign_targets(args: argparse.Namespace, model: CalibratedModel) -> _Targets:
    """The targets of one step of a campaign file, each in its nest unless --smr says otherwise."""
    source = read_campaign_targets(args.targets, args.step, args.orientation_convention)
    smr = source.smr if args.smr is None else np.full(len(source.frame), args.smr)
    print(f"{len(source.frame)} {source.step} targets of campaign {args.targets}", file=sys.stderr)
    if source.robot.lower() != model.robot.lower():
        print(f"warning: the campaign's robot is {source.robot}, the model's {model.robot}", file=sys.stderr)
    missing = sorted(set(smr.tolist()) - set(model.tools))
    if missing:
        raise CliError(
            f"targets of SMR nest(s) {missing}, but the model has tool points for nests {sorted(model.tools)}",
            f"calibrate with measurements of those nests, or give --smr {sorted(model.tools)[0]}",
        )
    return _Targets(source.targets, source.frame, source.q_seed, smr, source.step)


def _csv_targets(args: argparse.Namespace, model: CalibratedModel) -> _Targets:
    """The targets of a CSV, all in --smr's nest (default: the model's lowest)."""
    targets, df = read_targets(args.targets, args.orientation_convention)
    if args.frame == "base":
        targets = in_tracker_frame(model, targets)
    smr = np.full(len(df), sorted(model.tools)[0] if args.smr is None else args.smr)
    return _Targets(targets, df, None, smr, None)


def _options(args: argparse.Namespace) -> CompensationOptions:
    """compensate()'s options from the command line."""
    return CompensationOptions(
        generator=args.generator,
        threshold_m=args.threshold_mm / 1000.0,
        max_iter=args.max_iter,
        length_scale_m=args.length_scale_mm / 1000.0,
        ik_model=args.ik_model,
    )


def _q_seed(args: argparse.Namespace, chosen: _Targets) -> np.ndarray | None:
    """A campaign's joints seed the IK (not along a path, which seeds each target from its neighbour)."""
    return chosen.q_seed if chosen.q_seed is not None and not args.path else None


def _to_controller_joints(out: pd.DataFrame, coupling: JointCoupling) -> None:
    """The written joints as the controller takes them, and whether they keep its interaction limits (an IK
    solution within the model's joint box may break a limit on the coupled readings)."""
    cols = joint_columns(coupling.n_joints)
    q_controller = coupling.to_controller(out[cols].to_numpy(float))
    out[cols] = q_controller
    if coupling.limits:
        out["within_interaction_limits"] = coupling.within_limits(q_controller)
        beyond = int((~out["within_interaction_limits"]).sum())
        if beyond:
            print(
                f"warning: {beyond} target(s) need joints beyond the robot's interaction limits "
                f"({'; '.join(lim.describe() for lim in coupling.limits)}): marked within_interaction_limits "
                "= False",
                file=sys.stderr,
            )


def _output_frame(
    args: argparse.Namespace, chosen: _Targets, campaign: bool, drivers: dict, res: CompensationResult
) -> pd.DataFrame:
    """The targets as read, with the joints, predicted errors, iterations and status of each."""
    out = chosen.frame.copy()
    if campaign:
        out["smr"] = chosen.smr  # the nest each target was compensated for (--smr overrides the campaign's)
    if "temperature_c" in drivers:
        out["temperature_c"] = drivers["temperature_c"]  # what each target was compensated for
    for i, col in enumerate(joint_columns(res.q.shape[1])):
        out[col] = res.q[:, i]
    out["error_mm"] = res.error_m * 1000.0
    if res.full_pose:
        out["rotation_error_deg"] = np.rad2deg(res.rotation_error_rad)
    out["initial_error_mm"] = res.initial_error_m * 1000.0
    out["iterations"] = res.iterations
    out["status"] = res.status
    out["generator"] = res.generator
    out["outside_volume"] = res.outside_volume
    if args.path:
        out["branch_jump"] = res.branch_jump
    return out


def _print_summary(args: argparse.Namespace, res: CompensationResult) -> None:
    """One line on stdout; targets left above the threshold and branch jumps on stderr."""
    s = res.summary()
    statuses = ", ".join(f"{k} {v}" for k, v in sorted(s["statuses"].items()))
    print(
        f"{s['targets']} targets ({statuses}); predicted error mean {s['mean_error_mm_before']:.4f} -> "
        f"{s['mean_error_mm']:.4f} mm, max {s['max_error_mm']:.4f} mm; written to {args.output}"
    )
    if s["ok"] < s["targets"]:
        print(
            f"{s['targets'] - s['ok']} target(s) not below {args.threshold_mm} mm: see the status column "
            "(joints of unreachable targets are empty)",
            file=sys.stderr,
        )
    if args.path and res.branch_jump.any():
        print(f"warning: {int(res.branch_jump.sum())} branch jump(s) along the path", file=sys.stderr)
