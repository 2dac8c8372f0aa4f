"""`hil compensate model.json TARGETS -o JOINTS.csv`: joints that put the SMR on the targets, by the model.

TARGETS is a CSV of points / poses or a campaign file (hil.commands.campaign_targets says which targets).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import fields

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from hil.calibrated_model import CalibratedModel
from hil.commands.arg_checks import InputError, check_paths
from hil.commands.campaign_targets import DEFAULT_ORDER, SOURCES, read_campaign_targets
from hil.commands.errors import CliError
from hil.compensation import ENSEMBLE, CompensationResult, compensate, compensate_path
from hil.dataset import POSITION_COLUMNS, joint_columns
from hil.pseudo_targets import GENERATORS
from hil.store import is_campaign_file

ORIENTATION_COLUMNS: tuple[str, ...] = ("rx_deg", "ry_deg", "rz_deg")
DRIVER_COLUMNS: tuple[str, ...] = ("t_s", "temperature_c")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "compensate",
        help="joints that make a calibrated model put the SMR on target points or poses (pseudo-target loop)",
        description="Model-based pseudo-target compensation. Targets: x_mm, y_mm, z_mm of the SMR in the "
        "tracker frame, optionally rx_deg, ry_deg, rz_deg (flange orientation in the tracker frame as a "
        "rotation vector in degrees, like a UR pose) for full-pose targets, and t_s / temperature_c when "
        "the model has thermal effects. Or a campaign file (hil run / hil demo): the targets of one of its "
        "steps (--step), each with its point id and SMR nest. Writes one row per target: q1_rad..q6_rad, "
        "the predicted remaining error, the iterations used and a status; targets that cannot be "
        "compensated are kept and marked.",
    )
    p.add_argument("model", help="model JSON written by 'hil calibrate' or 'hil diagnose -o'")
    p.add_argument("targets", help="CSV of targets (see above), or a campaign file")
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
        help="targets are an ordered path: keep one IK branch, flag branch jumps (UR arms)",
    )
    p.set_defaults(func=run)


def compensate_per_smr(
    model: CalibratedModel, targets: np.ndarray, smr: np.ndarray, drivers: dict, path: bool, kwargs: dict
) -> CompensationResult:
    """`compensate` (or `compensate_path`) once per SMR nest of the targets, merged back into target order;
    per-target arrays among `kwargs` (q_seed) follow their rows."""
    results: list[tuple[np.ndarray, CompensationResult]] = []
    for nest in np.unique(smr):
        rows = np.flatnonzero(smr == nest)
        run_one = compensate_path if path else compensate
        d = {k: v[rows] for k, v in drivers.items()}
        options = {k: v[rows] if k == "q_seed" else v for k, v in kwargs.items()}
        results.append((rows, run_one(model, targets[rows], smr=int(nest), **d, **options)))
    if len(results) == 1:
        return results[0][1]
    n = len(smr)
    merged: dict = {"full_pose": results[0][1].full_pose}
    depth = max(r.history.shape[0] for _, r in results)
    history = np.full((depth, n), np.nan)
    for rows, r in results:
        history[: r.history.shape[0], rows] = r.history
    merged["history"] = history
    for f in fields(CompensationResult):
        if f.name in merged:
            continue
        first = getattr(results[0][1], f.name)
        if f.name == "branch_jump" and not path:
            merged[f.name] = first[:0]
            continue
        out = np.empty((n, *first.shape[1:]), dtype=first.dtype if first.dtype != object else object)
        if out.dtype.kind in "US":
            out = out.astype(object)
        for rows, r in results:
            out[rows] = getattr(r, f.name)
        merged[f.name] = out
    return CompensationResult(**merged)


def read_targets(path: str) -> tuple[np.ndarray, pd.DataFrame]:
    """Targets (N, 3) points or (N, 4, 4) poses in metres from a CSV; ValueError says what to fix."""
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
    values = df[cols].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if bad.size:
        raise ValueError(f"{path}: row {bad[0] + 1} has a missing or non-numeric value in {', '.join(cols)}")
    p = values[:, :3] / 1000.0
    if not have_rot:
        return p, df
    T = np.zeros((len(df), 4, 4))
    T[:, :3, :3] = Rotation.from_rotvec(np.deg2rad(values[:, 3:])).as_matrix()
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T, df


def run(args: argparse.Namespace) -> int:
    if args.threshold_mm <= 0 or args.max_iter < 0 or args.length_scale_mm <= 0:
        raise CliError("--threshold-mm and --length-scale-mm must be > 0, --max-iter >= 0", "give values in range")
    try:
        check_paths({"MODEL": args.model, "TARGETS": args.targets}, {"--output": args.output})
    except InputError as exc:
        raise CliError.from_text(str(exc)) from exc
    campaign = is_campaign_file(args.targets)
    if args.step is not None and not campaign:
        raise CliError(
            f"--step picks the targets of a campaign file; {args.targets} is a CSV",
            "drop --step, or give a campaign file",
        )
    try:
        model = CalibratedModel.load(args.model)
        if campaign:
            source = read_campaign_targets(args.targets, args.step)
            targets, df, q_seed = source.targets, source.frame, source.q_seed
            smr = source.smr if args.smr is None else np.full(len(df), args.smr)
            print(f"{len(df)} {source.step} targets of campaign {args.targets}", file=sys.stderr)
            if source.robot != model.robot.lower():
                print(
                    f"warning: the campaign's robot is {source.robot}, the model's {model.robot}",
                    file=sys.stderr,
                )
            missing = sorted(set(smr.tolist()) - set(model.tools))
            if missing:
                raise CliError(
                    f"targets of SMR nest(s) {missing}, but the model has tool points for nests {sorted(model.tools)}",
                    f"calibrate with measurements of those nests, or give --smr {sorted(model.tools)[0]}",
                )
        else:
            targets, df = read_targets(args.targets)
            q_seed = None
            smr = np.full(len(df), sorted(model.tools)[0] if args.smr is None else args.smr)
        drivers = {c: df[c].to_numpy(float) for c in DRIVER_COLUMNS if c in df.columns}
        kwargs = dict(
            generator=args.generator,
            threshold_m=args.threshold_mm / 1000.0,
            max_iter=args.max_iter,
            length_scale_m=args.length_scale_mm / 1000.0,
            ik_model=args.ik_model,
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if q_seed is not None and not args.path:  # a path seeds each target from its neighbour
                kwargs["q_seed"] = q_seed
            res = compensate_per_smr(model, targets, smr, drivers, args.path, kwargs)
    except (ValueError, OSError, KeyError) as exc:
        raise CliError.from_text(str(exc)) from exc
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    out = df.copy()
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
    out.to_csv(args.output, index=False, float_format="%.10g")
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
    return 0
