"""`hil calibrate DATA.csv --robot ur10 -o model.json`: geometric calibration with both solvers."""

from __future__ import annotations

import argparse
import sys

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import (
    TOLERANCE_ANGLE_RAD,
    TOLERANCE_LENGTH_M,
    USER_UNITS,
    CalibrationResult,
    calibrate,
    implausible_changes,
    in_user_units,
)
from hil.analysis.diagnosis.pipeline import run_record
from hil.commands.arg_checks import (
    InputError,
    add_force_option,
    add_joint_convention_option,
    check_paths,
    float_in,
    float_list,
)
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.commands.inputs import read_measurements, record_in_campaign
from hil.data.dataset import (
    DEFAULT_ORIENTATION_CONVENTION,
    ORIENTATION_CONVENTIONS,
    DatasetError,
    convert_orientation_convention,
    orientation_columns,
)
from hil.data.joint_conventions import joints_to_kinematic
from hil.geometry.robots import ROBOT_NAMES, get_robot, robot_arg, robot_coupling
from hil.model.coupled_model import keep_coupling
from hil.runner.progress import Progress


def parse_mm_vector(text: str | None) -> np.ndarray | None:
    """'x,y,z' in mm -> metres (argparse type of --tool-mm); a tool point lies within 1 m of the flange."""
    if text is None:
        return None
    v = np.array(float_list(3, "x,y,z in mm")(text)) / 1000.0
    if np.linalg.norm(v) > 1.0:
        raise argparse.ArgumentTypeError(f"'{text}' lies more than 1 m from the flange: give millimetres")
    return v


def add_probe_options(p: argparse.ArgumentParser) -> None:
    """--orientation-convention and --probe-angle-noise-deg: how a 6-DoF probe's rx/ry/rz_deg are read."""
    p.add_argument(
        "--orientation-convention",
        default=DEFAULT_ORIENTATION_CONVENTION,
        choices=tuple(ORIENTATION_CONVENTIONS),
        help="convention of a 6-DoF probe's rx_deg, ry_deg, rz_deg (tracker frame): xyz-extrinsic = "
        "Rz(rz) Ry(ry) Rx(rx), xyz-intrinsic = Rx(rx) Ry(ry) Rz(rz)",
    )
    p.add_argument(
        "--probe-angle-noise-deg",
        type=float_in(0.0, 10.0, lo_open=True),
        default=0.01,
        help="1-sigma noise per axis of a 6-DoF probe's orientation, deg, in (0, 10]: weighs the rotation "
        "equations against the positions (tracker noise)",
    )


def orientation_summary(res_dict: dict) -> str:
    """' orientation RMS x deg' for a solver that had 6-DoF probe rows, else ''."""
    rms = res_dict.get("orientation_rms_deg")
    return "" if rms is None else f", orientation RMS {rms:.4f} deg"


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="identify base frame, tool point(s) and kinematic errors from a measurement dataset",
        description="Robust kinematic calibration. Runs both solvers (ridge + IGG3, and Levenberg-Marquardt "
        "with a robust loss), prints both, and writes the chosen one as a model file.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument(
        "data", help="dataset CSV (q1_rad..q6_rad, x_mm, y_mm, z_mm, optional t_s, temperature_c, smr)"
    )
    p.add_argument(
        "--robot",
        default="ur10",
        type=robot_arg,
        help=f"nominal robot: {', '.join(ROBOT_NAMES)}, a robot definition file (.toml, see "
        "hil/geometry/robot_models) or a URDF (FILE.urdf: its chain to the last link; FILE.urdf#LINK: to that flange link)",
    )
    p.add_argument("-o", "--output", required=True, help="model JSON to write")
    p.add_argument("--solver", default="ridge", choices=("ridge", "lm"), help="solver whose model is written")
    p.add_argument(
        "--tool-mm",
        default=None,
        type=parse_mm_vector,
        help="initial guess of the tool point in the flange, 'x,y,z' mm (none: from the data)",
    )
    p.add_argument("--no-beta", action="store_true", help="plain DH on every joint (no Hayati beta)")
    add_joint_convention_option(p)
    p.add_argument(
        "--accept-implausible",
        action="store_true",
        help="write the model even when a parameter moved beyond a manufacturing tolerance (wrong robot or units?)",
    )
    add_force_option(p)
    p.add_argument(
        "--residuals",
        default=None,
        help="CSV to write per row: residual dx/dy/dz/norm (mm), IGG3 weight and outlier flag of the chosen solver",
    )
    add_probe_options(p)
    p.set_defaults(func=run)


def print_parameter_table(result: CalibrationResult) -> None:
    """The change of every free parameter from the nominal, in mm and degrees, with its standard errors."""
    print(
        f"{'parameter':<16}{'change':>12}{'std':>11}{'std LS':>11}  unit  (std: larger of LS and spatial folds)"
    )
    for row in result.parameter_table():
        if row["delta"] is None:
            continue
        unit = USER_UNITS[row["unit"]][0]
        delta, std, std_ls = (in_user_units(row[k], row["unit"]) for k in ("delta", "std", "std_ls"))
        std_ls_text = f"{std_ls:11.5f}" if std_ls is not None else f"{'-':>11}"
        print(f"{row['name']:<16}{delta:+12.5f}{std:11.5f}{std_ls_text}  {unit}")


