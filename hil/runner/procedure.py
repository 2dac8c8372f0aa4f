"""A procedure declared as data: its name, purpose, parameters, plan, measurement limits and steps.

The declaration is what the command line, `--help`, `--dry-run` and the session read; a procedure module
adds the shop-floor instruction it automates (its body, a function of a Session) and nothing else.
Parameters are declared in the user's unit (the flag `--step-mm` takes millimetres, its default and range are
in millimetres); the procedure receives them in SI under the SI name (`step_m`). Every value is checked
against its range or choices before anything connects, and a refusal names the flag and the allowed range.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass, make_dataclass
from enum import StrEnum
from typing import Any

from hil.runner.cell_config import CellConfig
from hil.runner.plan import Plan

# user unit -> (suffix of the SI keyword, conversion to SI); "" is a count, a seed, a name
UNITS: dict[str, tuple[str, Callable[[float], float]]] = {
    "": ("", lambda v: v),
    "mm": ("_m", lambda v: v / 1e3),
    "deg": ("_rad", math.radians),
    "s": ("_s", lambda v: v),
}
# units a length or an angle is commonly given in by mistake: their flags are refused with the right one
WRONG_UNITS: dict[str, tuple[str, ...]] = {
    "mm": ("m", "cm", "in", "um"),
    "deg": ("rad", "mrad"),
    "s": ("ms", "min"),
}


class ParameterError(ValueError):
    """A parameter value the procedure cannot run with; the message names the flag and what is allowed."""


class ProcedureFormError(TypeError):
    """A declaration whose plan, body or options record does not have the form hil calls (a plug-in written
    for an older hil); the message says what to change."""


@dataclass(frozen=True)
class Parameter:
    """One parameter: `name` (the flag's stem), what it means, its type, default, range or choices, in `unit`.

    `count` > 1 takes that many values (a point x y z). `default=None` means "absent" (the procedure picks);
    `required` parameters have no default. `type=bool` is a switch (`--both-directions`).
    """

    name: str
    help: str
    default: Any = None
    type: type = float
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] = ()
    count: int = 1
    required: bool = False

    def __post_init__(self) -> None:
        if self.unit not in UNITS:
            raise ValueError(
                f"parameter {self.name}: unit {self.unit!r} is not one of {', '.join(map(repr, UNITS))}"
            )

    @property
    def keyword(self) -> str:
        """The SI keyword the procedure receives: step + mm -> step_m, tilt + deg -> tilt_rad."""
        return self.name + UNITS[self.unit][0]

    @property
    def flag(self) -> str:
        """The command-line flag, in the user's unit: --step-mm."""
        return "--" + self.name.replace("_", "-") + (f"-{self.unit}" if self.unit else "")

    def to_si(self, value: Any) -> Any:
        """The user's value (or values) in SI."""
        if value is None or not self.unit:
            return value
        convert = UNITS[self.unit][1]
        return tuple(convert(float(v)) for v in value) if self.count > 1 else convert(float(value))

    def from_si(self, value: float) -> float:
        """An SI value back in the user's unit, for messages."""
        return value / UNITS[self.unit][1](1.0)

    def allowed(self) -> str:
        """The allowed values in words, in the user's unit: '20..500 mm', 'at least 2', 'travel, random'."""
        if self.choices:
            return "one of " + ", ".join(str(c) for c in self.choices)
        unit = f" {self.unit}" if self.unit else ""
        if self.minimum is not None and self.maximum is not None:
            return f"{self.minimum:g}..{self.maximum:g}{unit}"
        if self.minimum is not None:
            return f"at least {self.minimum:g}{unit}"
        if self.maximum is not None:
            return f"at most {self.maximum:g}{unit}"
        return "any value"

    def check(self, value_si: Any) -> None:
        """Refuse a value (SI) outside the range or choices, naming the flag and what is allowed."""
        if value_si is None:
            if self.required:
                raise ParameterError(f"{self.flag} is required ({self.help})")
            return
        values = value_si if self.count > 1 else (value_si,)
        if self.count > 1 and len(values) != self.count:
            raise ParameterError(f"{self.flag} takes {self.count} values, got {len(values)}")
        for v in values:
            shown = (
                f"{self.from_si(v):g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else repr(v)
            )
            if self.choices and v not in self.choices:
                raise ParameterError(f"{self.flag} {shown}: allowed {self.allowed()}")
            low = None if self.minimum is None else UNITS[self.unit][1](self.minimum)
            high = None if self.maximum is None else UNITS[self.unit][1](self.maximum)
            if (low is not None and v < low) or (high is not None and v > high):
                raise ParameterError(f"{self.flag} {shown} is out of range: allowed {self.allowed()}")


# The tracker's shots per point, a parameter of every procedure that measures; default: the cell's own.
SHOTS = Parameter(
    "shots", "tracker shots per point (default: the cell's tracker.shots_per_point)", None, int, minimum=1
)


@dataclass(frozen=True)
class Limit:
    """A measurement limit the procedure judges its results against (the quality gate), in `unit`."""

    name: str
    help: str
    value: float
    unit: str = ""

    @property
    def keyword(self) -> str:
        return self.name + UNITS[self.unit][0]

    def to_si(self) -> float:
        return UNITS[self.unit][1](self.value)


class Role(StrEnum):
    """What a procedure's step holds that the rest of hil reads: a procedure publishes which of its steps
    plays which role (`Procedure.publishes`), so the core finds them through the registry, never by name."""

    REGISTRATION = "registration"  # a step result: T_tracker_base (4x4, m) and rms_mm
    TOOL = "tool"  # a step result: nests_flange_mm, each nest's centre in the flange frame
    GRID = "grid"  # measurements: the calibration grid the analysis reads
    VALIDATION = "validation"  # measurements: held-out poses in the grid's volume


class Bound(StrEnum):
    """Which side of a measurement its limit bounds."""

    MAX = "max"  # the measurement passes at or below the limit
    MIN = "min"  # ... at or above it


@dataclass(frozen=True)
class Measurement:
    """A figure a procedure measures, declared with the limit it is judged against (the engine judges it and
    records the outcome: pass, fail, or not judged when no limit is declared or no finite value came).

    `name` is the figure's stem, reported in SI under `keyword` (circle_residual + mm -> circle_residual_m);
    `limit`, the name of one of the procedure's Limits (None: recorded, not judged, unless the procedure
    gives the limit it computed at run time); `bound`: which side the limit bounds.
    """

    name: str
    help: str
    unit: str = ""
    limit: str | None = None
    bound: Bound = Bound.MAX

    @property
    def keyword(self) -> str:
        return self.name + UNITS[self.unit][0]

    @property
    def si_unit(self) -> str:
        """The SI unit the value is reported in: m, rad, s, or "" (a count, a ratio)."""
        return UNITS[self.unit][0].removeprefix("_")


@dataclass(frozen=True)
class Procedure:
    """A shop-floor procedure: what it is for, what it takes, what it plans, what it judges and records.

    The declared parameters and limits reach the procedure as one options record (`options`: a frozen
    dataclass whose fields are their SI keywords, `step_m`, `max_circle_residual_m`; None: one is built from
    the declarations). `plan(config, options)` is a pure function of the cell config and the options (a plan
    that depends on what a campaign holds takes a third argument, `campaign`: its path, to read only);
    `body(session, options)` runs it and returns its result, and `body(session, options, plan)` is handed
    the plan built once (the one `--dry-run` shows and the envelope check passed). `summary(result)` is
    the paragraph printed after a run; `steps` names the campaign steps it records; `measurements` the
    figures the engine judges; `publishes` which steps play which role for the rest of hil.
    """

    name: str
    purpose: str
    instruction: str
    parameters: tuple[Parameter, ...]
    plan: Callable[..., Plan]
    body: Callable[..., Any]
    limits: tuple[Limit, ...] = ()
    steps: tuple[str, ...] = ()
    summary: Callable[[Any], str] = str
    measurements: tuple[Measurement, ...] = ()
    publishes: tuple[tuple[Role, str], ...] = ()
    options: type | None = None
    _names: frozenset[str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_names", frozenset(p.keyword for p in self.parameters))
        keywords = [p.keyword for p in self.parameters] + [limit.keyword for limit in self.limits]
        if self.options is None:
            record = make_dataclass(_camel(self.name) + "Options", [(k, Any) for k in keywords], frozen=True)
            object.__setattr__(self, "options", record)
        else:
            _check_options(self.name, self.options, keywords)
        _check_form(self.name, "plan", self.plan, ("config", "options"), ("campaign",), keywords)
        _check_form(self.name, "body", self.body, ("session", "options"), ("plan",), keywords)
        limits = {limit.name for limit in self.limits}
        for m in self.measurements:
            if m.limit is not None and m.limit not in limits:
                raise ValueError(
                    f"{self.name}: measurement {m.name} names limit {m.limit!r}, which is not declared "
                    f"(declared: {', '.join(sorted(limits)) or 'none'})"
                )

    def resolve(self, values: dict[str, Any]) -> dict[str, Any]:
        """Every parameter in SI: the given values (SI keywords) over the declared defaults, each checked."""
        unknown = sorted(set(values) - self._names)
        if unknown:
            known = ", ".join(sorted(self._names))
            raise ParameterError(f"{self.name} has no parameter {', '.join(unknown)}; it takes {known}")
        resolved = {
            p.keyword: values[p.keyword] if p.keyword in values else p.to_si(p.default)
            for p in self.parameters
        }
        for p in self.parameters:
            p.check(resolved[p.keyword])
        return resolved

    def limit_values(self) -> dict[str, float]:
        """The measurement limits in SI, by keyword."""
        return {limit.keyword: limit.to_si() for limit in self.limits}

    def options_for(self, values: dict[str, Any]) -> Any:
        """The options record of these parameter values (SI keywords; defaults filled in and checked) and
        the declared limits."""
        assert self.options is not None  # set in __post_init__
        return self.options(**self.resolve(values), **self.limit_values())

    def plan_for(self, config: CellConfig, options: Any, campaign: Any = None) -> Plan:
        """The plan of an options record; a plan that reads a campaign gets its path."""
        if _positional_count(self.plan) > 2:
            return self.plan(config, options, campaign)
        return self.plan(config, options)

    def make_plan(self, config: CellConfig, campaign: Any = None, **values: Any) -> Plan:
        """The plan for these parameter values (SI keywords; defaults filled in and checked)."""
        return self.plan_for(config, self.options_for(values), campaign)

    def __call__(self, session: Any, planned: Plan | None = None, **values: Any) -> Any:
        """Run the procedure on a Session with these parameter values (SI keywords; defaults filled in and
        checked). A body that takes the plan gets `planned` (built by the caller, e.g. for the dry run and
        the envelope check, from the same values), else the plan is built here, once. The engine judges the
        declared measurements the body reports (`session.engine.measured`)."""
        options = self.options_for(values)
        limits = {limit.name: limit.to_si() for limit in self.limits}
        with session.engine.judging(self.name, self.measurements, limits):
            if _positional_count(self.body) > 2:
                the_plan = planned or self.plan_for(session.config, options, session.store.path)
                return self.body(session, options, the_plan)
            return self.body(session, options)

    def describe(self) -> str:
        """The shop-floor instruction, the measurement limits and the steps, for `hil run NAME --help`."""
        lines = [self.instruction.strip()]
        if self.limits:
            lines += ["", "measurement limits (the result is refused beyond them):"]
            lines += [f"  {limit.help}: {limit.value:g} {limit.unit}".rstrip() for limit in self.limits]
        if self.measurements:
            lines += ["", "judged measurements (the outcome is recorded in the campaign):"]
            lines += [f"  {m.help}" + (f" (limit {m.limit})" if m.limit else "") for m in self.measurements]
        if self.steps:
            lines += ["", "campaign steps: " + ", ".join(self.steps)]
        return "\n".join(lines)


def from_user_values(procedure: Procedure, values: dict[str, Any]) -> dict[str, Any]:
    """Parameter values in the user's units by keyword (the command line's) -> SI, checked."""
    return procedure.resolve(
        {p.keyword: p.to_si(values[p.keyword]) for p in procedure.parameters if p.keyword in values}
    )


def _camel(name: str) -> str:
    return "".join(part.capitalize() for part in name.split("_"))


def _positional_count(fn: Callable[..., Any]) -> int:
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return sum(p.kind in kinds for p in inspect.signature(fn).parameters.values())


def _check_options(procedure: str, record: type, keywords: list[str]) -> None:
    """A procedure's own options record must be a frozen dataclass with exactly its parameters and limits."""
    if not is_dataclass(record) or not record.__dataclass_params__.frozen:  # type: ignore[attr-defined]
        raise ProcedureFormError(
            f"procedure {procedure!r}: options must be a frozen dataclass, got {record!r}"
        )
    names = [f.name for f in fields(record)]
    missing, extra = sorted(set(keywords) - set(names)), sorted(set(names) - set(keywords))
    if missing or extra:
        raise ProcedureFormError(
            f"procedure {procedure!r}: its options record {record.__name__} must hold the declared parameters "
            f"and limits by their SI keywords; missing: {', '.join(missing) or 'none'}; not declared: "
            f"{', '.join(extra) or 'none'}"
        )


def _check_form(
    procedure: str,
    role: str,
    fn: Callable[..., Any],
    required: tuple[str, ...],
    optional: tuple[str, ...],
    keywords: list[str],
) -> None:
    """Refuse a plan or body that does not take (required..., [optional...]) positionally, naming the change:
    the form before options records took every parameter as a keyword."""
    parameters = inspect.signature(fn).parameters.values()
    by_keyword = [p.name for p in parameters if p.kind in (p.KEYWORD_ONLY, p.VAR_KEYWORD)]
    count = _positional_count(fn)
    if not by_keyword and len(required) <= count <= len(required) + len(optional):
        return
    name = getattr(fn, "__name__", role)
    example = f"options.{keywords[0]}" if keywords else "options.<keyword>"
    raise ProcedureFormError(
        f"procedure {procedure!r}: its {role} {name}{inspect.signature(fn)} has the form hil no longer calls "
        + (
            f"(it takes {', '.join(by_keyword)} by keyword)"
            if by_keyword
            else f"({count} positional arguments)"
        )
        + f". Write it as `def {name}({', '.join(required)})`"
        + (f" (or with `{', '.join(optional)}` after them)" if optional else "")
        + f": the declared parameters and limits arrive as one options record, read as {example} "
        "(see docs/extending.md)"
    )
