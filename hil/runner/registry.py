"""The registered procedures: found through the `hil.procedures` entry-point group, loaded only when asked.

A package (this one's `procedures/`, or a shop floor's own) registers a procedure by naming its declaration
in its metadata, e.g. in pyproject.toml:

    [project.entry-points."hil.procedures"]
    registration = "procedures.registration:PROCEDURE"

Listing the names reads installed metadata only; `load(name)` imports the one module that declares it.
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points

from hil.runner.procedure import Procedure

GROUP = "hil.procedures"


class UnknownProcedureError(LookupError):
    """No procedure of that name is registered (or its entry point does not name a Procedure)."""


def registered() -> dict[str, EntryPoint]:
    """Every registered procedure's entry point by name (nothing imported), sorted by name."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=GROUP):
        found.setdefault(ep.name, ep)  # the first on the path wins, as for any installed distribution
    return dict(sorted(found.items()))


def load(name: str) -> Procedure:
    """The declaration of the procedure registered as `name`."""
    available = registered()
    if name not in available:
        known = ", ".join(available) or "none (is hil installed? pip install -e .)"
        raise UnknownProcedureError(f"no procedure {name!r} is registered; registered: {known}")
    declared = available[name].load()
    if not isinstance(declared, Procedure) or declared.name != name:
        raise UnknownProcedureError(
            f"the entry point {name} = {available[name].value} does not name the Procedure declaration {name!r}"
        )
    return declared
