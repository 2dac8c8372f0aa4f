"""Every module of hil/ has a place in the layers contract (pyproject.toml), so lint-imports checks it; and
no module of the project takes part in an import circle (lazy and type-checking imports included)."""

import re
import tomllib
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "drivers", "fakes", "procedures")


def layer_modules() -> set[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    layers = next(c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers")["layers"]
    return {name.strip("() ") for layer in layers for name in re.split(r"[:|]", layer)}


def import_circles(imports: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, or a module importing itself (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for imported in imports.get(module, ()):
            if imported not in index:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], index[imported])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == module:
                    break
            if len(component) > 1 or module in imports.get(module, ()):
                circles.append(sorted(component))

    for module in sorted(imports):
        if module not in index:
            visit(module)
    return circles


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


def test_the_circle_finder_finds_circles():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"a": {"a"}, "b": set()}) == [["a"]]
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_import_circle_anywhere():
    graph = grimp.build_graph(*PACKAGES, cache_dir=None)  # imports inside functions and TYPE_CHECKING count
    imports = {module: graph.find_modules_directly_imported_by(module) for module in graph.modules}
    assert {m.split(".")[0] for m in imports} == set(PACKAGES)
    circles = import_circles(imports)
    assert not circles, (
        f"import circles (break each, e.g. with a Protocol or by passing the object in): {circles}"
    )
