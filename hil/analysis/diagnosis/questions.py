"""What a diagnosis could not decide on its campaign, as data: the questions the next measurements must answer.

After selection a campaign can leave an effect undecided for reasons no test on it can fix:

- ``period_not_covered`` (joint j): the joint's sampled range covers less than `CYCLIC_MIN_PERIODS` of a
  turn, so a once-per-turn error of it is not even a candidate (over a short arc it looks like geometry);
  decided once the range covers that much (the candidate is then tested like any other).
- ``one_approach_direction`` (joint j): fewer than `MIN_ROWS_PER_DIRECTION` rows approached from one side,
  so backlash cannot be told from geometry; decided once both sides hold that many rows.
- ``drift_unmonitored``: no pose was measured again later, so drift and slow thermal change of the cell
  have no direct evidence; decided once `MIN_REVISITS` poses were measured again at least `REVISIT_GAP`
  of the campaign's duration after their first visit.
- ``temperature_not_spanned``: the recorded temperature spans less than `MIN_TEMPERATURE_SPAN_K`; poses
  cannot decide it (a run at another temperature can), so it is reported but never planned.
- ``marginal``: a candidate that lowered the held-out error with alpha <= p < `MARGINAL_P`, or with any
  p >= alpha when its full-fit test passed (`full_fit_passed`): then the selection's two tests disagree
  (a p_cv of 0.02 beside a full-fit p of 1e-14 is no weaker a question than a p_cv of 0.005), and only the
  held-out test passing (or the full-fit one failing) decides it: its evidence is that test's own z (below);
- ``confounded_with_geometry``: a candidate the geometry imitates on these poses (refitted with every
  geometric parameter free, it was rejected as collinear or inseparable);
- ``ambiguous_effects``: two candidates that explain the same residual (the winner, refitted, took the
  rival's gain);
- ``confounded_parameters``: two geometric parameters whose estimates correlate beyond 0.95;
- ``thermal_rivals``: the model carries the links' growth driven by the recorded temperature, not the
  tracker's scale (a wrong air temperature stretches every distance about the tracker, about 1 ppm per K),
  and the temperature spans at least `MIN_TEMPERATURE_SPAN_K`: the growth (about the base, along the links)
  may have absorbed the tracker's stretch. Poses measured now, at the temperature the cell has reached, where
  the two move the SMR differently separate them.
The last five are decided when the campaign separates the rivals: hil.analysis.design.plan's evidence
(every rival coefficient's smallest relevant size at `DECISIVE_Z` standard errors or more) passes; except a
marginal candidate the full fit finds, whose evidence is the held-out test's z (below the test's own level by
definition), so that it stays open until the selection's own test decides it.

Each kind is a record class (`QuestionKind`, `QUESTIONS`); the campaign's records and report.json hold a
question as a dict (`Question.to_dict`: kind, plannable, its fields, its evidence once weighed), read back with
`question_from_dict`.

Thermal questions are kinds like the others, so a later physical treatment of temperature adds its own
rivals (arm growth against the tracker's air-temperature scale) without changing this contract.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from hil.data.dataset import joints_rad, pose_ids
from hil.model.effects import CYCLIC_MIN_PERIODS, Effect, approach_signs, stuck_air_scale, temperature_driven

MARGINAL_P = 0.01  # held-out p-value below this but not below alpha: the data leans, it does not decide
MIN_ROWS_PER_DIRECTION = 5  # the backlash candidate's own requirement (hil.model.effects.Backlash)
MIN_REVISITS = 4
REVISIT_GAP = (
    0.5  # fraction of the campaign's duration (time, else rows) between a pose's first and last visit
)
MIN_TEMPERATURE_SPAN_K = 1.0
CONFOUNDED_CORRELATION = 0.95  # hil.analysis.calibration.solve.confounded_pairs' limit


class QuestionKind(enum.StrEnum):
    """What kind of doubt a question is (its `kind` in the stored records and report.json)."""

    PERIOD_NOT_COVERED = "period_not_covered"
    ONE_APPROACH_DIRECTION = "one_approach_direction"
    DRIFT_UNMONITORED = "drift_unmonitored"
    TEMPERATURE_NOT_SPANNED = "temperature_not_spanned"
    MARGINAL = "marginal"
    CONFOUNDED_WITH_GEOMETRY = "confounded_with_geometry"
    AMBIGUOUS_EFFECTS = "ambiguous_effects"
    CONFOUNDED_PARAMETERS = "confounded_parameters"
    THERMAL_RIVALS = "thermal_rivals"


# Kinds that measurements at other poses can decide (the plan serves them); the rest need another run.
PLANNABLE = frozenset(QuestionKind) - {QuestionKind.TEMPERATURE_NOT_SPANNED}
# Kinds whose evidence is a rival model's (hil.analysis.diagnosis.evidence); the others are decided by the
# campaign's extent (joint ranges, approach directions, revisits, temperature).
STATISTICAL = frozenset(
    {
        QuestionKind.MARGINAL,
        QuestionKind.CONFOUNDED_WITH_GEOMETRY,
        QuestionKind.AMBIGUOUS_EFFECTS,
        QuestionKind.CONFOUNDED_PARAMETERS,
        QuestionKind.THERMAL_RIVALS,
    }
)
_EVIDENCE = ("evidence_z", "decisive_z")


@dataclass(frozen=True, kw_only=True)
class Question:
    """One open question; its class says which kind (`kind`), its fields what it is about and why it is open.
    A statistical question carries its evidence once the diagnosis has weighed it (`decisive_z` set: z
    `evidence_z`, None when its rival cannot be built, decided at `decisive_z`)."""

    kind: ClassVar[QuestionKind]
    evidence_z: float | None = None
    decisive_z: float | None = None

    @property
    def plannable(self) -> bool:
        """Can measurements at other poses decide it (else another run must, e.g. at another temperature)?"""
        return self.kind in PLANNABLE

    def to_dict(self) -> dict[str, Any]:
        """The question as the campaign's records and report.json hold it: kind, plannable, its fields in
        declared order, then its evidence once weighed."""
        own = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in _EVIDENCE}
        weighed = (
            {} if self.decisive_z is None else {"evidence_z": self.evidence_z, "decisive_z": self.decisive_z}
        )
        return {"kind": self.kind.value, "plannable": self.plannable, **own, **weighed}


@dataclass(frozen=True, kw_only=True)
class PeriodNotCovered(Question):
    """A joint's sampled range (deg) covers too little of a turn to test a once-per-turn error of it."""

    kind = QuestionKind.PERIOD_NOT_COVERED
    effect: dict
    range_deg: float
    needs_deg: float


