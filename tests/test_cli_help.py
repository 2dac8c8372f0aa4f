"""Every option of every `hil` command (the procedures' declared parameters included) has help text, shows
its default where it has one, and names a metavar in the option's own unit; every command has a description."""

from __future__ import annotations

import argparse
import re

import pytest

from hil.cli import build_parser

UNIT_SUFFIXES = ("mm", "um", "m", "deg", "rad", "s", "c", "k")


def _parsers(parser: argparse.ArgumentParser, path: str):
    """(command path, parser) for this parser and every subcommand below it, procedures loaded."""
    if hasattr(parser, "load"):
        parser.load()  # a procedure's parser reads its declaration lazily
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, f"{path} {name}")


def _options(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if (
            isinstance(action, argparse._SubParsersAction | argparse._HelpAction)
            or action.help == argparse.SUPPRESS
        ):
            continue
        yield action


def _unit(token: str) -> str | None:
    words = re.split(r"[-_]", token.lower())
    return words[-1] if len(words) > 1 and words[-1] in UNIT_SUFFIXES else None


ALL = list(_parsers(build_parser(), "hil"))


def test_the_walk_reaches_every_command_and_procedure():
    paths = {path for path, _ in ALL}
    assert {"hil predict", "hil campaign show", "hil run joint_axes", "hil run pseudo_target"} <= paths


@pytest.mark.parametrize("path,parser", ALL, ids=[path for path, _ in ALL])
def test_every_option_has_help_and_its_default(path, parser):
    problems = []
    formatter = parser._get_formatter()
    for action in _options(parser):
        name = "/".join(action.option_strings) or action.dest
        if not (action.help or "").strip():
            problems.append(f"{name}: no help text")
            continue
        shown = formatter._get_help_string(action) or ""
        has_default = action.default not in (None, False, "", [], argparse.SUPPRESS)
        if action.option_strings and has_default and action.nargs != 0 and "default" not in shown:
            problems.append(f"{name}: its default {action.default!r} is not shown")
        flag_unit = next((_unit(o) for o in action.option_strings if _unit(o)), None)
        metavars = (
            action.metavar if isinstance(action.metavar, tuple) else (action.metavar or action.dest.upper(),)
        )
        for metavar in metavars if flag_unit else ():
            if (
                _unit(metavar)
                and _unit(metavar) != flag_unit
                or metavar.lower() in UNIT_SUFFIXES
                and metavar.lower() != flag_unit
            ):
                problems.append(f"{name}: metavar {metavar} contradicts the option's unit {flag_unit}")
    assert not problems, f"{path}: " + "; ".join(problems)


COMMANDS = [(path, parser) for path, parser in ALL if path.count(" ") == 1]


@pytest.mark.parametrize("path,parser", COMMANDS, ids=[path for path, _ in COMMANDS])
def test_every_command_has_a_description(path, parser):
    assert (parser.description or "").strip(), f"{path} --help has no description"


def test_the_walk_finds_what_it_checks():
    parser = argparse.ArgumentParser()
    parser.add_argument("--tilt-deg", type=float, default=2.0, help="tilt", metavar="TILT_RAD")
    parser.add_argument("--count", type=int, default=3)
    with pytest.raises(AssertionError, match="no help text.*contradicts|contradicts.*no help"):
        test_every_option_has_help_and_its_default("test", parser)
