"""`hil diagnose DATA.csv --robot ur10 [--validate VAL.csv] [-o model.json] [--json report.json] [--html ...] [--force]`."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import implausible_changes, position_noise_m
from hil.analysis.diagnosis.pipeline import DiagnosisOptions, DiagnosisReport, run_diagnosis
from hil.commands.arg_checks import (
    InputError,
    add_force_option,
    add_joint_convention_option,
    check_paths,
    float_in,
    float_list,
    int_in,
)
from hil.commands.calibrate import add_probe_options, orientation_summary, parse_mm_vector, refuse_implausible
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.commands.inputs import read_training_and_validation, record_in_campaign
from hil.data.dataset import DatasetError, convert_orientation_convention, joint_columns, points_m, pose_ids
from hil.data.joint_conventions import joints_to_kinematic
from hil.geometry.coupling import JointCoupling
from hil.geometry.robots import ROBOT_NAMES, get_robot, robot_arg, robot_coupling
from hil.model.coupled_model import keep_coupling
from hil.model.effects import EFFECT_FAMILIES
from hil.runner.progress import Progress


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="calibrate, trace the residual to missing effects, add them, report before/after",
        description="Calibrate, then test candidate effects the model lacks (gravity compliance, cyclic joint "
        "errors, backlash, thermal expansion/drift) by k-fold held-out improvement and a significance test "
        "against the measurement noise; add the winner, refit, repeat.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("data", help="training dataset CSV")
    p.add_argument(
        "--robot",
        default="ur10",
        type=robot_arg,
        help=f"nominal robot: {', '.join(ROBOT_NAMES)}, a robot definition file (.toml, see "
        "hil/geometry/robot_models) or a URDF (FILE.urdf: its chain to the last link; FILE.urdf#LINK: to that flange link)",
    )
    add_joint_convention_option(p)
    p.add_argument("--validate", default=None, help="a separate dataset CSV never used for fitting")
    p.add_argument(
        "--validate-reregister",
        default="none",
        choices=("none", "base", "base+tool"),
        help="refit the base frame (and tool) of every stage on --validate first: a campaign from another "
        "tracker placement; the report shows both",
    )
    p.add_argument("-o", "--output", default=None, help="write the final model (effects included) as JSON")
    p.add_argument("--json", default=None, dest="json_path", help="write the report as JSON")
    p.add_argument(
        "--accept-implausible",
        action="store_true",
        help="write the model even when a parameter moved beyond a manufacturing tolerance (wrong robot or units?)",
    )
    add_force_option(p)
    p.add_argument("--html", default=None, help="write the report as a self-contained HTML page")
    p.add_argument("--folds", type=int_in(2, 50), default=5, help="k of the k-fold cross-validation, 2..50")
    p.add_argument(
        "--alpha",
        type=float_in(0.0, 0.5, lo_open=True),
        default=1e-3,
        help="significance level of the tests, in (0, 0.5]",
    )
    p.add_argument(
        "--families",
        default=",".join(EFFECT_FAMILIES),
        help="candidate effect families, comma separated",
    )
    p.add_argument(
        "--repeatability-mm",
        type=float_in(0.0, 5.0),
        default=0.0,
        help="robot repeatability added to the noise floor, mm, 0..5",
    )
    p.add_argument(
        "--tool-mm",
        default=None,
        type=parse_mm_vector,
        help="initial guess of the tool point, 'x,y,z' mm (none: from the data)",
    )
    p.add_argument(
        "--tracker-mpe-um",
        default="15,6",
        type=float_list(2, "'a,b': a um (> 0) + b um/m (>= 0)", lo=(0.0, 0.0), positive_first=True),
        help="tracker MPE 'a,b' (a um + b um/m, taken as 2 sigma) for the noise floor (15,6: AT901/AT960)",
    )
    p.add_argument("--no-beta", action="store_true", help="plain DH on every joint (no Hayati beta)")
    p.add_argument(
        "--compare-maps",
        action="store_true",
        help="always compare the residual maps (IDW, SVR, GP) on held-out blocks of the volume (and on random "
        "folds when none beats no map there), even at the noise floor",
    )
    p.add_argument(
        "--propose",
        type=int_in(1),
        default=None,
        metavar="N",
        help="design at most N poses that decide what this campaign leaves undecided (needs --plan)",
    )
    p.add_argument(
        "--plan",
        default=None,
        help="write the proposed poses here as CSV: q1_rad..q6_rad in measurement order and purpose; measure "
        "them, append the rows to the campaign and diagnose again",
    )
    p.add_argument(
        "--cell",
        default=None,
        help="cell.toml: proposed poses stay inside its envelope and face its tracker (the SMR's acceptance cone)",
    )
    add_probe_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        if args.validate_reregister != "none" and not args.validate:
            raise InputError("--validate-reregister needs --validate VAL.csv; give the validation campaign")
        if (args.propose is None) != (args.plan is None):
            raise InputError(
                "--propose N and --plan PLAN.csv go together: give both to get a plan of at most N poses"
            )
        check_paths(
            {"DATA": args.data, "--validate": args.validate, "--cell": args.cell},
            {"--output": args.output, "--json": args.json_path, "--html": args.html, "--plan": args.plan},
            overwrite=args.force,
        )
        cell = _plan_cell(args)
        families = tuple(f.strip() for f in args.families.split(",") if f.strip())
        unknown = [f for f in families if f not in EFFECT_FAMILIES]
        if unknown or not families:
            raise InputError(
                f"--families: unknown effect famil{'y' if len(unknown) == 1 else 'ies'} {unknown}; "
                f"choose from {', '.join(EFFECT_FAMILIES)}"
            )
        mpe = tuple(v * 1e-6 for v in args.tracker_mpe_um)
        df, val = read_training_and_validation(args.data, args.validate)
        df = convert_orientation_convention(df, args.orientation_convention)
        val = None if val is None else convert_orientation_convention(val, args.orientation_convention)
        coupling = robot_coupling(args.robot)
        df = joints_to_kinematic(df, coupling, args.joint_convention, str(args.data))
        val = (
            None
            if val is None
            else joints_to_kinematic(val, coupling, args.joint_convention, str(args.validate))
        )
        # A 6-DoF probe's rotation equations, weighted by its angle noise against the tracker's noise.
        df.attrs["probe_angle_noise_rad"] = float(np.deg2rad(args.probe_angle_noise_deg))
        df.attrs["position_noise_m"] = position_noise_m(points_m(df), mpe)
        tool = args.tool_mm
    except (InputError, DatasetError, ValueError) as exc:
        raise CliError.from_text(str(exc)) from exc
    n_poses = int(pose_ids(df).max()) + 1 if len(df) else 0  # several SMRs at one pose are one sample
    if n_poses < 8 * args.folds:
        raise CliError(
            f"{n_poses} distinct poses ({len(df)} rows) are too few for {args.folds}-fold cross-validation",
            f"measure at least {8 * args.folds} poses or lower --folds",
        )
    try:
        report = _diagnose(args, df, val, tool, families, mpe)
        plan = None if args.propose is None else _propose(args, df, report, cell)
    except ValueError as exc:
        raise CliError.from_text(str(exc)) from exc
    if plan is not None:
        report.plan = plan.to_dict()
    refuse_implausible(implausible_changes(report.model), args.accept_implausible)
    _print_and_write(args, report)
    from hil.report.campaign_results import diagnosis_result

    recorded = record_in_campaign(args.data, diagnosis_result(report, df, report.model.nominal.name))
    if recorded:
        print(f"model and summary recorded in the campaign {recorded}")
    if plan is not None:
        frame, said = _in_the_datas_joints(plan.frame(), coupling, df.attrs.get("joints_read_as"))
        frame.to_csv(args.plan, index=False)
        print(f"plan of {len(plan.purpose)} poses written to {args.plan}{said}")
    return 0


def _plan_cell(args: argparse.Namespace):
    """The cell a plan is for (None without --cell), checked against --robot and the campaign's robot."""
    from hil.data.campaigns import is_campaign, open_campaign
    from hil.runner.cell_config import load_cell_config

    robot = get_robot(args.robot).name
    if args.plan and is_campaign(args.data):  # a file or the shared store: the robot it was measured on
        with open_campaign(args.data, create=False) as store:
            recorded = [s.get("robot_definition", {}).get("model") for s in store.snapshots()]
        recorded = [r for r in recorded if r]
        if recorded and get_robot(recorded[-1]).name != robot:
            raise InputError(
                f"--plan: the campaign was measured on a {recorded[-1]}, --robot says {args.robot}; "
                "a plan for another robot would send it to wrong poses: give the campaign's robot"
            )
    if args.cell is None:
        return None
    if not args.plan:
        raise InputError("--cell only shapes a plan: give --propose N --plan PLAN.csv with it")
    cell = load_cell_config(args.cell)
    if cell.nominal.name != robot:
        raise InputError(
            f"--cell: {args.cell} configures a {cell.robot_model}, the campaign is diagnosed as {args.robot}; "
            "a plan must be made for the robot that measured the campaign"
        )
    return cell