@dataclass(frozen=True, kw_only=True)
class OneApproachDirection(Question):
    """Too few rows approached a joint from one side to tell its backlash from geometry."""

    kind = QuestionKind.ONE_APPROACH_DIRECTION
    effect: dict
    rows_up: int
    rows_down: int
    needs_rows: int


@dataclass(frozen=True, kw_only=True)
class DriftUnmonitored(Question):
    """Too few poses measured again late in the campaign (`gap`: what the delay is counted in)."""

    kind = QuestionKind.DRIFT_UNMONITORED
    effect: dict
    revisited_poses: int
    needs_poses: int
    gap: str


@dataclass(frozen=True, kw_only=True)
class TemperatureNotSpanned(Question):
    """The recorded temperature spans too little (or none is `recorded`) to decide thermal growth."""

    kind = QuestionKind.TEMPERATURE_NOT_SPANNED
    effect: dict
    span_k: float
    needs_k: float
    recorded: bool


@dataclass(frozen=True, kw_only=True)
class Marginal(Question):
    """A candidate the selection's tests leave between found and not found."""

    kind = QuestionKind.MARGINAL
    effect: dict
    p_cv: float
    p_chi2: float
    full_fit_passed: bool


@dataclass(frozen=True, kw_only=True)
class ConfoundedWithGeometry(Question):
    """A candidate the geometry imitates on these poses (`note`: the screening's reason)."""

    kind = QuestionKind.CONFOUNDED_WITH_GEOMETRY
    effect: dict
    correlation: float | None
    note: str


@dataclass(frozen=True, kw_only=True)
class AmbiguousEffects(Question):
    """Two candidates that explain the same residual: the one chosen and its rival."""

    kind = QuestionKind.AMBIGUOUS_EFFECTS
    effect: dict
    rival: dict


@dataclass(frozen=True, kw_only=True)
class ConfoundedParameters(Question):
    """Two geometric parameters whose estimates correlate beyond CONFOUNDED_CORRELATION."""

    kind = QuestionKind.CONFOUNDED_PARAMETERS
    parameters: list[str]
    correlation: float