def refuse_implausible(implausible: list[str], accept: bool) -> None:
    """A fit that moves a length or an angle beyond a manufacturing tolerance is another robot's data, wrong
    units or a wrong model: refuse to write it unless the user insists (--accept-implausible)."""
    if not implausible:
        return
    for message in implausible:
        print(("warning: " if accept else "error: ") + message, file=sys.stderr)
    if not accept:
        raise CliError.from_text(
            f"no model written: {len(implausible)} parameter(s) moved beyond a manufacturing tolerance "
            f"({TOLERANCE_LENGTH_M * 1e3:g} mm, {np.rad2deg(TOLERANCE_ANGLE_RAD):g} deg); check --robot and the "
            "units of the data, or give --accept-implausible to write the model anyway"
        )


def run(args: argparse.Namespace) -> int:
    try:
        check_paths(
            {"DATA": args.data},
            {"--output": args.output, "--residuals": args.residuals},
            overwrite=args.force,
        )
        df = convert_orientation_convention(read_measurements(args.data), args.orientation_convention)
        coupling = robot_coupling(args.robot)
        df = joints_to_kinematic(df, coupling, args.joint_convention, str(args.data))
        tool = args.tool_mm
    except (InputError, DatasetError, ValueError) as exc:
        raise CliError.from_text(str(exc)) from exc
    nominal = get_robot(args.robot, use_beta=not args.no_beta)
    angle_noise = float(np.deg2rad(args.probe_angle_noise_deg))
    try:
        results = {}
        with Progress().phases() as progress:
            for i, s in enumerate(("ridge", "lm")):
                progress(f"calibrating {len(df)} poses", i, 2)
                results[s] = calibrate(
                    df, nominal, solver=s, tool_guess_m=tool, probe_angle_noise_rad=angle_noise
                )
            progress(f"calibrating {len(df)} poses", 2, 2)
    except ValueError as exc:
        raise CliError.from_text(str(exc)) from exc
    identifiability = results["ridge"].identifiability
    if identifiability is not None:  # calibrate() always sets it
        print(identifiability.summary())
    for res in results.values():
        flagged = res.outlier_rows
        print(
            f"{res.solver:>12}: RMS {res.rms_mm:.4f} mm over {int((~res.outliers).sum())} points, "
            f"sigma0 {res.sigma0_m * 1000:.4f} mm{orientation_summary(res.to_dict())}, outliers flagged: "
            + (", ".join(f"row {r}" for r in flagged) if flagged else "none")
        )
    chosen = results[args.solver]
    implausible = implausible_changes(chosen)
    for note in chosen.notes:
        if note not in implausible:
            print(f"warning: {note}", file=sys.stderr)
    print_parameter_table(chosen)
    refuse_implausible(implausible, args.accept_implausible)
    for smr, R in sorted(chosen.model.probes.items()):
        angles = ", ".join(f"{k} {float(v[0]):.4f}" for k, v in orientation_columns(R[None]).items())
        print(f"probe orientation SMR {smr} in the flange: {angles} ({DEFAULT_ORIENTATION_CONVENTION})")
    for smr, tool_m in sorted(chosen.model.tools.items()):
        print(f"tool point SMR {smr}: " + ", ".join(f"{v * 1000:.4f}" for v in tool_m) + " mm (flange frame)")
    if args.residuals:
        r_mm = chosen.residual_m * 1000.0
        table = pd.DataFrame(
            {
                "row": chosen.row_numbers,
                "dx_mm": r_mm[:, 0],
                "dy_mm": r_mm[:, 1],
                "dz_mm": r_mm[:, 2],
                "norm_mm": np.linalg.norm(r_mm, axis=1),
                "weight": chosen.weights,
                "outlier": chosen.outliers,
            }
        )
        if chosen.residual_rot_rad is not None:  # a 6-DoF probe: the angle of log(R_measured R_predicted^T)
            table.insert(5, "rot_deg", np.rad2deg(np.linalg.norm(chosen.residual_rot_rad, axis=1)))
        table.to_csv(args.residuals, index=False, float_format="%.6g")
        print(f"residuals written to {args.residuals}")
    chosen.model.info["run"] = run_record(nominal, {"training": df})  # what the model was made from
    keep_coupling(chosen.model, coupling)
    chosen.model.save(args.output)
    print(f"model written to {args.output}")
    from hil.analysis.calibration.cube_svr import raw_error, registered_nominal
    from hil.report.campaign_results import calibration_result

    _, _, before = raw_error(registered_nominal(nominal, df, tool), df)
    rms_before_m = float(np.sqrt(np.mean(np.sum(before[~chosen.outliers] ** 2, axis=1))))
    recorded = record_in_campaign(args.data, calibration_result(chosen, df, rms_before_m, nominal.name))
    if recorded:
        print(f"model and summary recorded in the campaign {recorded}")
    return 0
