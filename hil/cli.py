"""The `hil` command: one argparse front end, each subcommand in its own module under hil/commands."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import os
import sys

from hil.commands.errors import EXIT_USAGE, CliError

# Each module defines `register(subparsers)`, which adds its parser and sets `func(args) -> int`.
COMMAND_MODULES: tuple[str, ...] = (
    "hil.commands.demo",
    "hil.commands.calibrate",
    "hil.commands.compensate",
    "hil.commands.diagnose",
    "hil.commands.predict",
    "hil.commands.sim",
    "hil.commands.tracker",
    "hil.commands.cell",
    "hil.commands.run",
    "hil.commands.campaign",
)


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument parser whose usage errors follow the CLI convention (message, what to do; exit 2)."""

    def error(self, message: str):  # type: ignore[override]
        print(CliError(message, f"see '{self.prog} --help'").render(self.prog.removeprefix("hil ")), file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def _version() -> str:
    try:
        return importlib.metadata.version("hil")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every registered subcommand."""
    parser = OneLineErrorParser(
        prog="hil",
        description="Hardware-in-the-loop measurement runner for industrial-robot accuracy.",
    )
    parser.add_argument("--version", action="version", version=f"hil {_version()}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(exc.render(args.command), file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return _exit_after_interrupt()


def _exit_after_interrupt() -> int:
    """130; but if a driver's clean-up is still stuck (its controller is gone), leave at once instead of
    letting the interpreter wait for it at exit: the campaign is already closed."""
    from hil.runner.session import abandoned_cleanups

    if abandoned_cleanups():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    return 130


if __name__ == "__main__":
    sys.exit(main())
