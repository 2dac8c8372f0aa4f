"""Every module of hil/ has a place in the layers contract (pyproject.toml), so lint-imports checks it; no
module of the project takes part in an import circle (lazy and type-checking imports included); and no
function is longer than MAX_FUNCTION_LINES or takes more than MAX_PARAMETERS (an options record instead)."""

import ast
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "drivers", "fakes", "procedures")
MAX_FUNCTION_LINES = 100  # from `def` to the last line, docstring included
MAX_PARAMETERS = 10  # self and cls not counted; *args and **kwargs count one each


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
    import grimp  # the import-linter's graph builder, only where it is used

    graph = grimp.build_graph(*PACKAGES, cache_dir=None)  # imports inside functions and TYPE_CHECKING count
    imports = {module: graph.find_modules_directly_imported_by(module) for module in graph.modules}
    assert {m.split(".")[0] for m in imports} == set(PACKAGES)
    circles = import_circles(imports)
    assert not circles, (
        f"import circles (break each, e.g. with a Protocol or by passing the object in): {circles}"
    )


def oversized_functions(source: str) -> dict[str, tuple[int, int]]:
    """Functions (qualified by class) longer than MAX_FUNCTION_LINES or with more than MAX_PARAMETERS:
    name -> (lines, parameters)."""
    found: dict[str, tuple[int, int]] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                a = child.args
                names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg) if x]
                params = len([n for n in names if n not in ("self", "cls")])
                lines = (child.end_lineno or child.lineno) - child.lineno + 1
                if lines > MAX_FUNCTION_LINES or params > MAX_PARAMETERS:
                    found[prefix + child.name] = (lines, params)
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")

    visit(ast.parse(source), "")
    return found


def test_the_size_check_finds_long_functions_and_long_signatures():
    long_body = "def long():\n" + "    x = 1\n" * MAX_FUNCTION_LINES
    many = ", ".join(f"p{i}" for i in range(MAX_PARAMETERS + 1))
    source = f"{long_body}\nclass C:\n    def wide(self, {many}):\n        pass\n    def fine(self, *a, **k):\n        pass\n"
    assert oversized_functions(source) == {
        "long": (MAX_FUNCTION_LINES + 1, 0),
        "C.wide": (2, MAX_PARAMETERS + 1),
    }
    at_limit = ", ".join(f"p{i}" for i in range(MAX_PARAMETERS))
    assert oversized_functions(f"def f(self, {at_limit}):\n    pass\n") == {}


def test_no_function_too_long_or_with_too_many_parameters():
    oversized = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for name, size in oversized_functions(path.read_text()).items():
                oversized[f"{rel}:{name}"] = size
    assert not oversized, (
        f"functions over {MAX_FUNCTION_LINES} lines or {MAX_PARAMETERS} parameters, (lines, parameters): "
        f"{oversized}; split them by what each part does, or pass an options record"
    )
