"""`hil sim`: run one simulated cell as a process (`python -m fakes.sim` under the `hil` CLI, plus --write-cell)."""

from __future__ import annotations

import argparse
from pathlib import Path

from fakes.sim import DESCRIPTION, SimOptionError, add_sim_arguments, sim_options
from hil.commands.errors import CliError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sim", help="run a simulated robot cell on a loopback address", description=DESCRIPTION
    )
    add_sim_arguments(parser)
    parser.add_argument(
        "--write-cell",
        metavar="FILE",
        default=None,
        help="write the cell.toml for this cell (robot, tracker, tool drawing, envelope) once it listens",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        options = sim_options(args)
    except SimOptionError as exc:
        raise CliError(exc.message, exc.remedy) from exc
    if args.write_cell:
        from hil.commands.sim_cell import write_sim_cell

        if not Path(args.write_cell).resolve().parent.is_dir():
            raise CliError(f"--write-cell: the folder of {args.write_cell} does not exist", "create it first")

        def on_ready(info: dict, truth: dict) -> None:
            write_sim_cell(args.write_cell, info, truth, args.time_scale)

        options.on_ready = on_ready
    from fakes.sim_process import run_cell

    return run_cell(options)
