"""The tree reads as the pipeline: imports go one way, and no tool can miss one.

Layers, from the foundation up (``docs/ARCHITECTURE.md``); a module imports only from its own
layer and those below it:

    scanner.core < scanner.formats < scanner.stripe < calibration < scanner.scanning
    < scanner.virtual_cell < metrology < scanner.app

Every import statement counts, at module level or inside a function, and so does a string
naming one of our modules (``importlib.import_module("metrology.x")``, ``"pkg.mod:attr"``):
none may hide an import from this test. No module imports itself back through others.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("scanner", "calibration", "metrology")

#: Module prefixes, lowest layer first. ``scanner`` alone (its ``__init__``: the version) is
#: the foundation too.
LAYERS = (
    ("scanner", "scanner.core"),
    ("scanner.formats",),
    ("scanner.stripe",),
    ("calibration",),
    ("scanner.scanning",),
    ("scanner.virtual_cell",),
    ("metrology",),
    ("scanner.app", "scanner.__main__"),
)

_MODULE_STRING = re.compile(r"^(scanner|calibration|metrology)(\.[A-Za-z_]\w*)+(:\w+)?$")


def layer_of(module: str) -> int:
    """The layer index of a dotted module name (the longest matching prefix wins)."""
    best, best_len = -1, -1
    for index, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            matches = module == prefix or module.startswith(prefix + ".")
            exact_root = prefix == "scanner" and module != "scanner"
            if matches and not exact_root and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    if best < 0:
        raise ValueError(f"expected a module of {ROOTS}, got {module!r}")
    return best


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def our_modules() -> dict[str, Path]:
    return {
        module_name(p): p
        for root in ROOTS
        for p in sorted((REPO / root).rglob("*.py"))
        if "__pycache__" not in p.parts
    }


def _exists(module: str) -> bool:
    """Whether a dotted name is one of our modules or packages (not ``calibration.json``)."""
    base = REPO.joinpath(*module.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imports_of(path: Path) -> list[tuple[str, int, str]]:
    """``(imported module, line, how)`` for every import of our packages in ``path``.

    ``how`` is ``"module"``, ``"function"`` (inside a def) or ``"string"``.
    """
    tree = ast.parse(path.read_text(encoding="utf-8"))
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            inside |= {id(n) for n in ast.walk(node) if n is not node}
    found: list[tuple[str, int, str]] = []
    for node in ast.walk(tree):
        how = "function" if id(node) in inside else "module"
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                names = [".".join(base + ([node.module] if node.module else []))]
            elif node.module:
                names = [node.module]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if _MODULE_STRING.match(node.value) and _exists(node.value.split(":")[0]):
                names, how = [node.value.split(":")[0]], "string"
        found += [(n, node.lineno, how) for n in names if n.split(".")[0] in ROOTS]
    return found


def test_imports_go_down_the_layers_only():
    wrong = []
    for module, path in our_modules().items():
        for imported, line, how in imports_of(path):
            if layer_of(imported) > layer_of(module):
                wrong.append(
                    f"{path.relative_to(REPO)}:{line}: {module} imports {imported} ({how})"
                )
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def test_no_import_of_our_modules_is_hidden():
    hidden = [
        f"{path.relative_to(REPO)}:{line}: {imported} ({how})"
        for path in our_modules().values()
        for imported, line, how in imports_of(path)
        if how != "module"
    ]
    assert not hidden, "imports inside functions or by name:\n" + "\n".join(hidden)


def test_no_import_circle():
    modules = our_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        for imported, _, _ in imports_of(path):
            # "from pkg import mod" names a module or an attribute: resolve to what exists.
            while imported not in modules and "." in imported:
                imported = imported.rpartition(".")[0]
            if imported in modules and imported != module:
                graph[module].add(imported)
    # A package's __init__ importing its own sub-modules is how Python packages work.
    for module in graph:
        graph[module] = {i for i in graph[module] if not module.startswith(i + ".")}
    cycles = _strongly_connected(graph)
    assert not cycles, "import circles: " + "; ".join(" -> ".join(sorted(c)) for c in cycles)


def _strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's components with more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[set[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in graph:
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize(
    ("module", "imported", "allowed"),
    [
        ("scanner.core.camera", "scanner.formats.session", False),
        ("scanner.formats.session", "scanner.core.targets", True),
        ("calibration.pipeline", "scanner.stripe.extract", True),
        ("scanner.scanning.pipeline", "metrology.measure", False),
        ("metrology.ef_check", "calibration.extrinsics", True),
        ("scanner.virtual_cell.simulate", "scanner.app.stages", False),
        ("scanner", "scanner.core.fileio", True),
    ],
)
def test_the_layer_rule_itself(module, imported, allowed):
    # The checker would pass vacuously if layer_of ranked everything alike.
    assert (layer_of(imported) <= layer_of(module)) is allowed


def test_modules_stay_under_800_lines():
    long = {
        str(p.relative_to(REPO)): n
        for p in our_modules().values()
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > 800
    }
    assert not long, f"modules over 800 lines: {long}"
