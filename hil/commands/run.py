"""`hil run PROCEDURE --cell cell.toml --campaign FILE [--dry-run] [options]`: run a shop-floor procedure.

Re-running the same procedure on the same campaign resumes it: recorded points are skipped, nothing is
measured twice. `--dry-run` prints the plan (poses, order, estimated duration, bounding box) and connects to
nothing. Ctrl-C stops the robot, closes the campaign and exits; a second Ctrl-C exits at once.

The procedures are those registered in the `hil.procedures` entry-point group; each one's options come from
its declaration (`hil run NAME --help`), in the units their names carry.
"""

from __future__ import annotations

import argparse
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from hil.commands.errors import CliError
from hil.commands.interrupts import interrupt_guard, stop_on_interrupt
from hil.data.pg_errors import CampaignStoreLost
from hil.data.store import CampaignError
from hil.runner.cell_config import CellConfigError, load_cell_config
from hil.runner.engine import CampaignStopped
from hil.runner.envelope import EnvelopeError
from hil.runner.operator import OperatorAbortError
from hil.runner.procedure import (
    WRONG_UNITS,
    Parameter,
    ParameterError,
    Procedure,
    ProcedureFormError,
    from_user_values,
)
from hil.runner.registry import UnknownProcedureError, load, registered


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run", help="run a measurement procedure on a cell", description=__doc__, add_help=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument(
        "-h", "--help", action=_HelpWithPurposes, help="show the registered procedures and exit"
    )
    lazy = type("ProcedureParser", (_DeclaredOptions, type(parser)), {})
    procedures = parser.add_subparsers(
        dest="procedure", metavar="PROCEDURE", required=True, parser_class=lazy
    )
    for name in registered():
        procedures.add_parser(name, help="", formatter_class=argparse.RawDescriptionHelpFormatter)


class _DeclaredOptions(argparse.ArgumentParser):
    """A procedure's parser whose options are read from its declaration the first time it parses or helps,
    so that listing the commands imports no procedure."""

    declaration: Procedure | None = None

    def load(self) -> Procedure:
        if self.declaration is None:
            name = self.prog.split()[-1]
            self.declaration = load(name)
            add_procedure_arguments(self, self.declaration)
        return self.declaration

    def _load_or_refuse(self) -> None:
        """Load the declaration; a plug-in that cannot be used (written for another hil) is refused with its
        message, which says what to change."""
        try:
            self.load()
        except (UnknownProcedureError, ProcedureFormError) as exc:
            self.error(str(exc))

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._load_or_refuse()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._load_or_refuse()
        return super().format_help()


