"""The documentation says only what the code does: every `hil ...` command line in the README and the docs
names commands and options that exist; the cell-config reference lists exactly the keys the cell config
accepts; the generated CLI reference covers every command and option; every procedure has its page.

In process and offline: the argparse parsers are built, nothing is run. (`mkdocs build --strict`, run by
`make test`, checks links, anchors and the nav.)
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import shlex
import sys
from functools import cache
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted([ROOT / "README.md", *DOCS.rglob("*.md")])

# Procedures that pages show as examples of a plug-in from outside the repository (extending.md); they are
# not installed here, so only their command word is let through.
EXAMPLE_PROCEDURES = {"distance_check"}
# Words in a command line that stand for a name the reader chooses: `hil run NAME --help`, `hil COMMAND`.
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_.]*$")
NUMBER = re.compile(r"^-?\d+(\.\d+)?([eE]-?\d+)?$")


def _load_reference():
    spec = importlib.util.spec_from_file_location("docs_reference", ROOT / "tools" / "docs_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


reference = _load_reference()


@cache
def _tree() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    return {c.words: c.parser for c in reference.commands()}


# --------------------------------------------------------------------------- command lines in the pages


def command_lines(text: str) -> list[str]:
    """Every `hil ...` invocation in a markdown text: lines of fenced code blocks (with their indented or
    backslash continuation lines) and inline code spans."""
    found: list[str] = []
    prose: list[str] = []
    in_fence = False
    current: str | None = None
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("```"):
            if current:
                found.append(current)
            current, in_fence = None, not in_fence
            continue
        if in_fence:
            body = stripped.removeprefix("$ ")
            if body.startswith("hil ") or body == "hil":
                if current:
                    found.append(current)
                current = body
            elif current and line[:1].isspace() and stripped and not stripped.startswith("#"):
                current += " " + stripped  # a synopsis continued on an indented line
            else:
                if current:
                    found.append(current)
                current = None
            if current and current.endswith("\\"):
                current = current[:-1]
            continue
        prose.append(line)
    if current:
        found.append(current)
    return found + re.findall(r"`(hil [^`]+)`", " ".join(prose))  # a span may wrap onto the next line


def _tokens(line: str) -> list[str]:
    line = re.sub(r"\s#\s.*$", "", line)  # a comment after the command
    try:
        return shlex.split(line)
    except ValueError:
        return line.split()


def _option(token: str) -> str | None:
    """The option a token names (`[--cell` -> `--cell`, `--x=1` -> `--x`), or None for a value."""
    token = token.strip("[](),;|")
    if not token.startswith("-") or NUMBER.match(token) or token in ("-", "--"):
        return None
    return token.split("=", 1)[0]


def _stands_for_a_name(word: str, words: tuple[str, ...]) -> bool:
    """`NAME`, `<command>`, `...`, or an example plug-in's procedure: a word the reader fills in."""
    example = words == ("run",) and word in EXAMPLE_PROCEDURES
    return bool(PLACEHOLDER.match(word)) or word.startswith("<") or word in ("...", "…") or example


def problems_of(line: str) -> list[str]:
    """What in one `hil ...` line names no existing command or option."""
    tree = _tree()
    top = reference.option_strings(tree[()])
    words: tuple[str, ...] = ()
    placeholder = False
    problems = []
    for token in _tokens(line)[1:]:
        option = _option(token)
        if option is not None:
            if placeholder:
                children = [p for w, p in tree.items() if w[:-1] == words and len(w) == len(words) + 1]
                known = set().union(top, *(reference.option_strings(p) for p in children))
            else:
                known = top | reference.option_strings(tree[words])
            if option not in known:
                problems.append(f"{line!r}: `{' '.join(('hil', *words))}` has no option {option}")
            continue
        if placeholder or reference._subparsers(tree[words]) is None:
            continue  # a value or a positional argument
        sub = token.strip("[]")
        if (*words, sub) in tree:
            words = (*words, sub)
        elif _stands_for_a_name(sub, words):
            placeholder = True
        else:
            problems.append(f"{line!r}: `{' '.join(('hil', *words))}` has no command {sub!r}")
            placeholder = True
    return problems


def test_the_line_parser_finds_synopses_continuations_and_inline_spans():
    text = (
        "Run `hil run tool_fit\n--cell c.toml` or `hil --version`.\n"
        "```text\n"
        "hil diagnose DATA.csv --robot ur10 [--validate VAL.csv]\n"
        "             [--propose N --plan PLAN.csv [--cell cell.toml]]   \n"
        "make test\n"
        "$ hil campaign export job.sqlite --csv grid.csv  # a comment --nope\n"
        "```\n"
    )
    lines = command_lines(text)
    assert lines[2:] == ["hil run tool_fit --cell c.toml", "hil --version"]
    assert "--plan PLAN.csv [--cell cell.toml]]" in lines[0] and len(lines) == 4
    assert all(problems_of(line) == [] for line in lines)


