"""`hil predict model.json DATA.csv -o predicted.csv`: tracker-frame SMR positions the model predicts."""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np
import pandas as pd

from hil.commands.arg_checks import InputError, add_force_option, add_joint_convention_option, check_paths
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.commands.inputs import read_measurements
from hil.data.dataset import (
    POSITION_COLUMNS,
    DatasetError,
    has_orientation,
    joints_rad,
    orientation_columns,
)
from hil.data.joint_conventions import joints_to_kinematic
from hil.model.calibrated_model import CalibratedModel
from hil.model.coupled_model import model_coupling
from hil.model.intervals import IntervalError, Intervals
from hil.model.prediction_intervals import prediction_intervals


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "predict",
        help="predict x_mm, y_mm, z_mm (tracker frame) for the joints in a CSV with a calibrated model",
        description="Where a calibrated model puts the SMR for each row of joints: reads a CSV with "
        "q1_rad..q6_rad (and the columns the model's effects need, such as t_s and temperature_c), writes the "
        "same rows with x_mm, y_mm, z_mm in the tracker frame as the model predicts them (and, for rows with a "
        "6-DoF probe's rx_deg, ry_deg, rz_deg and a model that knows the probe, its predicted orientation).",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("model", help="model JSON written by 'hil calibrate' or 'hil diagnose -o'")
    p.add_argument(
        "data", help="CSV with q1_rad..q6_rad (and the drivers the model's effects need: t_s, ...)"
    )
    p.add_argument("-o", "--output", required=True, help="CSV to write: the input columns, x/y/z_mm replaced")
    add_joint_convention_option(p)
    p.add_argument(
        "--interval",
        type=float,
        nargs="?",
        const=0.95,
        default=None,
        metavar="P",
        help="add interval_mm: the radius about each predicted point that holds the measured point with "
        "probability P (0.95 when P is left out), and for a 6-DoF probe's rows interval_deg, the angle about "
        "the predicted orientation; needs a model written by 'hil diagnose' (format 2)",
    )
    add_force_option(p)
    p.set_defaults(func=run)


def plausibility_notes(model: CalibratedModel, df: pd.DataFrame, p_m: np.ndarray) -> list[str]:
    """Joints outside what the model was trained on; predictions far from positions the file holds."""
    notes = []
    lo_hi = model.info.get("training_joint_range_rad")
    if lo_hi:
        q = joints_rad(df, model.nominal.n_joints)
        lo, hi = np.asarray(lo_hi[0]), np.asarray(lo_hi[1])
        out = np.flatnonzero(np.any((q < lo - 0.05) | (q > hi + 0.05), axis=0))
        if out.size:
            notes.append(
                f"joint(s) {', '.join(str(j + 1) for j in out)} leave the range the model was trained on "
                "(extrapolation: expect larger errors there)"
            )
    if all(c in df.columns for c in POSITION_COLUMNS):
        off = np.linalg.norm(p_m * 1000.0 - df[list(POSITION_COLUMNS)].to_numpy(float), axis=1)
        rms = float(np.sqrt(np.mean(off**2)))
        if rms > 10.0:
            notes.append(
                f"the predictions are {rms:.1f} mm RMS off the positions in the file: joints of another robot "
                f"(the model is for {model.robot}), another tracker placement, or positions not in mm?"
            )
    return notes


def run(args: argparse.Namespace) -> int:
    try:
        check_paths({"MODEL": args.model, "DATA": args.data}, {"--output": args.output}, overwrite=args.force)
        model = CalibratedModel.load(args.model)
        as_read = read_measurements(args.data, require_positions=False)
        df = joints_to_kinematic(as_read, model_coupling(model), args.joint_convention, str(args.data))
        intervals: Intervals | None = None
        if args.interval is not None:  # refused before any prediction is written
            intervals = prediction_intervals(model, df, args.interval)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            p = model.predict(df)
        R = model.predict_rotation(df) if model.probes and has_orientation(df) else None
    except IntervalError as exc:
        raise CliError.from_text(f"--interval: {exc}") from exc
    except (InputError, DatasetError, ValueError, OSError, KeyError) as exc:
        raise CliError.from_text(str(exc)) from exc
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    for note in plausibility_notes(model, df, p):
        print(f"warning: {note}", file=sys.stderr)
    if R is None and has_orientation(df):
        print(
            "note: rx_deg, ry_deg, rz_deg are written as read: the model does not know the probe's mounting "
            "(it was fitted without orientations), so it predicts no orientation",
            file=sys.stderr,
        )
    out = as_read.copy()  # the joints as given, in their convention
    for i, col in enumerate(POSITION_COLUMNS):
        out[col] = p[:, i] * 1000.0
    if R is not None:
        for col, values in orientation_columns(R).items():
            out[col] = values
    if intervals is not None:
        out["interval_mm"] = intervals.radius_mm
        if intervals.angle_deg is not None:
            out["interval_deg"] = intervals.angle_deg
        for note in intervals.notes:
            print(f"note: {note}", file=sys.stderr)
    out.to_csv(args.output, index=False, float_format="%.10g")
    print(f"{len(out)} predicted positions written to {args.output}")
    if intervals is not None:
        r = intervals.radius_mm
        print(
            f"interval_mm ({intervals.probability:g} probability): median {np.median(r):.4f}, "
            f"max {np.max(r):.4f} mm"
        )
        if intervals.angle_deg is not None:
            a = intervals.angle_deg
            print(f"interval_deg: median {np.median(a):.4f}, max {np.max(a):.4f} deg")
    return 0
