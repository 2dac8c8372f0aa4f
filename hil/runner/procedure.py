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
from dataclasses import dataclass, field
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

    `plan(config, **parameters)` is a pure function of the cell config and the parameters (SI; it takes
    the subset it names); `body(session, **parameters, **limits)` runs it and returns its result;
    `summary(result)` is the paragraph printed after a run; `steps` names the campaign steps it records.
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
    _names: frozenset[str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_names", frozenset(p.keyword for p in self.parameters))
        limits = {limit.name for limit in self.limits}
        for m in self.measurements:
            if m.limit is not None and m.limit not in limits:
                raise ValueError(
                    f"{self.name}: measurement {m.name} names limit {m.limit!r}, which is not declared "
                    f"(declared: {', '.join(sorted(limits)) or 'none'})"
                )

    def step_for(self, role: Role) -> str | None:
        """The step of this procedure that plays `role`, None when it publishes none."""
        return next((step for r, step in self.publishes if r is role), None)

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

    def make_plan(self, config: CellConfig, campaign: Any = None, **values: Any) -> Plan:
        """The plan for these parameters (SI keywords; defaults filled in and checked). A plan that depends
        on what a campaign holds names a `campaign` keyword and gets the campaign's path (to read only)."""
        resolved = self.resolve(values)
        accepted = inspect.signature(self.plan).parameters
        if "campaign" in accepted:
            resolved["campaign"] = campaign
        return self.plan(config, **{k: v for k, v in resolved.items() if k in accepted})

    def __call__(self, session: Any, **values: Any) -> Any:
        """Run the procedure on a Session with these parameters (SI keywords; defaults filled in and checked);
        its engine judges the declared measurements the body reports (`session.engine.measured`)."""
        resolved = self.resolve(values)
        limits = {limit.name: limit.to_si() for limit in self.limits}
        with session.engine.judging(self.name, self.measurements, limits):
            return self.body(session, **resolved, **self.limit_values())

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
