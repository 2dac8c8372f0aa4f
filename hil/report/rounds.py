"""An active diagnosis loop's rounds in words, for the terminal and the HTML report (the records are
hil.analysis.design.rounds')."""

from __future__ import annotations

import html

from hil.report.text import group_text, question_text


def _effects(effects: list[dict]) -> str:
    return ", ".join(e["name"] + (f" j{e['joint']}" if e["joint"] else "") for e in effects) or "none"


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _count(n: int, noun: str) -> str:
    """'1 pose', '8 poses'."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def round_text(record: dict) -> str:
    """One round in words: what was undecided, what was measured, what got decided, the error before and after."""
    m = record["measured"]
    planned = m.get("planned", m["poses"])
    unmeasurable = m.get("unmeasurable", planned - m["poses"])
    why = [
        f"{n} {what}"
        for n, what in (
            (unmeasurable, "not measurable with this cell config"),
            (m.get("not_needed", 0), "not needed: their questions were decided before they came up"),
        )
        if n
    ]
    left = f" of {planned} planned ({'; '.join(why)})" if planned != m["poses"] else ""
    lines = [
        f"round {record['round']}: {_count(m['poses'], 'pose')} measured{left} ({m['rows_before']} -> {m['rows_after']} training rows)"
    ]
    lines.append("  undecided before:")
    lines += [f"    - {question_text(q)}" for q in record["undecided"]]
    lines.append("  measured:")
    lines += ["  " + group_text(g) for g in m["groups"]]
    for skipped in m.get("not_planned", []):
        lines.append(f"    not planned: {question_text(skipped['question']).split(':')[0]}: {skipped['why']}")
    for b in m.get("blocks", []):
        lines.append(
            f"    after block {b['block']} ({_count(b['rows'], 'pose')}): effects {_effects(b['effects'])}; "
            f"still to measure: {', '.join(b['open']) or 'nothing'}"
        )
    decided = sum(1 for s in record["settled"] if s["decided"])
    lines.append(f"  after: decided {decided} of {_count(len(record['settled']), 'question')}")
    for s in record["settled"]:
        what = question_text(s["question"]).split(":")[0]
        if not s["decided"]:
            verdict = "still open"
        elif s["present"] is None:
            verdict = "decided"
        else:
            verdict = "decided: present, added to the model" if s["present"] else "decided: not in the model"
        lines.append(f"    - {what}: {verdict}")
    lines.append(f"  effects: {_effects(record['effects_before'])} -> {_effects(record['effects_after'])}")
    b, a = record["error_before"], record["error_after"]
    lines.append(
        f"  RMS error, mm: validation {_mm(b['validation_rms_mm'])} -> {_mm(a['validation_rms_mm'])}; "
        f"held-out {_mm(b['heldout_rms_mm'])} -> {_mm(a['heldout_rms_mm'])} (on the longer campaign)"
    )
    return "\n".join(lines)


def stop_text(stop: dict) -> str:
    """Why the loop ended (a record of hil's active_loop procedure's `stop` step)."""
    return f"active loop ended after {stop['rounds']} round(s): {stop['why']}"


def rounds_text(records: list[dict], stop: dict | None = None) -> str:
    """Every round, then why the loop ended."""
    parts = [round_text(r) for r in records]
    if stop is not None:
        parts.append(stop_text(stop))
    return "\n".join(parts)


def rounds_html(records: list[dict], stop: dict | None = None) -> str:
    """The HTML section: a table of the rounds' errors, then every round in words."""
    rows = "".join(
        f"<tr><td>{r['round']}</td><td>{r['measured']['poses']}</td>"
        f"<td>{html.escape(_effects(r['effects_before']))}</td><td>{html.escape(_effects(r['effects_after']))}</td>"
        f"<td>{_mm(r['error_before']['validation_rms_mm'])}</td><td>{_mm(r['error_after']['validation_rms_mm'])}</td>"
        f"<td>{sum(1 for s in r['settled'] if s['decided'])}/{len(r['settled'])}</td></tr>"
        for r in records
    )
    table = (
        "<table><tr><th>round</th><th>poses</th><th>effects before</th><th>effects after</th>"
        "<th>validation RMS before (mm)</th><th>after (mm)</th><th>questions decided</th></tr>"
        + rows
        + "</table>"
    )
    text = html.escape(rounds_text(records, stop))
    return "<h2>Active loop: the measurements that decide</h2>" + table + f"<pre>{text}</pre>"
