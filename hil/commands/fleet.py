"""`hil fleet URL|FOLDER [--serial S] [--html fleet.html]`: every robot's calibrations and diagnoses over time,
the robots whose parameters moved or whose error grew flagged, most attention first."""

from __future__ import annotations

import argparse

from hil.commands.errors import CliError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "fleet",
        help="every robot's calibrations and diagnoses over time; which moved, which to look at first",
        description="Read the results of every campaign in the shared store (postgresql://USER@HOST/DATABASE) "
        "or in a folder of campaign files, flag each robot whose own parameters moved beyond their "
        "uncertainties since its previous result or whose error is over the limit, and list them most "
        "attention first.",
    )
    p.add_argument("source", help="postgresql://USER@HOST/DATABASE (password from PGPASSWORD) or a folder")
    p.add_argument(
        "--serial", default=None, help="only this robot (its serial number, or its name as listed)"
    )
    p.add_argument("--html", default=None, help="write the fleet view (table and plots per robot) here")
    p.add_argument(
        "--false-alarm",
        type=float,
        default=0.05,
        help="fleet-wide false-alarm rate of the moved flag (default 0.05)",
    )
    p.add_argument(
        "--error-limit-mm", type=float, default=0.5, help="error after calibration to flag (default 0.5 mm)"
    )
    p.add_argument("--password-file", default=None, help="file holding the database password")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hil.analysis.fleet.status import FleetOptions, fleet_status
    from hil.data.fleet_source import read_fleet
    from hil.data.pg_errors import CampaignStoreLost
    from hil.data.pg_url import CampaignURLError
    from hil.data.store import CampaignError
    from hil.report.fleet_html import attention_table, write_fleet_html

    if not 0 < args.false_alarm < 1 or args.error_limit_mm <= 0:
        raise CliError.from_text(
            "--false-alarm is a rate between 0 and 1, --error-limit-mm a positive number"
        )
    try:
        history = read_fleet(args.source, args.serial, args.password_file)
    except CampaignStoreLost as exc:
        raise CliError(exc.message, exc.remedy) from exc
    except (CampaignError, CampaignURLError, FileNotFoundError) as exc:
        raise CliError.from_text(str(exc)) from exc
    if history.results.empty:
        what = f"robot {args.serial}" if args.serial else "any robot"
        raise CliError(
            f"{history.source}: no calibration or diagnosis of {what}",
            "run hil calibrate or hil diagnose on the campaigns (they record their results), or push them",
        )
    status = fleet_status(history, FleetOptions(args.false_alarm, args.error_limit_mm * 1e-3))
    print(attention_table(status).to_string(index=False))
    flagged = int((status.robots["moved"] | status.robots["error_flag"]).sum())
    print(
        f"{len(status.robots)} robots, {len(history.results)} results; {flagged} flagged (moved: fleet-wide "
        f"false-alarm rate {args.false_alarm:g} over {status.compared} robots compared; error limit "
        f"{args.error_limit_mm:g} mm)"
    )
    if args.html:
        write_fleet_html(args.html, history, status)
        print(f"fleet view written to {args.html}")
    return 0
