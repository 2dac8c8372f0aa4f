"""The HTML report is made for a person: the verdict, the error at each stage and the closed-loop result come
first, what it was made from (each input's SHA-256, the instruments, the software) heads it, every value is in
words (no Python repr: [], True, None), and a long table is folded below its first rows."""

from __future__ import annotations

import html
import re

import pytest
from calib_data import cell_datasets

from hil.analysis.diagnosis.pipeline import content_sha256, run_diagnosis
from hil.report.html import FOLD_ROWS, _table, cell_text, render_html

PYTHON_REPR = re.compile(
    r"\[\]|\[\d|\bTrue\b|\bFalse\b|\bNone\b|\bnan\b|\(~ \)|\{'|'\}|<built-in|object at 0x"
)

COMPENSATION = {  # procedures.pseudo_target's summary, as the demo passes it
    "visited": 3, "targets": 3, "smrs": 1, "generator": "model", "iterations_mean": 2.0, "start": "model-based",
    "position_mm": {
        key: {"n": 3, "mean": v, "rms": v, "max": v, "p95": v}
        for key, v in (("uncompensated", 1.2), ("start", 0.02), ("best_of_iterations", 0.011), ("final", 0.013))
    },
}  # fmt: skip


def visible_text(page: str) -> str:
    """What a browser shows: no tags, no embedded images, entities decoded."""
    page = re.sub(r"<img[^>]*>|<style>.*?</style>", "", page, flags=re.S)
    return html.unescape(re.sub(r"<[^>]+>", " ", page))


@pytest.fixture(scope="module")
def page():
    _, train, val = cell_datasets(seed=1)
    report = run_diagnosis(train, "ur10", df_validate=val)
    return report, render_html(report, compensation=COMPENSATION)


def test_the_verdict_the_stages_and_the_closed_loop_come_first(page):
    _, text = page
    order = [
        text.index(h) for h in ("<b>", "Error at each stage", "Measured pseudo-target loop", "Effects added")
    ]
    assert order == sorted(order), order
    assert text.index("Geometric calibration") > text.index("Residual left")  # the solvers' detail at the end


def test_the_head_says_what_the_report_was_made_from(page):
    report, text = page
    head = text[: text.index("Error at each stage")]
    training = report.run["inputs"]["training"]
    assert training["sha256"] and len(training["sha256"]) == 64  # data built in Python: its rows' hash
    assert "Made from" in head and training["sha256"][:12] in head and "numpy" in head


def test_no_python_value_reaches_the_page(page):
    _, text = page
    found = sorted({m.group(0) for m in PYTHON_REPR.finditer(visible_text(text))})
    assert not found, found


def test_the_repr_check_and_the_words_for_values():
    assert PYTHON_REPR.search("outlier rows []") and PYTHON_REPR.search("unexplained structure: False")
    assert cell_text(True) == "yes" and cell_text([]) == "none" and cell_text(None) == ""
    assert cell_text([3, 7]) == "3, 7" and cell_text(float("nan")) == "-"


def test_a_long_table_is_folded_below_its_first_rows():
    rows = [{"n": i} for i in range(FOLD_ROWS + 5)]
    folded = _table(rows, ["n"])
    shown, rest = folded.split("<details>")
    assert shown.count("<tr>") == FOLD_ROWS + 1 and f"all {FOLD_ROWS + 5} rows" in rest
    assert "<details>" not in _table(rows[:FOLD_ROWS], ["n"])


def test_the_content_hash_names_the_rows():
    _, train, _ = cell_datasets(seed=1)
    assert content_sha256(train) == content_sha256(train.copy())
    assert content_sha256(train) != content_sha256(train.iloc[1:])
