"""`hil iso9283 CAMPAIGN.csv [--json R.json] [--smr N] [--paths PATHS.csv]`: ISO 9283 figures of a recorded campaign."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from hil.analysis.standards.iso9283 import (
    Iso9283Error,
    path_campaign_figures,
    pose_performance,
)
from hil.commands.arg_checks import InputError, add_force_option, check_paths, int_in
from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter
from hil.data.dataset import CMD_POSITION_COLUMNS, DatasetError, load_dataset
from hil.data.jsonable import to_jsonable

HELP = "ISO 9283 pose accuracy and repeatability (AP, RP, AD, RD; path AT, RT) of a recorded campaign"


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "iso9283",
        help=HELP,
        description="The standard's pose performance figures from a campaign recorded on any cell: the dataset "
        "columns plus `pose` (P1..P5), `cycle` (1..n) and the commanded position x_cmd_mm, y_cmd_mm, z_cmd_mm in "
        "the tracker frame (with rx/ry/rz_deg and rx/ry/rz_cmd_deg also the orientation figures). "
        "Per pose: AP (and its x, y, z parts) and RP; between P2 and P4: AD and RD.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("data", help="campaign CSV (dataset columns, pose, cycle, x_cmd_mm, y_cmd_mm, z_cmd_mm)")
    p.add_argument("--json", default=None, dest="json_path", help="write the figures as JSON")
    p.add_argument(
        "--smr",
        type=int_in(1),
        default=None,
        help="SMR to assess when several were read per pose (default: the lowest id)",
    )
    p.add_argument(
        "--paths",
        default=None,
        help="path samples CSV for path accuracy AT / RT: path, run, x_mm, y_mm, z_mm (attained) and "
        "x_cmd_mm, y_cmd_mm, z_cmd_mm (commanded at the same instant), in time order",
    )
    add_force_option(p)
    p.set_defaults(func=run)


def read_paths(path: str) -> pd.DataFrame:
    """The path samples CSV, checked for its columns and numbers."""
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"--paths {path}: not a readable CSV ({exc}); export it as CSV text") from exc
    cols = ["x_mm", "y_mm", "z_mm", *CMD_POSITION_COLUMNS]
    missing = [c for c in ["path", "run", *cols] if c not in df.columns]
    if missing:
        raise InputError(f"--paths {path}: missing column(s) {', '.join(missing)}; add them")
    values = df[cols + ["run"]].apply(pd.to_numeric, errors="coerce")
    if values.isna().any().any():
        raise InputError(
            f"--paths {path}: missing or non-numeric values in {', '.join(values.columns[values.isna().any()])}; fill them"
        )
    df[cols + ["run"]] = values
    return df


def run(args: argparse.Namespace) -> int:
    try:
        check_paths(
            {"CAMPAIGN": args.data, "--paths": args.paths}, {"--json": args.json_path}, overwrite=args.force
        )
        df = load_dataset(args.data)
        report = pose_performance(df, source=str(args.data), smr=args.smr)
        paths = path_campaign_figures(read_paths(args.paths), args.paths) if args.paths else {}
    except (InputError, DatasetError, Iso9283Error) as exc:
        raise CliError.from_text(str(exc)) from exc
    print(report.table(f"ISO 9283 pose performance of {Path(args.data).name}"))
    for name, fig in paths.items():
        print(f"path {name}: AT {fig.AT_m * 1e3:.4f} mm, RT {fig.RT_m * 1e3:.4f} mm ({fig.runs} runs, "
              f"{fig.points} commanded points)")  # fmt: skip
    if args.json_path:
        out = report.to_dict()
        out["source"] = str(args.data)
        out["paths"] = {k: v.to_dict() for k, v in paths.items()}
        Path(args.json_path).write_text(json.dumps(to_jsonable(out), indent=1, allow_nan=False))
        print(f"figures written to {args.json_path}")
    return 0
