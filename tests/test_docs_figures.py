"""The figures the docs quote from the demo are the demo's: every number a quoting page gives to three or more
decimals, and every 'decided N of M questions', is in docs/demo-run.txt, the transcript of one `hil demo` run
that tools/demo_figures.py writes. A page quotes the demo when it carries the marker below (the README always)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hil.report.rounds import _count
from hil.report.text import z_text

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- figures: docs/demo-run.txt -->"
FIGURE = re.compile(r"(?<![\d.])-?\d+\.\d{3,}(?![\d.])")  # 1.037, 0.0148; not an address (127.69.164.192)
DECIDED = re.compile(r"decided \d+ of \d+ questions?")
TRANSCRIPT = (ROOT / "docs" / "demo-run.txt").read_text()
QUOTING = [ROOT / "README.md", *(p for p in sorted((ROOT / "docs").rglob("*.md")) if MARKER in p.read_text())]


def test_the_pages_that_quote_the_demo_say_so():
    assert {p.name for p in QUOTING} >= {"README.md", "getting-started.md"}


def stale_figures(text: str) -> list[str]:
    """What `text` quotes that the transcript does not hold, each with its line number."""
    shown = set(FIGURE.findall(TRANSCRIPT))
    lines = list(enumerate(text.splitlines(), 1))
    missing = [
        f"line {i}: {figure}" for i, line in lines for figure in FIGURE.findall(line) if figure not in shown
    ]
    return missing + [
        f"line {i}: '{p}'" for i, line in lines for p in DECIDED.findall(line) if p not in TRANSCRIPT
    ]


@pytest.mark.parametrize("page", QUOTING, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_figure_a_page_quotes_is_in_the_demo_transcript(page):
    missing = stale_figures(page.read_text())
    assert not missing, (
        f"{page.name} quotes figures the demo transcript does not hold (run the demo, `python "
        "tools/demo_figures.py demo.log`, then copy the figures): " + "; ".join(missing)
    )


def test_the_check_finds_a_stale_figure():
    assert FIGURE.findall("RMS 1.034 mm at 127.69.164.192, noise 0.0130 mm") == ["1.034", "0.0130"]
    assert stale_figures("registration RMS 98.7654 mm\nit decided 99 of 100 questions") == [
        "line 1: 98.7654",
        "line 2: 'decided 99 of 100 questions'",
    ]


def test_counts_and_evidence_read_as_words():
    assert _count(1, "pose") == "1 pose" and _count(8, "pose") == "8 poses"
    assert z_text(4.56, 4.6) == "4.56" and z_text(4.62, 4.6) == "4.62" and z_text(3.4, 4.6) == "3.4"
    assert z_text(4.6, 4.6) == "4.6"
