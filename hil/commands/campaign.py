"""`hil campaign show FILE` and `hil campaign export FILE --csv OUT | --parquet OUT`: read a campaign file."""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

from hil.commands.campaign_push import add_push_parser
from hil.commands.errors import CliError
from hil.data.campaigns import open_campaign
from hil.data.dataset import DatasetError
from hil.data.pg_url import is_campaign_url
from hil.data.store import (
    CampaignError,
    OutcomeRecord,
    Verdict,
    export_csv,
    export_parquet,
    is_campaign_file,
)

SNAPSHOT_SECTIONS = ("cell", "robot", "tracker", "software")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "campaign",
        help="inspect or export a campaign (the file a measurement session writes, or one in the shared store)",
        description="Show what a campaign holds, or export one procedure's measurements in the dataset "
        "contract (CSV for hil calibrate/diagnose, or Parquet). A campaign is its file, or a "
        "postgresql://USER@HOST/DATABASE?campaign=LABEL URL in the shared store.",
    )
    sub = parser.add_subparsers(dest="campaign_command", metavar="ACTION")
    show = sub.add_parser("show", help="station snapshot, steps, points, events and the last log lines")
    show.add_argument("file", help="campaign file or shared-store URL")
    show.add_argument("--log-lines", type=int, default=10, help="last log lines to print (default 10)")
    show.set_defaults(func=run_show)
    export = sub.add_parser("export", help="write one procedure's measurements as a dataset CSV or Parquet")
    export.add_argument("file", help="campaign file or shared-store URL")
    export.add_argument("--csv", default=None, help="CSV file to write (dataset contract)")
    export.add_argument("--parquet", default=None, help="Parquet file to write (same columns)")
    export.add_argument(
        "--procedure", default=None, help="procedure to export (default: the one that measures the grid)"
    )
    export.add_argument("--step", default=None, help="export only this step (default: all of them)")
    export.add_argument("--force", action="store_true", help="overwrite the output file if it exists")
    export.set_defaults(func=run_export)
    add_push_parser(sub)
    parser.set_defaults(func=lambda args: _usage(parser))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def _check_campaign(path: str) -> str | None:
    """Why `path` cannot be read as a campaign (one line with what to do), or None. A postgresql:// URL
    names a campaign in the shared store: opening it says what is wrong with it."""
    if is_campaign_url(path):
        return None
    p = Path(path)
    if not p.exists():
        return f"campaign file not found: {p}; give the path of a campaign a session wrote"
    if not is_campaign_file(p):
        return f"{p} is not a hil campaign file; give the campaign file a session wrote (hil run --campaign FILE); a CSV of measurements needs no campaign: give it to hil calibrate or hil diagnose as it is"
    return None


