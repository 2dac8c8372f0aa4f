"""Every module of hil/ has a place in the layers contract (pyproject.toml), so lint-imports checks it."""

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def layer_modules() -> set[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    layers = next(c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers")["layers"]
    return {name.strip("() ") for layer in layers for name in re.split(r"[:|]", layer)}


def test_every_hil_module_is_placed_in_a_layer():
    placed = layer_modules()
    unplaced = []
    for path in sorted((ROOT / "hil").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if module != "hil" and not any(module == p or module.startswith(p + ".") for p in placed):
            unplaced.append(module)
    assert not unplaced, f"place {unplaced} in a layer of [tool.importlinter] in pyproject.toml"


def test_the_other_packages_are_layers_of_their_own():
    assert {"procedures", "fakes", "drivers"} <= layer_modules()
