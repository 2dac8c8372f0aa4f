"""`hil model export MODEL --urdf OUT.urdf | --ur-kinematics OUT.yaml | --dh OUT.csv`: a calibrated model for
other software (ROS and motion planners read URDFs; the UR ROS description reads its kinematics file)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hil.commands.arg_checks import InputError, add_force_option, check_paths
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.commands.inputs import read_measurements

NAMES = ("auto", "ur", "generic")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "model",
        help="write a calibrated model for other software: URDF, UR kinematics file, DH table",
        description="Act on a model file written by 'hil calibrate' or 'hil diagnose -o'.",
    )
    sub = parser.add_subparsers(dest="model_command", metavar="ACTION")
    p = sub.add_parser(
        "export",
        help="write the calibrated chain as a URDF, the UR ROS description's kinematics file or a DH table",
        description="Write the calibrated kinematic chain for other software. A URDF or a DH table holds "
        "geometry only: a model with other terms (gravity yield, gear errors, temperature, a residual map) is "
        "replaced by the purely kinematic chain that best fits its predictions over the joints it was trained "
        "on, and what that costs is printed in mm (RMS and max).",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("model", help="model JSON written by 'hil calibrate' or 'hil diagnose -o'")
    p.add_argument("--urdf", default=None, help="URDF to write (base_link to tool0, the model's flange)")
    p.add_argument(
        "--ur-kinematics",
        default=None,
        help="UR arms: the kinematics YAML the UR ROS description reads (its kinematics_parameters_file)",
    )
    p.add_argument("--dh", default=None, help="CSV of the DH table (standard DH with Hayati's beta; mm, deg)")
    p.add_argument(
        "--names",
        default="auto",
        choices=NAMES,
        help="the URDF's link and joint names: ur (the UR ROS description's), generic (joint_1.., link_1..), "
        "auto (ur for a UR arm)",
    )
    p.add_argument(
        "--joints",
        default=None,
        help="the training data (CSV or campaign): fit the kinematic chain over its joints (default: joints "
        "uniform in the model's training range, a wider box)",
    )
    add_force_option(p)
    p.set_defaults(func=run_export)
    parser.set_defaults(func=lambda args: _usage(parser))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def run_export(args: argparse.Namespace) -> int:
    from hil.analysis.calibration.kinematic_equivalent import kinematic_equivalent
    from hil.data.dataset import DatasetError, joints_rad
    from hil.geometry.urdf_write import ExportError, dh_table_csv, is_ur, ur_kinematics_yaml, urdf_text
    from hil.model.calibrated_model import CalibratedModel

    outputs = {"--urdf": args.urdf, "--ur-kinematics": args.ur_kinematics, "--dh": args.dh}
    try:
        if not any(outputs.values()):
            raise InputError("give at least one of --urdf OUT.urdf, --ur-kinematics OUT.yaml, --dh OUT.csv")
        check_paths({"MODEL": args.model, "--joints": args.joints}, outputs, overwrite=args.force)
        model = CalibratedModel.load(args.model)
        joints = None
        if args.joints is not None:
            joints = joints_rad(
                read_measurements(args.joints, require_positions=False), model.nominal.n_joints
            )
        chain = kinematic_equivalent(model, joints)
        kin = chain.model.kinematic
        names = ("ur" if is_ur(kin) else "generic") if args.names == "auto" else args.names
        texts = {
            "--urdf": (args.urdf, lambda: urdf_text(kin, names, chain.T_base_chain)),
            "--ur-kinematics": (args.ur_kinematics, lambda: ur_kinematics_yaml(kin, chain.T_base_chain)),
            "--dh": (args.dh, lambda: dh_table_csv(kin)),
        }
        written = {option: text() for option, (path, text) in texts.items() if path}  # all before any write
    except ExportError as exc:
        raise CliError.from_text(str(exc)) from exc
    except (InputError, DatasetError, ValueError, OSError, KeyError) as exc:
        raise CliError.from_text(str(exc)) from exc
    _print_cost(chain)
    if args.dh and not chain.exact:
        print(f"note: --dh: {_base_note(chain.T_base_chain)}")
    for option, text in written.items():
        Path(texts[option][0]).write_text(text)
        print(f"{option}: {texts[option][0]} written ({_what(option, names)})")
    return 0


def _print_cost(chain) -> None:
    """What the chain leaves out and what it costs, or that it is the model's own geometry."""
    if chain.exact:
        print("the model is purely kinematic: its chain is written as calibrated")
        return
    held = ", ".join(f"{k} = {v:g}" for k, v in chain.references.items())
    print(
        f"left out (not kinematics, a URDF cannot hold them): {', '.join(chain.left_out)}"
        + (f"; thermal terms at the training reference {held}" if held else "")
    )
    print(
        f"the best kinematic chain, fitted to the full model on {chain.poses} poses, is off it by "
        f"{chain.rms_m * 1e3:.4f} mm RMS, {chain.max_m * 1e3:.4f} mm max: what the export costs"
    )


def _base_note(T_base_chain) -> str:
    """Where the fitted chain's base sits in the model's base frame (a DH table has no place for it)."""
    import numpy as np

    angle = float(np.degrees(np.arccos(np.clip((np.trace(T_base_chain[:3, :3]) - 1) / 2, -1.0, 1.0))))
    t = ", ".join(f"{v * 1e3:.4f}" for v in T_base_chain[:3, 3])
    return (
        f"the table's base frame is the model's moved by [{t}] mm and turned by {angle:.5f} deg (the fit moves "
        "it; a DH table cannot hold that, the URDF and the UR kinematics file put it in the first joint's origin)"
    )


def _what(option: str, names: str) -> str:
    if option == "--urdf":
        return "the UR ROS description's names, base_link to tool0" if names == "ur" else "base_link to tool0"
    if option == "--ur-kinematics":
        return "for the UR description's kinematics_parameters_file"
    return "standard DH with Hayati's beta, mm and degrees"