def _utc(t_s: float) -> str:
    if pd.isna(t_s):
        return "?"
    return datetime.fromtimestamp(float(t_s), UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _summary(section: object) -> str:
    if not isinstance(section, dict):
        return str(section)
    parts = [f"{k}={v}" for k, v in section.items() if not isinstance(v, dict | list)]
    nested = [k for k, v in section.items() if isinstance(v, dict | list)]
    return " ".join(parts + ([f"(+{', '.join(nested)})"] if nested else [])) or "(empty)"


def _snapshot_section(snapshot: dict, key: str) -> dict | None:
    """One part of a station snapshot, wherever the session put it: top level, inside the cell
    configuration ([robot], [tracker] tables) or among the station facts read from the instruments."""
    cell: dict = snapshot["cell"] if isinstance(snapshot.get("cell"), dict) else {}
    station: dict = snapshot["station"] if isinstance(snapshot.get("station"), dict) else {}
    if key == "cell":
        if not cell and "source" not in snapshot:
            return None
        out = {"source": snapshot["source"]} if "source" in snapshot else {}
        return {**out, **{k: v for k, v in cell.items() if k not in ("robot", "tracker")}}
    found: dict = {}
    for part in (snapshot.get(key), cell.get(key), station.get(key)):
        if isinstance(part, dict):
            found.update(part)
        elif part is not None:
            found[key] = part
    prefix = f"{key}_"
    found.update({k[len(prefix) :]: v for k, v in station.items() if k.startswith(prefix)})
    return found or None


def _plan_progress(steps: pd.DataFrame, recorded: pd.DataFrame) -> dict[str, str]:
    """Per procedure with a pinned plan (its "plan" step): "finished (plan complete)" once every planned point
    is recorded, else "open (n of N planned points)" for its measurement steps."""
    out = {}
    plans = steps[steps["step"] == "plan"].drop_duplicates("procedure", keep="last")
    for procedure, result in zip(plans["procedure"], plans["result"], strict=True):
        planned = set(result.get("point_ids", ())) if isinstance(result, dict) else set()
        if not planned:
            continue
        done = len(planned & set(recorded.loc[recorded["procedure"] == procedure, "point_id"]))
        out[procedure] = (
            "finished (plan complete)"
            if done == len(planned)
            else f"open ({done} of {len(planned)} planned points)"
        )
    return out


def _status_by_procedure(key: tuple[str, str], steps: pd.DataFrame, counts: pd.DataFrame) -> str:
    """A measurement step without a result or plan of its own (the registration's poses, the tool fit's holes)
    is done when its procedure recorded a result after its last point ("done: fit finished ..."), else open."""
    procedure, step = key
    row = counts[(counts["procedure"] == procedure) & (counts["step"] == step)]
    later = steps[steps["procedure"] == procedure]
    if not row.empty:
        later = later[later["recorded_s"] >= float(row["last_recorded_s"].max())]
    if later.empty:
        return "open"
    last = later.iloc[-1]
    return f"done: {last['step']} finished {_utc(last['recorded_s'])}"


def run_show(args: argparse.Namespace) -> int:
    problem = _check_campaign(args.file)
    if problem:
        raise CliError.from_text(problem)
    try:
        with open_campaign(args.file, create=False) as store:
            snapshots = store.snapshots()
            counts = store.point_counts()
            steps = store.steps()
            events = store.events()
            recorded = store.measurement_columns(("procedure", "point_id"))
            log = store.log_lines(last=max(args.log_lines, 0))
            outcomes = store.outcomes()
            created_s = store.created_s
    except CampaignError as exc:
        raise CliError.from_text(str(exc)) from exc

    print(f"campaign {args.file}: created {_utc(created_s)}, {int(counts['points'].sum())} measurements")
    if counts.size:
        first, last = counts["first_recorded_s"].min(), counts["last_recorded_s"].max()
        print(f"  measured from {_utc(first)} to {_utc(last)} (recorded by this computer's clock)")
    print(f"station snapshots: {len(snapshots)} (one per session start)")
    if snapshots:
        last = snapshots[-1]
        for key in SNAPSHOT_SECTIONS:
            section = _snapshot_section(last, key)
            print(f"  {key:<9} {_summary(section) if section else '(not recorded)'}")
        others = [k for k in last if k not in SNAPSHOT_SECTIONS + ("station", "source")]
        if others:
            print(f"  also: {', '.join(others)}")

    finished = steps.drop_duplicates(["procedure", "step"], keep="last").set_index(["procedure", "step"])
    keys = list(
        dict.fromkeys(list(zip(counts["procedure"], counts["step"], strict=True)) + list(finished.index))
    )
    points = dict(zip(zip(counts["procedure"], counts["step"], strict=True), counts["points"], strict=True))
    print("steps:" if keys else "steps: none")
    if keys:
        print(f"  {'procedure':<18}{'step':<22}{'points':>7}  status")
        plans = _plan_progress(steps, recorded)
        for key in keys:
            if key in finished.index:
                status = f"finished {_utc(finished.loc[key, 'recorded_s'])}"
            elif key[0] in plans:
                status = plans[key[0]]
            else:
                status = _status_by_procedure(key, steps, counts)
            print(f"  {key[0]:<18}{key[1]:<22}{points.get(key, 0):>7}  {status}")

    _print_outcomes(outcomes)
    if events.empty:
        print("events: none")
    else:
        by_kind = events.groupby("kind", sort=False).size()
        print("events: " + ", ".join(f"{kind} {n}" for kind, n in by_kind.items()))
        for row in events.tail(5).itertuples():
            where = "/".join(str(v) for v in (row.procedure, row.step, row.point_id) if v is not None)
            print(f"  {_utc(row.recorded_s)} {row.kind}: {row.message}" + (f" [{where}]" if where else ""))
    if not log.empty:
        print(f"last {len(log)} log line(s):")
        for row in log.itertuples():
            print(f"  {_utc(row.recorded_s)} {row.level:<7} {row.logger}: {row.message}")
    return 0


def _print_outcomes(outcomes: list[OutcomeRecord]) -> None:
    """The declared measurements as last judged (a procedure run again judges again), in mm and degrees."""
    latest = {(o.procedure, o.measurement): o for o in outcomes}
    if not latest:
        print("outcomes: none (no procedure with declared measurements has finished)")
        return
    tally = Counter(o.verdict for o in latest.values())
    print("outcomes: " + ", ".join(f"{tally[v]} {v.value}" for v in Verdict))
    for o in latest.values():
        limit = (
            f"{o.bound} {_in_user_units(o.limit_value, o.unit)}" if o.limit_value is not None else "no limit"
        )
        value = _in_user_units(o.value, o.unit)
        print(f"  {o.procedure:<18}{o.measurement:<22}{value:>14}  {limit:<20} {o.verdict.value}")


def _in_user_units(value: float | None, si_unit: str) -> str:
    """A judged value as the edges show it: metres in mm, radians in degrees."""
    if value is None:
        return "-"
    if si_unit == "m":
        return f"{value * 1e3:.4g} mm"
    if si_unit == "rad":
        return f"{math.degrees(value):.4g} deg"
    return f"{value:.4g} {si_unit}".rstrip()


def run_export(args: argparse.Namespace) -> int:
    if args.procedure is None:
        from hil.commands.inputs import grid_procedure

        args.procedure = grid_procedure()
    problem = _check_campaign(args.file)
    if problem:
        raise CliError.from_text(problem)
    if (args.csv is None) == (args.parquet is None):
        raise CliError.from_text("give exactly one of --csv OUT or --parquet OUT")
    out = Path(args.csv or args.parquet)
    if not out.parent.is_dir():
        raise CliError.from_text(
            f"output folder {out.parent} does not exist; create it or choose another path"
        )
    if out.exists() and not is_campaign_url(args.file) and out.resolve() == Path(args.file).resolve():
        raise CliError.from_text(
            "the output would overwrite the campaign file itself; choose another output path"
        )
    if out.exists() and not args.force:
        raise CliError.from_text(f"{out} exists; choose another output path, or give --force to overwrite it")
    write = export_csv if args.csv else export_parquet
    try:
        with open_campaign(args.file, create=False) as store:
            rows = write(store, out, args.procedure, args.step)
    except (DatasetError, CampaignError, ValueError) as exc:
        raise CliError.from_text(str(exc)) from exc
    what = args.procedure + (f"/{args.step}" if args.step else "")
    print(f"{rows} measurements of {what} written to {out}")
    return 0
