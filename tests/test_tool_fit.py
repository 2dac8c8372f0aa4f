"""The tool fit's operator prompts: where on the flange each one asks for the SMR, drawn for the console."""

from __future__ import annotations

import tomllib
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from hil.runner.cell_config import parse_cell_config
from procedures.tool_fit import _seat, hole_points_flange
from tests.cell_fixtures import sim_cell_toml


def test_each_flange_prompt_draws_the_flange_with_its_place_marked():
    """The hole and face prompts carry a drawing of the flange (for the console) with the asked place marked
    where the fit expects it; the nest prompts (on the tool, not the flange) carry none."""
    config = parse_cell_config(tomllib.loads(sim_cell_toml()))
    points = hole_points_flange(config)
    for location in ("hole3", "hole7", "face"):
        svg = ET.fromstring(_seat(config, location).drawing_svg)
        circles = [c for c in svg.iter() if c.tag.endswith("circle") and "data-location" in c.attrib]
        (asked,) = [c for c in circles if c.get("class") == "asked"]
        assert asked.get("data-location") == location
        assert len([c for c in circles if c.get("class") == "hole"]) == 7 - (location != "face")
        if location != "face":  # on the screen +x runs right and +y up, about the drawing's centre
            x, y = float(asked.get("cx")) - 120, 120 - float(asked.get("cy"))
            expected = points[location][:2]
            assert np.degrees(np.arctan2(y, x)) == pytest.approx(
                np.degrees(np.arctan2(*expected[::-1])), abs=1
            )
    assert _seat(config, "nest1").drawing_svg is None
