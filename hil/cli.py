"""The `hil` command: one argparse front end, each subcommand in its own module under hil/commands."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import sys

# Each module defines `register(subparsers)`, which adds its parser and sets `func(args) -> int`.
COMMAND_MODULES: tuple[str, ...] = (
    "hil.commands.demo",
    "hil.commands.calibrate",
    "hil.commands.diagnose",
    "hil.commands.predict",
    "hil.commands.sim",
    "hil.commands.tracker",
)


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, "message; what to do", exit 2."""

    def error(self, message: str):  # type: ignore[override]
        print(f"error: {self.prog}: {message}; see '{self.prog} --help'", file=sys.stderr)
        raise SystemExit(2)


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
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