@dataclass(frozen=True, kw_only=True)
class ThermalRivals(Question):
    """The tracker's scale (`effect`) against the links' growth (`rival`) over a span of `span_k`."""

    kind = QuestionKind.THERMAL_RIVALS
    effect: dict
    rival: dict
    span_k: float


QUESTIONS: dict[QuestionKind, type[Question]] = {
    cls.kind: cls
    for cls in (
        PeriodNotCovered,
        OneApproachDirection,
        DriftUnmonitored,
        TemperatureNotSpanned,
        Marginal,
        ConfoundedWithGeometry,
        AmbiguousEffects,
        ConfoundedParameters,
        ThermalRivals,
    )
}


def question_from_dict(data: dict) -> Question:
    """A question as a campaign's records or report.json hold it (`Question.to_dict`), read back."""
    cls = QUESTIONS[QuestionKind(data["kind"])]
    return cls(**{f.name: data[f.name] for f in fields(cls) if f.name in data})


def with_questions(entry: dict, convert: Callable[[Any], Any]) -> dict:
    """`entry` (a plan group, a question not planned, a settled question) with the questions it holds (under
    `question`, `also_question`, `now`) passed through `convert`: `question_to_dict` at the edge where it is
    stored, `as_question` where it is read back."""
    return {k: convert(v) if k in _HOLDS_QUESTIONS and v is not None else v for k, v in entry.items()}


_HOLDS_QUESTIONS = ("question", "also_question", "now")


def question_to_dict(q: Question | dict) -> dict:
    """A question as stored (one already a dict, e.g. read from a campaign, as it is)."""
    return q if isinstance(q, dict) else q.to_dict()


def as_question(q: Question | dict) -> Question:
    """A question record, whether stored (a dict) or already one."""
    return question_from_dict(q) if isinstance(q, dict) else q


def coverage_questions(df: pd.DataFrame) -> list[Question]:
    """Questions the campaign's extent leaves open: joint ranges, approach directions, revisits, temperature."""
    q = joints_rad(df)
    out: list[Question] = []
    need = CYCLIC_MIN_PERIODS * 2 * np.pi
    for j, span in enumerate(np.ptp(q, axis=0)):
        if span < need:
            out.append(
                PeriodNotCovered(
                    effect={"name": "cyclic", "joint": j + 1},
                    range_deg=float(np.rad2deg(span)),
                    needs_deg=float(np.rad2deg(need)),
                )
            )
    signs = approach_signs(q)
    for j in range(q.shape[1]):
        up, down = int(np.sum(signs[:, j] > 0)), int(np.sum(signs[:, j] < 0))
        if min(up, down) < MIN_ROWS_PER_DIRECTION:
            out.append(
                OneApproachDirection(
                    effect={"name": "backlash", "joint": j + 1},
                    rows_up=up,
                    rows_down=down,
                    needs_rows=MIN_ROWS_PER_DIRECTION,
                )
            )
    revisits, gap = revisited_poses(df)
    if revisits < MIN_REVISITS:
        out.append(
            DriftUnmonitored(
                effect={"name": "thermal_drift", "joint": None},
                revisited_poses=revisits,
                needs_poses=MIN_REVISITS,
                gap=gap,
            )
        )
    span_k = temperature_span_k(df)
    if span_k < MIN_TEMPERATURE_SPAN_K:
        out.append(
            TemperatureNotSpanned(
                effect={"name": "thermal_expansion", "joint": None},
                span_k=span_k,
                needs_k=MIN_TEMPERATURE_SPAN_K,
                recorded="temperature_c" in df.columns,
            )
        )
    return out


def temperature_span_k(df: pd.DataFrame) -> float:
    """The recorded temperature's span (K); 0 without a temperature column or rows."""
    if "temperature_c" not in df.columns or not len(df):
        return 0.0
    return float(np.ptp(df["temperature_c"].to_numpy(float)))


def revisited_poses(df: pd.DataFrame) -> tuple[int, str]:
    """Poses measured again at least REVISIT_GAP of the campaign's duration after their first visit, and
    what the gap is measured in ('t_s' or 'rows')."""
    if len(df) == 0:
        return 0, "rows"
    pose = pose_ids(df)
    if "t_s" in df.columns and np.ptp(df["t_s"].to_numpy(float)) > 0:
        clock, unit = df["t_s"].to_numpy(float), "t_s"
    else:
        clock, unit = np.arange(len(df), dtype=float), "rows"
    n = int(pose.max()) + 1
    first = np.full(n, np.inf)
    last = np.full(n, -np.inf)
    np.minimum.at(first, pose, clock)
    np.maximum.at(last, pose, clock)
    duration = float(np.ptp(clock))
    return int(np.sum(last - first >= REVISIT_GAP * duration)) if duration > 0 else 0, unit