class _HelpWithPurposes(argparse.Action):
    """`hil run --help`: load every registered declaration to list each procedure with its purpose."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        for choice in action._choices_actions:
            try:
                choice.help = action.choices[choice.dest].load().purpose
            except Exception as exc:  # noqa: BLE001 - a broken plug-in must not hide the others
                choice.help = f"(cannot load: {exc})"
        parser.print_help()
        parser.exit()


def add_procedure_arguments(parser: argparse.ArgumentParser, procedure: Procedure) -> None:
    """The common options and the procedure's declared parameters (flags in the user's units)."""
    parser.description = procedure.describe()
    parser.add_argument("--cell", required=True, help="cell configuration (TOML)")
    parser.add_argument(
        "--campaign",
        required=True,
        help="campaign file (SQLite), or postgresql://USER@HOST/DB?campaign=NAME in the shared store "
        "(password from PGPASSWORD or the cell's store.password_file); created if missing, resumed if present",
    )
    parser.add_argument("--dry-run", action="store_true", help="print the plan and move nothing")
    parser.add_argument(
        "--operator-name",
        default="",
        help="who runs the campaign, recorded with it (default: the cell config's [cell] operator)",
    )
    parser.add_argument(
        "--operator",
        choices=["auto", "console", "sim"],
        default="auto",
        help="who does the manual steps (default auto: sim on a simulated cell, else console)",
    )
    for p in procedure.parameters:
        parser.add_argument(p.flag, dest=p.keyword, **_argparse_options(p))
        for wrong in WRONG_UNITS.get(p.unit, ()):
            flag = p.flag.removesuffix(p.unit) + wrong
            parser.add_argument(flag, nargs="?", action=_WrongUnit, help=argparse.SUPPRESS, parameter=p)
    parser.set_defaults(func=run)


def _argparse_options(p: Parameter) -> dict[str, Any]:
    """argparse keywords for a declared parameter; the help says its unit, range and default."""
    if p.type is bool:
        return {"action": "store_true", "help": p.help}
    default = "required" if p.required else f"default {_shown(p.default)}" if p.default is not None else None
    allowed = p.allowed() if (p.choices or p.minimum is not None or p.maximum is not None) else None
    unit = f", {p.unit}" if p.unit else ""
    notes = "; ".join(s for s in (allowed and f"allowed {allowed}", default) if s)
    options: dict[str, Any] = {
        "type": p.type,
        "default": p.default,
        "help": f"{p.help}{unit} ({notes})" if notes else f"{p.help}{unit}",
    }
    if p.choices:
        options["choices"] = list(p.choices)
    if p.unit:
        options["metavar"] = p.unit.upper()
    if p.count > 1:
        options["nargs"] = p.count
        options["metavar"] = ("X", "Y", "Z") if p.count == 3 else (p.unit.upper() or "VALUE")
    if p.required:
        options["required"] = True
    return options


def _shown(value: Any) -> str:
    return " ".join(map(str, value)) if isinstance(value, tuple) else str(value)


class _WrongUnit(argparse.Action):
    """A flag in another unit than the declared one (--step-m for --step-mm): refused with the right flag."""

    def __init__(self, option_strings, dest, parameter: Parameter, **kwargs):
        self.parameter = parameter
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        p = self.parameter
        parser.error(f"{option_string}: {p.help} is given in {p.unit}: use {p.flag} (allowed {p.allowed()})")


def open_instruments(
    config, campaign: str | Path, operator, stack: ExitStack, holder: str = "hil run", operator_name: str = ""
):
    """open_session, its failures worded for the command line (what failed, what to do; no campaign is left)."""
    from hil.instruments.robot import RobotConnectionError, RobotError
    from hil.instruments.tracker import TrackerError
    from hil.station.instruments import open_session

    again = "then run the same command again"
    try:
        session = open_session(config, campaign, operator, stack, holder=holder, operator_name=operator_name)
    except CampaignStoreLost as exc:
        raise CliError(exc.message, f"{exc.remedy}; nothing moved") from exc
    except CampaignError as exc:
        raise CliError(str(exc), "nothing moved") from exc
    except RobotConnectionError as exc:
        raise CliError(
            f"cannot connect to the robot: {exc.message}",
            f"check that the controller is on and reachable at {config.robot_host} (robot.host in {config.source}), {again}",
        ) from exc
    except RobotError as exc:
        raise CliError(f"the robot is not ready: {exc.message}", f"{exc.remedy}; {again}") from exc
    except (TrackerError, OSError) as exc:
        reason = exc.message if isinstance(exc, TrackerError) else str(exc)
        raise CliError(
            f"cannot connect to the tracker at {config.tracker_url}: {reason}",
            f"check that the tracker is on and reachable (tracker.url in {config.source}), {again}",
        ) from exc
    stack.enter_context(stop_on_interrupt(session.engine.request_stop))  # Ctrl-C takes the engine's stop path
    return session


def run(args: argparse.Namespace) -> int:
    try:
        procedure = load(args.procedure)
        values = from_user_values(
            procedure, {p.keyword: getattr(args, p.keyword) for p in procedure.parameters}
        )
    except (UnknownProcedureError, ParameterError, ProcedureFormError) as exc:
        raise CliError(str(exc), f"see 'hil run {args.procedure} --help'; nothing moved") from exc
    try:
        config = load_cell_config(args.cell)
    except CellConfigError as exc:
        raise CliError(str(exc), "fix the keys named above (hil cell check shows the same list)") from exc
    from hil.data.pg_url import is_campaign_url

    campaign: str | Path = args.campaign if is_campaign_url(args.campaign) else Path(args.campaign)
    if isinstance(campaign, Path) and not campaign.parent.exists():
        raise CliError(
            f"campaign folder {campaign.parent} does not exist", "create it or choose another --campaign path"
        )
    try:  # built once: what --dry-run shows and the envelope check passed is what the run executes
        the_plan = procedure.make_plan(config, campaign=campaign, **values)
        config.envelope.check_poses(
            config.nominal, the_plan.joints(), config.nests_flange_m, [p.point_id for p in the_plan.poses]
        )
    except (ValueError, EnvelopeError) as exc:
        raise CliError(str(exc), "change the options or the cell config; nothing moved") from exc
    if args.dry_run:
        print(the_plan.describe())
        return 0
    from hil.station.instruments import choose_operator

    try:
        operator = choose_operator(config, args.operator)
    except ValueError as exc:
        raise CliError(str(exc), "pick another --operator") from exc
    from hil.commands.native_output import capture_native_output

    if config.reduced_speed:  # said before anything moves, so the slow first motions surprise nobody
        print(f"hil run: {config.speed_text()}")
    with interrupt_guard(), ExitStack() as stack:
        stack.enter_context(capture_native_output(verbose=getattr(args, "verbose", False)))
        session = open_instruments(
            config,
            campaign,
            operator,
            stack,
            holder=f"hil run {procedure.name}",
            operator_name=args.operator_name,
        )
        try:
            with session:
                result = procedure(session, planned=the_plan, **values)
        except (CampaignStopped, CampaignStoreLost) as exc:
            raise CliError(exc.message, exc.remedy) from exc
        except OperatorAbortError as exc:
            raise CliError(str(exc), "re-run the same command to resume; recorded points are kept") from exc
        except EnvelopeError as exc:
            raise CliError(str(exc), "nothing moved") from exc
    print(procedure.summary(result))
    return 0
