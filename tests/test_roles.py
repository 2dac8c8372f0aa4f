"""Plug-ins are named through the registry: a procedure publishes which of its steps plays which role, and
the core reads the registration, the tool and the grid through those roles, never by a plug-in's name."""

from __future__ import annotations

import pytest

from hil.runner.procedure import Limit, Measurement, Procedure, Role
from hil.runner.registry import load, publisher


def test_each_role_the_core_reads_is_published_by_one_registered_procedure():
    assert publisher(Role.REGISTRATION) == ("registration", "fit")
    assert publisher(Role.TOOL) == ("tool_fit", "fit")
    assert publisher(Role.GRID) == ("grid_sampling", "grid")
    assert publisher(Role.VALIDATION) == ("grid_sampling", "validation")
    for role in Role:  # a published step is one the procedure declares it records
        procedure, step = publisher(role)
        assert step in load(procedure).steps, (role, procedure, step)


def test_a_measurement_naming_an_undeclared_limit_is_refused_when_declared():
    with pytest.raises(ValueError, match="names limit 'max_gap', which is not declared .*max_error"):
        Procedure(
            name="p", purpose="", instruction="", parameters=(), plan=lambda config, options: None, body=lambda session, options: None,
            limits=(Limit("max_error", "error", 1.0, "mm"),),
            measurements=(Measurement("gap", "gap", "mm", "max_gap"),),
        )  # fmt: skip
