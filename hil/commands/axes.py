"""`hil axes CAMPAIGN.csv -o ROBOT.toml [--json R.json]`: joint axes by circle point analysis, as a robot file."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

from hil.analysis.standards.joint_axes import AxesResult, SweepError, identify_axes, robot_file_text
from hil.commands.arg_checks import (
    InputError,
    add_force_option,
    add_joint_convention_option,
    check_paths,
    float_in,
)
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.data.dataset import DatasetError, load_dataset
from hil.data.joint_conventions import joints_to_kinematic
from hil.data.jsonable import to_jsonable
from hil.geometry.robots import get_robot, load_robot_file, robot_arg, robot_coupling

# The sweeps' 1-sigma beyond which the table cautions: half of what a calibration start needs (0.01 deg,
# 0.06 mm), so that two sigma stay within it.
CAUTION_DIRECTION_RAD = math.radians(0.005)
CAUTION_POINT_M = 0.03e-3
HELP = "joint axes from single-joint sweeps (circle point analysis), written as a robot file calibration starts from"


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "axes",
        help=HELP,
        description="Each joint turned alone while the others stand still: every SMR's arc is fitted to a "
        "circle, one axis line per joint to all its arcs, and the lines (all at one reference pose) are chained "
        "into standard DH with Hayati's beta where axes are parallel. Rows of a sweep share a `sweep` label, or "
        "(without one) follow each other with only one joint changing. Joints in q1_rad.. or q1_deg...",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument(
        "data", help="campaign CSV of the sweeps (q1_rad..q6_rad or q1_deg.., x_mm, y_mm, z_mm, smr, sweep)"
    )
    p.add_argument("-o", "--output", required=True, help="robot definition file (.toml) to write")
    p.add_argument("--json", default=None, dest="json_path", help="write the axes and the model as JSON")
    p.add_argument("--name", default=None, help="the robot's name in the file (default: the output's stem)")
    p.add_argument(
        "--robot",
        type=robot_arg,
        default=None,
        help="the arm's robot file or built-in name: its joint coupling ([coupling]) and joint limits go into "
        "the measured file (its geometry is not used: the sweeps give it)",
    )
    add_joint_convention_option(p)
    p.add_argument(
        "--tracker-sigma-um",
        type=float_in(0.1, 500.0),
        default=10.0,
        help="per-axis 1-sigma of one reading, um: judges collinear points and an SMR too near its axis",
    )
    add_force_option(p)
    p.set_defaults(func=run)


def axes_table(result: AxesResult) -> str:
    """Each axis in the tracker frame: its point and direction in separate columns, the direction's and
    the point's 1-sigma from the fit, the arcs' residual and the joint's travel."""
    head = (
        f"{'joint':<6}{'x':>11}{'y':>11}{'z':>11}  {'dx':>9}{'dy':>9}{'dz':>9}"
        f"{'dir sigma':>11}{'pt sigma':>10}{'resid':>9}{'swept':>8}"
    )
    units = f"{'':<6}{'mm':>11}{'mm':>11}{'mm':>11}  {'':>9}{'':>9}{'':>9}{'deg':>11}{'mm':>10}{'mm':>9}{'deg':>8}"
    lines = ["joint axes, tracker frame (point on the axis, unit direction of a positive turn)", head, units]
    for a in result.axes:
        lines.append(
            f"{a.joint + 1:<6}" + "".join(f"{v * 1e3:11.3f}" for v in a.point_m) + "  "
            + "".join(f"{v:+9.5f}" for v in a.direction)
            + f"{math.degrees(a.direction_sigma_rad):11.4f}{a.point_sigma_m * 1e3:10.4f}"
            f"{a.residual_rms_m * 1e3:9.4f}{math.degrees(a.swept_rad):8.1f}"
        )  # fmt: skip
    for a in result.axes:
        loose = []
        if a.direction_sigma_rad > CAUTION_DIRECTION_RAD:
            loose.append(f"its direction to {math.degrees(a.direction_sigma_rad):.4f} deg")
        if a.point_sigma_m > CAUTION_POINT_M:
            loose.append(f"its position to {a.point_sigma_m * 1e3:.4f} mm")
        if loose:
            lines.append(
                f"caution: joint {a.joint + 1}'s sweeps fix {' and '.join(loose)} (1 sigma) only: turn it farther "
                "or add SMRs farther from its axis (each SMR draws its own arc)"
            )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    try:
        if not str(args.output).lower().endswith(".toml"):
            raise InputError(f"-o {args.output}: a robot file ends in .toml; give e.g. -o robot.toml")
        check_paths(
            {"CAMPAIGN": args.data}, {"--output": args.output, "--json": args.json_path}, overwrite=args.force
        )
        coupling = robot_coupling(args.robot) if args.robot else None
        df = joints_to_kinematic(load_dataset(args.data), coupling, args.joint_convention, str(args.data))
        name = args.name or Path(args.output).stem
        result = identify_axes(
            df,
            sigma_m=args.tracker_sigma_um * 1e-6,
            source=str(args.data),
            name=name,
            coupling=coupling.describe() if coupling and coupling.coupled_rows() else None,
        )
    except (InputError, DatasetError, SweepError) as exc:
        raise CliError.from_text(str(exc)) from exc
    model = result.model
    if args.robot:  # the maker's limits: the sweeps say nothing about them
        model = replace(model, joint_limits=get_robot(args.robot).joint_limits)
    print(axes_table(result))
    limits = f"joint limits and coupling from {args.robot}" if args.robot else "joint limits unknown"
    comment = (
        f"Measured by circle point analysis (hil axes) from {Path(args.data).name}.\n"
        "Standard DH; hayati_beta marks parallel axes (their small beta is left to calibration).\n"
        f"Base frame on axis 1; the flange frame on the last axis, level with the SMR; {limits}."
    )
    text = robot_file_text(model, comment, coupling)
    Path(args.output).write_text(text)
    try:
        load_robot_file(args.output)  # what calibration will read: never leave a file it cannot
    except ValueError as exc:
        Path(args.output).unlink()
        raise CliError(f"the measured model makes no valid robot file ({exc})", "check the sweeps") from exc
    print(f"robot file written to {args.output}")
    if args.json_path:
        out = result.to_dict()
        out["source"] = str(args.data)
        out["robot_file"] = str(args.output)
        if coupling is not None:
            out["coupling"] = coupling.describe()
            out["joints_read_as"] = df.attrs.get("joints_read_as", "kinematic")
        Path(args.json_path).write_text(json.dumps(to_jsonable(out), indent=1, allow_nan=False))
        print(f"axes written to {args.json_path}")
    return 0
