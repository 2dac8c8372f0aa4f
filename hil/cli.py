"""The `hil` command: one argparse front end, each subcommand in its own module under hil/commands."""

from __future__ import annotations

import argparse
import importlib
import os
import shlex
import sys
import warnings
from collections.abc import Iterable

from hil.commands.errors import EXIT_USAGE, CliError
from hil.errors import SessionSetupError

# Every command: its module and its one-line help. A module defines `add_parser(subparsers)`, which adds its
# parser (with the same help) and sets `func(args) -> int`; it is imported only when its command runs or
# its own --help is asked, so `hil --help` starts at once (no simulator, plotting or data libraries).
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("hil.commands.demo", "run the main job on a simulated cell: procedures through the drivers, diagnosis, report"),
    "calibrate": ("hil.commands.calibrate", "identify base frame, tool point(s) and kinematic errors from a measurement dataset"),
    "compensate": ("hil.commands.compensate", "joints that make a calibrated model put the SMR on target points or poses (pseudo-target loop)"),
    "diagnose": ("hil.commands.diagnose", "calibrate, trace the residual to missing effects, add them, report before/after"),
    "predict": ("hil.commands.predict", "predict x_mm, y_mm, z_mm (tracker frame) for the joints in a CSV with a calibrated model"),
    "model": ("hil.commands.model", "write a calibrated model for other software: URDF, UR kinematics file, DH table"),
    "iso9283": ("hil.commands.iso9283", "ISO 9283 pose accuracy and repeatability (AP, RP, AD, RD; path AT, RT) of a recorded campaign"),
    "axes": ("hil.commands.axes", "joint axes from single-joint sweeps (circle point analysis), written as a robot file calibration starts from"),
    "sim": ("hil.commands.sim", "run a simulated robot cell on a loopback address"),
    "tracker": ("hil.commands.tracker", "laser tracker: state, aim and measure (Leica emScon)"),
    "cell": ("hil.commands.cell", "check a cell configuration (and optionally its instruments)"),
    "run": ("hil.commands.run", "run a measurement procedure on a cell"),
    "serve": ("hil.commands.serve", "the operator console: start procedures, watch them live, answer prompts, find every campaign"),
    "campaign": ("hil.commands.campaign", "inspect or export a campaign (the file a measurement session writes, or one in the shared store)"),
    "fleet": ("hil.commands.fleet", "every robot's calibrations and diagnoses over time; which moved, which to look at first"),
}  # fmt: skip


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument parser whose usage errors follow the CLI convention (message, what to do; exit 2)."""

    def error(self, message: str):  # type: ignore[override]
        print(
            CliError(message, f"see '{self.prog} --help'").render(self.prog.removeprefix("hil").strip()),
            file=sys.stderr,
        )
        raise SystemExit(EXIT_USAGE)


class _VersionAction(argparse.Action):
    """`--version`: reads the installed version only when asked (importlib.metadata is slow to import)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, help: str | None = None):
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"hil {_version()}")
        parser.exit()


def _version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("hil")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def build_parser(load: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """Build the top-level parser; the commands in `load` (default: all) get their full parsers, the others
    are listed with their one-line help only, without importing their modules."""
    loaded = set(COMMANDS if load is None else load)
    parser = OneLineErrorParser(
        prog="hil",
        description="Hardware-in-the-loop measurement runner for industrial-robot accuracy.",
    )
    parser.add_argument("--version", action=_VersionAction, help="show the version of hil and exit")
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="also show what the instrument libraries print (anywhere on the line)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_line) in COMMANDS.items():
        if name in loaded:
            importlib.import_module(module_name).add_parser(subparsers)
        else:
            subparsers.add_parser(name, help=help_line)
    return parser


def _command_of(argv: list[str]) -> str | None:
    """The command named on the line: the first word that is not an option (the top level takes no values)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def _deepest_parser(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The parser of the last subcommand named on the line (`hil campaign export`), or the top level."""
    for word in argv:
        subcommands = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if subcommands is not None and word in subcommands.choices:
            parser = subcommands.choices[word]
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    typed = sys.argv[1:] if argv is None else list(argv)
    argv = [a for a in typed if a != "--verbose"]  # accepted after the command too
    command = _command_of(argv)
    try:
        parser = build_parser(load=[command] if command else [])
    except CliError as exc:  # a command whose options come from a plug-in that is missing
        print(exc.render(command or ""), file=sys.stderr)
        return EXIT_USAGE
    args, extras = parser.parse_known_args(argv)
    if extras:  # named with the (sub)command that refused them, so its own --help is the remedy
        _deepest_parser(parser, argv).error(f"unrecognized arguments: {' '.join(extras)}")
    args.verbose = len(argv) < len(typed)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    previous_showwarning = warnings.showwarning
    warnings.showwarning = _show_warning
    if args.command in RESUMABLE:  # said also when a stuck clean-up makes the Ctrl-C deadline end the process
        from hil.commands.interrupts import say_on_forced_exit

        say_on_forced_exit(_forced_exit_text(args.command, typed))
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, not at exit: a reader that left is then seen below
        return code
    except BrokenPipeError:  # the reader left (`| head`): stop quietly, as git does
        _silence_stdout()
        return EXIT_BROKEN_PIPE
    except CliError as exc:
        print(exc.render(args.command), file=sys.stderr)
        return EXIT_USAGE
    except SessionSetupError as exc:  # the station's refusal (hil.station), said as the command's own
        print(CliError(exc.message, exc.remedy).render(args.command), file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(_interrupted(args.command, typed).render(args.command), file=sys.stderr)
        return _exit_after_interrupt()
    finally:
        warnings.showwarning = previous_showwarning


EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a command whose reader went away


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as the CLI says it: one `warning: ...` line, without the Python file and line."""
    print(f"warning: {message}", file=sys.stderr if file is None else file)


def _silence_stdout() -> None:
    """Point stdout at the null device, so that flushing it at exit raises no second BrokenPipeError."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


RESUMABLE = ("run", "demo")  # commands whose campaign keeps every recorded point and resumes


def _interrupted(command: str, typed: list[str]) -> CliError:
    """What a Ctrl-C did, and the command that resumes (or repeats) the work."""
    again = "hil " + shlex.join(typed)
    if command in RESUMABLE:
        return CliError(
            "interrupted (Ctrl-C): the robot was stopped and every recorded point is kept",
            f"resume with: {again}",
        )
    return CliError("interrupted (Ctrl-C)", f"run it again: {again}")


def _forced_exit_text(command: str, typed: list[str]) -> str:
    """What a Ctrl-C says when the clean-up did not finish in time and the deadline ended the process."""
    again = "hil " + shlex.join(typed)
    return CliError(
        "interrupted (Ctrl-C): the clean-up did not finish in time and hil left without it; every recorded "
        "point is kept (each is committed before the next motion), the controller stops the robot when its "
        "connection drops",
        f"resume with: {again}",
    ).render(command)


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