def _propose(args: argparse.Namespace, df: pd.DataFrame, report: DiagnosisReport, cell):
    from hil.analysis.design.plan import propose

    admissible = None if cell is None else _cell_admissible(cell)
    sigma = float(np.sqrt(np.mean(report.noise.sigma_axis_m**2)))
    return propose(df, report.model, report.undecided, args.propose, sigma, admissible=admissible)


def _cell_admissible(cell):
    """Poses inside the cell's envelope (whole tool and wrist) with nest 1's SMR facing the tracker."""
    from hil.runner.sight import measurable

    return measurable(cell)


def _diagnose(
    args: argparse.Namespace,
    df: pd.DataFrame,
    val: pd.DataFrame | None,
    tool: np.ndarray | None,
    families: tuple[str, ...],
    mpe: tuple[float, ...],
) -> DiagnosisReport:
    with Progress().phases() as progress:
        return _run(args, df, val, tool, families, mpe, progress)


def _run(args, df, val, tool, families, mpe, progress) -> DiagnosisReport:
    return run_diagnosis(
        df,
        get_robot(args.robot, use_beta=not args.no_beta),
        df_validate=val,
        options=DiagnosisOptions(
            folds=args.folds,
            alpha=args.alpha,
            families=families,
            repeatability_m=args.repeatability_mm / 1000.0,
            tool_guess_m=tool,
            tracker_mpe_m=mpe,
            compare_maps=args.compare_maps,
            reregister_validation=args.validate_reregister,
        ),
        progress=progress,
    )


