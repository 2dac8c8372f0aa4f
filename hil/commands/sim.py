"""`hil sim`: run one simulated cell as a process (the simulated cell plug-in under the `hil` CLI, plus --write-cell)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from hil.commands.cell_options import simulator
from hil.commands.errors import CliError
from hil.instruments.plugins import PluginOptionError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    cell = simulator()
    parser = subparsers.add_parser(
        "sim", help="run a simulated robot cell on a loopback address", description=cell.description
    )
    cell.add_arguments(parser)
    parser.add_argument(
        "--write-cell",
        metavar="FILE",
        default=None,
        help="write the cell.toml for this cell (robot, tracker, tool drawing, envelope) once it listens",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cell = simulator()
    try:
        cell.check_arguments(args)
    except PluginOptionError as exc:
        raise CliError(exc.message, exc.remedy) from exc
    on_ready: Callable[[dict, dict], None] | None = None
    if args.write_cell:
        from hil.commands.sim_cell import write_sim_cell

        if not Path(args.write_cell).resolve().parent.is_dir():
            raise CliError(f"--write-cell: the folder of {args.write_cell} does not exist", "create it first")

        def write_cell(info: dict, truth: dict) -> None:
            write_sim_cell(args.write_cell, info, truth, args.time_scale)

        on_ready = write_cell

    return cell.serve(args, on_ready)
