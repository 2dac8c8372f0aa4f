"""The registered procedures: found through the `hil.procedures` entry-point group, loaded only when asked.

A package (this one's `procedures/`, or a shop floor's own) registers a procedure by naming its declaration
in its metadata, e.g. in pyproject.toml:

    [project.entry-points."hil.procedures"]
    registration = "procedures.registration:PROCEDURE"

Listing the names reads installed metadata only; `load(name)` imports the one module that declares it.
"""

from __future__ import annotations

import logging
from functools import cache
from importlib.metadata import EntryPoint, entry_points

from hil.runner.procedure import Procedure, Role

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


class RoleNotPublishedError(LookupError):
    """No registered procedure publishes a step in this role (or two do)."""


@cache
def _publishers() -> dict[Role, list[tuple[str, str]]]:
    """Every role the registered procedures publish: (procedure, step) by role (each declaration loaded once;
    one that cannot be loaded is left out with a warning, so a broken plug-in hides no other)."""
    found: dict[Role, list[tuple[str, str]]] = {}
    for name in registered():
        try:
            declared = load(name)
        except Exception as exc:  # noqa: BLE001 - a broken plug-in must not hide the others
            logging.getLogger("hil").warning("procedure %s cannot be loaded: %s", name, exc)
            continue
        for role, step in declared.publishes:
            found.setdefault(role, []).append((name, step))
    return found


def publisher(role: Role) -> tuple[str, str]:
    """(procedure, step) of the one registered procedure that publishes `role`."""
    found = _publishers().get(role, [])
    if len(found) != 1:
        named = ", ".join(f"{p}/{s}" for p, s in found) or "none"
        raise RoleNotPublishedError(
            f"exactly one registered procedure must publish the {role.value} step; found {named}"
        )
    return found[0]