def _print_and_write(args: argparse.Namespace, report: DiagnosisReport) -> None:
    from hil.analysis.diagnosis.drift_monitor import drift_text
    from hil.report.html import in_report_units, write_html
    from hil.report.json_report import write_json
    from hil.report.text import (
        conclusion,
        final_orientation_text,
        gravity_text,
        intervals_text,
        plan_text,
        thermal_text,
        undecided_text,
    )

    print(report.table())
    for name, res in report.calibration.items():
        if res.get("orientation_rms_deg") is not None:
            print(
                f"6-DoF probe, geometric {name} fit: position RMS {res['rms_mm']:.4f} mm{orientation_summary(res)}"
            )
    final_orientation = final_orientation_text(report)
    if final_orientation:
        print(final_orientation)
    print(conclusion(report))
    for step in report.steps:
        figures = ", ".join(f"{k} {v:.4g}" for k, v in step.summary.items())
        print(f"  {step.title()}: {figures}")
        for p in map(in_report_units, step.parameters):
            std = "merged" if p["std"] is None else f"+- {p['std']:.2e}"
            print(f"    {p['name']:<34} {p['value']: .4e} {std} {p['unit']}")
    for line in (
        thermal_text(report.thermal),
        gravity_text(report.gravity),
        drift_text(report.drift),
        intervals_text(report.intervals),
    ):
        if line:
            print(line)
    print(undecided_text(report))
    if report.plan is not None:
        print(plan_text(report.plan))
    if args.json_path:
        write_json(report, args.json_path)
        print(f"report written to {args.json_path}")
    if args.html:
        write_html(report, args.html)
        print(f"HTML report written to {args.html}")
    if args.output:
        report.model.info["run"] = report.run  # what the model was made from
        keep_coupling(report.model, robot_coupling(args.robot))
        report.model.save(args.output)
        print(f"model written to {args.output}")


def _in_the_datas_joints(
    frame: pd.DataFrame, coupling: JointCoupling | None, joints_read_as: str | None
) -> tuple[pd.DataFrame, str]:
    """A plan's joints in the convention the campaign's data came in: a coupled robot's controller joints
    (what its pendant shows and its programs take) where the data held those, and a note that says so."""
    if coupling is None or not coupling.coupled_rows() or joints_read_as != "controller":
        return frame, ""
    columns = joint_columns(coupling.n_joints)
    out = frame.copy()
    out[columns] = coupling.to_controller(frame[columns].to_numpy(float))
    return out, " (in the controller's joints, as the campaign's data and the pendant give them)"