def selection_questions(final_round: list, ambiguities: list[dict], alpha: float) -> list[Question]:
    """Questions the last screening round left open: marginal candidates, candidates the geometry imitates,
    candidates that explain the same residual."""
    out: list[Question] = []
    for c in final_round:
        effect = {"name": c.name, "joint": c.joint}
        if c.note.startswith(("collinear", "inseparable")):
            corr = c.geometry_correlation
            out.append(
                ConfoundedWithGeometry(
                    effect=effect,
                    correlation=None if not np.isfinite(corr) else float(corr),
                    note=c.note,
                )
            )
        elif not c.passed and c.gain_mm2 > 0 and alpha <= c.p_cv and not c.note:
            full_fit = bool(c.p_chi2 < alpha / max(len(final_round), 1))  # the screening's level for it
            if not (full_fit or c.p_cv < MARGINAL_P):
                continue
            out.append(
                Marginal(
                    effect=effect,
                    p_cv=float(c.p_cv),
                    p_chi2=float(c.p_chi2),
                    full_fit_passed=full_fit,
                )
            )
    for amb in ambiguities:
        out.append(AmbiguousEffects(effect=amb["chosen"], rival=amb["confounded_with"]))
    return out


def parameter_questions(pairs: list[tuple]) -> list[Question]:
    """Geometric parameters reported as confounded (hil.analysis.calibration.solve.confounded_pairs)."""
    return [ConfoundedParameters(parameters=[a, b], correlation=float(c)) for a, b, c in pairs]


def thermal_questions(df: pd.DataFrame, effects: list[Effect]) -> list[Question]:
    """The tracker's scale against the links' growth, when the model carries a temperature-driven growth and
    no tracker scale the data chose (a scale put in from a stuck air reading, `stuck_air_scale`, leaves the
    question to the evidence: its prior may carry it), and the recorded temperature spans enough to show
    either."""
    families = {e.family for e in effects if temperature_driven(e) and not stuck_air_scale(e)}
    if "thermal_expansion" not in families or "tracker_scale" in families:
        return []
    span_k = temperature_span_k(df)
    if span_k < MIN_TEMPERATURE_SPAN_K:
        return []  # temperature_not_spanned says it: poses at one temperature cannot
    return [
        ThermalRivals(
            effect={"name": "tracker_scale", "joint": None},
            rival={"name": "thermal_expansion", "joint": None},
            span_k=span_k,
        )
    ]


def open_questions(
    df: pd.DataFrame,
    final_round: list,
    ambiguities: list[dict],
    pairs: list[tuple],
    alpha: float,
    effects: list[Effect] | None = None,
) -> list[Question]:
    """Every undecided question of a diagnosis on `df` whose model carries `effects`, plannable ones first."""
    found = coverage_questions(df) + selection_questions(final_round, ambiguities, alpha)
    found += parameter_questions(pairs) + thermal_questions(df, effects or [])
    return sorted(found, key=lambda x: not x.plannable)


def question_key(q: Question) -> tuple:
    """What identifies a question across rounds (kind and subject)."""
    return (q.kind, *question_subject(q))


def question_subject(q: Question) -> tuple:
    """What a question is about, whatever kind of doubt it is (a marginal effect can come back as one the
    geometry imitates): its effect, its rival, its parameters."""
    eff = getattr(q, "effect", None) or {}
    rival = getattr(q, "rival", None) or {}
    return (
        eff.get("name"),
        eff.get("joint"),
        rival.get("name"),
        rival.get("joint"),
        tuple(getattr(q, "parameters", ())),
    )


def settled(before: list[Question], after: list[Question], effects_after: list[dict]) -> list[dict]:
    """Each question of an earlier diagnosis judged on the longer campaign's diagnosis: `decided` (it is no
    longer open) with `present` when its effect is now in the model, or still open with its new evidence."""
    open_now = {question_key(q): q for q in after}
    named = {(e["name"], e["joint"]) for e in effects_after}
    out = []
    for q in before:
        now = open_now.get(question_key(q))
        eff = getattr(q, "effect", None) or {}
        out.append(
            {
                "question": q,
                "decided": now is None,
                "present": (eff.get("name"), eff.get("joint")) in named if eff else None,
                "now": now,
            }
        )
    return out
