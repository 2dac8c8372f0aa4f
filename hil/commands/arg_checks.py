"""Range checks for options and checks of every path, run before a command computes anything.

The `type=` factories raise argparse.ArgumentTypeError (argparse then names the option); the path checks
raise `InputError`, whose text is the one-line "what is wrong; what to do" the command prints (exit 2).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from hil.geometry.coupling import JointConvention


class InputError(ValueError):
    """A bad option value or path, found before any work; the message says what to do."""


def float_in(lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False):
    """argparse type: a finite float inside [lo, hi] (`lo_open` / `hi_open` exclude the bound)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        bad = not math.isfinite(v)
        bad |= lo is not None and (v <= lo if lo_open else v < lo)
        bad |= hi is not None and (v >= hi if hi_open else v > hi)
        if bad:
            raise argparse.ArgumentTypeError(f"{text} is outside {_interval(lo, hi, lo_open, hi_open)}")
        return v

    return parse


def int_in(lo: int, hi: int | None = None):
    """argparse type: an integer inside [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{text} is outside {_interval(lo, hi, False, False)}")
        return v

    return parse


def _interval(lo, hi, lo_open, hi_open) -> str:
    left = "-inf" if lo is None else f"{lo:g}"
    right = "inf" if hi is None else f"{hi:g}"
    return f"{'(' if lo is None or lo_open else '['}{left}, {right}{')' if hi is None or hi_open else ']'}"


def float_list(count: int, what: str, lo: tuple[float, ...] | None = None, positive_first: bool = False):
    """argparse type: `count` comma-separated finite floats (each >= lo[i] when given)."""

    def parse(text: str) -> tuple[float, ...]:
        parts = [p.strip() for p in text.split(",")]
        try:
            values = tuple(float(p) for p in parts)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got '{text}'") from None
        if len(values) != count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"expected {what}, got '{text}'")
        if lo is not None and any(v < b for v, b in zip(values, lo, strict=True)):
            raise argparse.ArgumentTypeError(f"'{text}': values must not be negative ({what})")
        if positive_first and values[0] <= 0:
            raise argparse.ArgumentTypeError(f"'{text}': the first value must be > 0 ({what})")
        return values

    return parse


def input_file(path: str, option: str) -> Path:
    """An existing, readable regular file."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{option}: file not found: {path}; check the path")
    if not p.is_file():
        raise InputError(f"{option}: {path} is not a file; give a file")
    if not os.access(p, os.R_OK):
        raise InputError(f"{option}: {path} is not readable; check its permissions")
    return p


FORCE_HELP = "overwrite output files that exist (without it an existing file is refused before any work)"


def add_force_option(parser: argparse.ArgumentParser) -> None:
    """`--force`: the one flag that lets a command overwrite its existing output files."""
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


def add_joint_convention_option(parser: argparse.ArgumentParser) -> None:
    """`--joint-convention`: which joints a coupled robot's data holds (hil.geometry.coupling); required for such
    a robot, never guessed."""
    parser.add_argument(
        "--joint-convention",
        choices=[str(c) for c in JointConvention],
        default=None,
        help="the data's joints when the robot file declares a coupling: controller (as the controller and "
        "pendant report them, converted here) or kinematic (already the model's); required for such a robot",
    )


def check_paths(
    inputs: dict[str, str | None], outputs: dict[str, str | None], overwrite: bool = False
) -> None:
    """Inputs exist; every output's folder exists and is writable; no output overwrites an input or another
    output; an output that exists already is refused unless `overwrite` (the command's --force), so a model or
    a report is never lost to a repeated command.

    Keys are what to name in the message (an option or 'DATA').
    """
    from hil.data.pg_url import is_campaign_url

    # a campaign in the shared store is an input too, checked when it is opened (not a file here)
    ins = {k: input_file(v, k) for k, v in inputs.items() if v and not is_campaign_url(v)}
    seen: dict[Path, str] = {}
    for option, path in outputs.items():
        if not path:
            continue
        p = Path(path)
        folder = p.parent if str(p.parent) else Path(".")
        if not folder.is_dir():
            raise InputError(f"{option}: folder {folder} does not exist; create it or choose another path")
        if p.is_dir():
            raise InputError(f"{option}: {path} is a folder; give a file name")
        if not os.access(folder, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
            raise InputError(f"{option}: {path} is not writable; choose another path")
        for in_opt, in_path in ins.items():
            if p.exists() and p.samefile(in_path) or p.resolve() == in_path.resolve():
                raise InputError(
                    f"{option}: {path} is the {in_opt} input and would be overwritten; write to another file"
                )
        if p.exists() and not overwrite:
            raise InputError(f"{option}: {path} exists; choose another path, or give --force to overwrite it")
        if p.resolve() in seen:
            raise InputError(f"{option} and {seen[p.resolve()]} name the same file {path}; give two files")
        seen[p.resolve()] = option
