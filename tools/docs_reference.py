"""Reference pages generated from the code, so that they cannot drift from it.

An MkDocs hook (`hooks:` in mkdocs.yml) and a small library for tests/test_docs.py:

- `reference/cli.md` is written at build time from `hil`'s argparse parser tree (hil/cli.py and every
  module in hil/commands, the `hil run` procedures included): every command, its usage, its arguments
  with their defaults and help. Nothing of it is written by hand.
- a line `<!-- hil:procedure NAME -->` in a page is replaced by the procedure's declaration
  (hil.runner.procedure.Procedure): its purpose, its parameters with units, ranges and defaults, its
  measurement limits and the campaign steps it records.

`python tools/docs_reference.py` prints the CLI reference (what the build writes).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from dataclasses import dataclass

CLI_PAGE = "reference/cli.md"
PROCEDURE_MARK = re.compile(r"^<!-- hil:procedure (\w+) -->$", re.MULTILINE)
USAGE_WIDTH = 100


@dataclass
class Command:
    """One parser of the tree: its words after `hil` (`("run", "tool_fit")`) and the parser."""

    words: tuple[str, ...]
    parser: argparse.ArgumentParser
    help: str

    @property
    def name(self) -> str:
        return " ".join(("hil", *self.words))


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def commands() -> list[Command]:
    """Every parser of `hil`, depth first in the order the CLI lists them, each fully loaded."""
    from hil.cli import build_parser

    found: list[Command] = []

    def walk(parser: argparse.ArgumentParser, words: tuple[str, ...], help_line: str) -> None:
        load = getattr(parser, "load", None)  # `hil run NAME` reads its procedure's declaration lazily
        if callable(load):
            help_line = help_line or load().purpose
        found.append(Command(words, parser, help_line))
        sub = _subparsers(parser)
        if sub is None:
            return
        helps = {choice.dest: choice.help or "" for choice in sub._choices_actions}
        for name, child in sub.choices.items():
            walk(child, (*words, name), helps.get(name, ""))

    walk(build_parser(), (), "")
    return found


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    """Every option a parser accepts, documented ones and hidden ones alike (`--step-m` is refused with
    the right unit, so it is an option a page may name)."""
    return {s for action in parser._actions for s in action.option_strings}


def _escape(text: str) -> str:
    """Text for one markdown table cell."""
    return " ".join(text.split()).replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _expanded_help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    if not action.help:
        return ""
    formatter = argparse.HelpFormatter(parser.prog, width=USAGE_WIDTH)
    return formatter._expand_help(action)


def _usage(parser: argparse.ArgumentParser) -> str:
    formatter = argparse.HelpFormatter(parser.prog, width=USAGE_WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def _default(action: argparse.Action) -> str:
    if isinstance(action, (argparse._StoreTrueAction, argparse._HelpAction)) or action.nargs == 0:
        return ""
    if action.required or action.default in (None, argparse.SUPPRESS):
        return "required" if action.required else ""
    if isinstance(action.default, (list, tuple)):
        return " ".join(str(v) for v in action.default)
    return str(action.default)


def _argument_rows(command: Command) -> Iterator[str]:
    for action in command.parser._actions:
        if action.help == argparse.SUPPRESS or isinstance(action, argparse._SubParsersAction):
            continue
        if action.option_strings:
            names = ", ".join(f"`{s}`" for s in action.option_strings)
            if action.nargs != 0:
                names += f" `{_metavar(action)}`"
        else:
            names = f"`{_metavar(action)}`"
        yield f"| {names} | {_escape(_default(action))} | {_escape(_expanded_help(command.parser, action))} |"


def _metavar(action: argparse.Action) -> str:
    if action.metavar is not None:
        return str(action.metavar) if not isinstance(action.metavar, tuple) else " ".join(action.metavar)
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    base = action.dest.upper() if action.option_strings else action.dest
    if isinstance(action.nargs, int) and action.nargs > 1:
        return " ".join([base] * action.nargs)
    return base


def _anchor(command: Command) -> str:
    return "-".join(("hil", *command.words)).replace("_", "-")


def cli_markdown() -> str:
    """The command-line reference page."""
    tree = commands()
    lines = [
        "# Command-line reference",
        "",
        '!!! note "Generated"',
        "    This page is generated from `hil`'s argparse parsers when the site is built "
        "(`tools/docs_reference.py`); edit the parsers' help, not this page. "
        "`hil COMMAND --help` prints the same.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    lines += [f"| [`{c.name}`](#{_anchor(c)}) | {_escape(c.help)} |" for c in tree if c.words]
    for command in tree:
        level = "#" * min(2 + max(len(command.words) - 1, 0), 4)
        lines += ["", f"{level} `{command.name}` {{#{_anchor(command)}}}", ""]
        description = command.parser.description or command.help
        if description:
            lines += ["```text", description.strip(), "```", ""]
        lines += ["```text", _usage(command.parser), "```", ""]
        rows = list(_argument_rows(command))
        if rows:
            lines += ["| argument | default | meaning |", "|---|---|---|", *rows]
        children = [
            c for c in tree if c.words[:-1] == command.words and len(c.words) == len(command.words) + 1
        ]
        if children and command.words:
            lines += [
                "",
                "Subcommands: " + ", ".join(f"[`{c.words[-1]}`](#{_anchor(c)})" for c in children) + ".",
            ]
    return "\n".join(lines) + "\n"


def procedure_markdown(name: str) -> str:
    """A procedure's declaration as markdown: purpose, parameter table, limits, steps."""
    from hil.runner.registry import load

    procedure = load(name)
    lines = [
        f"**Purpose** (`hil run {name} --help`): {procedure.purpose}.",
        "",
        "## Parameters",
        "",
        "Every run also takes `--cell cell.toml`, `--campaign FILE`, `--dry-run` and `--operator` "
        "(see the [command-line reference](../reference/cli.md#hil-run-" + name.replace("_", "-") + ")).",
        "",
        "| flag | unit | default | allowed | meaning |",
        "|---|---|---|---|---|",
    ]
    for p in procedure.parameters:
        values = f" ×{p.count}" if p.count > 1 else ""
        if p.type is bool:
            default, allowed = "off", "switch"
        else:
            default = "required" if p.required else "—" if p.default is None else _shown(p.default)
            allowed = p.allowed()
        lines.append(
            f"| `{p.flag}`{values} | {p.unit or '—'} | {_escape(default)} | {_escape(allowed)} | {_escape(p.help)} |"
        )
    if procedure.limits:
        lines += ["", "## Measurement limits", "", "The result is refused beyond them:", ""]
        lines += ["| limit | value | meaning |", "|---|---|---|"]
        lines += [
            f"| `{limit.name}` | {limit.value:g} {limit.unit} | {_escape(limit.help)} |"
            for limit in procedure.limits
        ]
    if procedure.steps:
        lines += ["", "**Campaign steps it records:** " + ", ".join(f"`{s}`" for s in procedure.steps) + "."]
    instruction = "\n".join(
        "    " + line if line else "" for line in procedure.instruction.strip().splitlines()
    )
    lines += [
        "",
        '??? quote "The shop-floor instruction (the procedure\'s own text, as `--help` prints it)"',
        "",
    ]
    lines += ["    ```text", instruction, "    ```"]
    return "\n".join(lines)


def _shown(value: object) -> str:
    if isinstance(value, (list, tuple)):
        return " ".join(_shown(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


# --- MkDocs hook ------------------------------------------------------------------------------------------


def on_files(files, config):  # type: ignore[no-untyped-def]
    """Add the generated CLI reference to the site's files."""
    from mkdocs.structure.files import File

    files.append(File.generated(config, CLI_PAGE, content=cli_markdown()))
    return files


def on_page_markdown(markdown, page, config, files):  # type: ignore[no-untyped-def]
    """Replace every procedure mark with that procedure's declaration."""
    return PROCEDURE_MARK.sub(lambda m: procedure_markdown(m.group(1)), markdown)


if __name__ == "__main__":
    print(cli_markdown(), end="")