@pytest.mark.parametrize(
    "line, complaint",
    [
        ("hil calibrate DATA.csv --no-such-flag", "has no option --no-such-flag"),
        ("hil run tool_fit --cell c --step-mm 100", "`hil run tool_fit` has no option --step-mm"),
        ("hil run no_such_procedure --cell c", "has no command 'no_such_procedure'"),
        ("hil frobnicate model.json", "has no command 'frobnicate'"),
        ("hil campaign export job.sqlite --cvs x.csv", "has no option --cvs"),
    ],
)
def test_a_command_or_option_that_does_not_exist_is_caught(line, complaint):
    assert any(complaint in p for p in problems_of(line)), problems_of(line)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_hil_command_line_in_the_docs_exists(page):
    lines = command_lines(page.read_text())
    problems = [p for line in lines for p in problems_of(line)]
    assert not problems, "\n".join(problems)


def test_the_readme_names_the_two_commands_and_stays_short():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    assert "make demo" in text and "make test" in text  # .ci/run runs `make test`, the README's test command
    assert "make test" in (ROOT / ".ci" / "run").read_text()


# --------------------------------------------------------------------------- the cell-config reference


BASE_CELL = {
    "robot": {"model": "ur10", "host": "127.0.0.9"},
    "tracker": {"url": "socket://127.0.0.9:7000", "position_base_mm": [1000.0, 2000.0, 200.0]},
    "tool": {"nests_flange_mm": [[30.0, -20.0, 110.0]]},
    "envelope": {"box_min_mm": [-1800.0, -1800.0, -200.0], "box_max_mm": [1800.0, 1800.0, 1800.0]},
}


def documented_cell_keys() -> dict[str, set[str]]:
    """The keys of the table of docs/reference/cell-config.md, by section: rows `| `[section]` `key`, ... |`."""
    keys: dict[str, set[str]] = {}
    for line in (DOCS / "reference" / "cell-config.md").read_text().splitlines():
        row = re.match(r"^\| `\[(\w+)\]` ([^|]+)\|", line)
        if row:
            keys.setdefault(row.group(1), set()).update(re.findall(r"`(\w+)`", row.group(2)))
    return keys


def accepted_cell_keys() -> dict[str, set[str]]:
    """The keys hil.runner.cell_config accepts, by section: what it lists as known beside an unknown key."""
    from hil.runner.cell_config import SECTIONS, CellConfigError, parse_cell_config

    data = {section: dict(BASE_CELL.get(section, {})) for section in SECTIONS}
    for table in data.values():
        table["zz_not_a_key"] = 1
    with pytest.raises(CellConfigError) as refused:
        parse_cell_config(data)
    accepted: dict[str, set[str]] = {}
    for problem in refused.value.problems:
        unknown = re.match(r"^(\w+)\.zz_not_a_key: unknown setting .*; known: (.*)$", problem)
        if unknown:
            accepted[unknown.group(1)] = set(unknown.group(2).split(", "))
    assert set(accepted) == set(SECTIONS), refused.value.problems
    return accepted


def test_the_base_cell_of_these_tests_is_valid():
    from hil.runner.cell_config import parse_cell_config

    parse_cell_config(BASE_CELL)


def test_the_cell_config_reference_lists_exactly_the_accepted_keys():
    documented, accepted = documented_cell_keys(), accepted_cell_keys()
    for section in sorted(set(documented) | set(accepted)):
        wrong = documented.get(section, set()) - accepted.get(section, set())
        missing = accepted.get(section, set()) - documented.get(section, set())
        assert not wrong, f"docs/reference/cell-config.md names [{section}] keys hil does not accept: {wrong}"
        assert not missing, f"[{section}] keys hil accepts but docs/reference/cell-config.md lacks: {missing}"


# --------------------------------------------------------------------------- generated pages and the nav


def test_the_cli_reference_is_generated_and_covers_every_command_and_option():
    assert not (DOCS / reference.CLI_PAGE).exists(), "the CLI reference is generated at build time, not kept"
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    assert "tools/docs_reference.py" in config["hooks"]
    page = reference.cli_markdown()
    sections = re.split(r"\n#+ `(hil[^`]*)` \{#[\w-]+\}\n", page)
    by_command = dict(zip(sections[1::2], sections[2::2], strict=True))
    for words, parser in _tree().items():
        name = " ".join(("hil", *words))
        assert name in by_command, f"{name} is missing from the CLI reference"
        for action in parser._actions:
            if action.help == argparse.SUPPRESS or isinstance(action, argparse._SubParsersAction):
                continue
            for option in action.option_strings:
                assert f"`{option}`" in by_command[name], f"{name} {option} is missing from the CLI reference"


def _nav_files(nav) -> list[str]:
    files: list[str] = []
    for entry in nav:
        value = next(iter(entry.values())) if isinstance(entry, dict) else entry
        files += _nav_files(value) if isinstance(value, list) else [value]
    return files


def test_every_procedure_has_its_page_with_its_generated_declaration():
    from hil.runner.registry import registered

    nav = _nav_files(yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"])
    for name in registered():
        page = DOCS / "procedures" / f"{name}.md"
        assert page.exists(), f"procedure {name} has no page docs/procedures/{name}.md"
        assert f"<!-- hil:procedure {name} -->" in page.read_text()
        assert f"procedures/{name}.md" in nav
        table = reference.procedure_markdown(name)
        assert all(f"`{p.flag}`" in table for p in _procedure(name).parameters)


def _procedure(name: str):
    from hil.runner.registry import load

    return load(name)


def test_every_page_is_in_the_nav():
    nav = set(_nav_files(yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]))
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")} | {reference.CLI_PAGE}
    assert pages == nav
