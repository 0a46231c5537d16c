"""The import graph between streamdet's packages, computed from the source with ``ast``.

Every ``import`` counts: top-level ones, those inside functions (lazy), relative ones and
``importlib.import_module("...")`` / ``__import__("...")`` with a constant name. The graph must have no cycle, the
vehicle-side packages must never reach PyTorch or the training side, nothing may import ``benchmarks`` or the tests,
and the package table of docs/architecture.md must name exactly each package's streamdet imports.

``python tests/test_import_graph.py`` prints the graph (edges with where they come from, and the table column).
"""

from __future__ import annotations

import ast
import re
import sys
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS_TABLE = ROOT / "docs" / "architecture.md"

# The packages the layering is about (folders at the repository root, imported as streamdet.<name>).
LAYERED = ("calibration", "core", "data", "runtime_ort", "evaluation", "models", "training", "export", "benchmarks")
# A vehicle process imports these without PyTorch; they reach none of FORBIDDEN_FROM_VEHICLE, even transitively.
TORCH_FREE = ("calibration", "core", "runtime_ort", "evaluation", "data")
FORBIDDEN_FROM_VEHICLE = ("torch", "torchvision", "onnxscript", "onnxconverter_common", "models", "export", "training", "benchmarks")
NOT_IMPORTABLE = ("benchmarks", "tests", "conftest")  # entry points and test code: nothing imports them
ROOT_PACKAGE = "streamdet"  # the root package itself (toplevel/: cli_utils): a package of the graph like the others


@dataclass(frozen=True)
class Edge:
    source: str  # importing package
    target: str  # imported package (streamdet.<name>) or top-level external module
    where: str  # file:line


def package_dirs() -> dict[str, list[Path]]:
    """Top-level streamdet package (the name after ``streamdet.``; ``streamdet`` for the root) -> its folders.

    From pyproject.toml's package-dir; a sub-package (``streamdet.runtime_ort.ros``) belongs to its top package.
    """
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    dirs: dict[str, list[Path]] = {}
    for name, folder in sorted(cfg["tool"]["setuptools"]["package-dir"].items()):
        parts = name.split(".")
        top = parts[1] if len(parts) > 1 else ROOT_PACKAGE
        dirs.setdefault(top, []).append(ROOT / folder)
    return dirs


def _sources(package: str, folders: list[Path]) -> Iterator[tuple[Path, str, bool]]:
    """(file, dotted module name, is a package __init__) of every source of a package, sub-packages included."""
    seen: set[Path] = set()
    base = [ROOT_PACKAGE] if package == ROOT_PACKAGE else [ROOT_PACKAGE, package]
    top = folders[0]
    for folder in folders:
        # the root package's folder holds only its own modules; the others are scanned with their sub-packages
        paths = folder.glob("*.py") if package == ROOT_PACKAGE else folder.rglob("*.py")
        for path in sorted(paths):
            if path in seen:
                continue
            seen.add(path)
            parts = list(path.relative_to(top if path.is_relative_to(top) else folder).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            yield path, ".".join(base + parts), is_package


def imported_modules(source: str, module: str, is_package: bool) -> Iterator[tuple[str, int]]:
    """(absolute dotted name, line) of every import in a module's source, nested and dynamic ones included."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                yield node.module or "", node.lineno
                continue
            base = module.split(".") if is_package else module.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            if node.module:
                yield ".".join(base + [node.module]), node.lineno
            else:  # from . import x: x is a module of the package (or a name in it: the package counts either way)
                for alias in node.names:
                    yield ".".join(base + [alias.name]), node.lineno
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                yield node.args[0].value, node.lineno


def _target(dotted: str, packages: set[str]) -> str:
    parts = dotted.split(".")
    if parts[0] == ROOT_PACKAGE:
        return parts[1] if len(parts) > 1 and parts[1] in packages else ROOT_PACKAGE
    return parts[0]


def import_edges() -> list[Edge]:
    """Every import that crosses a package boundary (to another streamdet package or outside streamdet)."""
    dirs = package_dirs()
    names = set(dirs)
    edges = []
    for package, folders in sorted(dirs.items()):
        for path, module, is_package in _sources(package, folders):
            for dotted, line in imported_modules(path.read_text(), module, is_package):
                target = _target(dotted, names)
                if target != package:
                    edges.append(Edge(package, target, f"{path.relative_to(ROOT)}:{line}"))
    return edges


def package_graph(edges: list[Edge]) -> dict[str, set[str]]:
    """Package -> the streamdet packages it imports directly."""
    names = set(package_dirs())
    graph: dict[str, set[str]] = {n: set() for n in names}
    for e in edges:
        if e.target in names:
            graph[e.source].add(e.target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one package (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Packages ``start`` imports directly or through others (itself excluded)."""
    seen: set[str] = set()
    todo = list(graph[start])
    while todo:
        p = todo.pop()
        if p not in seen:
            seen.add(p)
            todo.extend(graph[p])
    seen.discard(start)
    return seen


def docs_table() -> dict[str, set[str]]:
    """docs/architecture.md's package table: folder -> the streamdet packages its "imports" column names."""
    rows: dict[str, set[str]] = {}
    header: list[str] | None = None
    for line in DOCS_TABLE.read_text().splitlines():
        if not line.startswith("|"):
            header = None if rows else header
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            if "folder" in cells and "imports (streamdet)" in cells:
                header = cells
            continue
        if set(cells[0]) <= set("-: "):
            continue
        # keyed by the package's name in the graph (the root's folder is not named streamdet: pyproject.toml)
        package = cells[header.index("import")].strip("` ")
        folder = ROOT_PACKAGE if package == ROOT_PACKAGE else package.removeprefix(ROOT_PACKAGE + ".")
        named = cells[header.index("imports (streamdet)")]
        rows[folder] = set(re.findall(r"`([a-z_]+)`", named))
    return rows


@pytest.fixture(scope="module")
def edges() -> list[Edge]:
    """The scan of every source, once for the tests below (they only read it)."""
    return import_edges()


def test_packages_form_no_cycle(edges):
    graph = package_graph(edges)
    found = cycles(graph)
    assert not found, f"import cycles between packages: {found}; edges: {_edges_among(edges, found)}"


def _edges_among(edges: list[Edge], components: list[list[str]]) -> list[str]:
    inside = [set(c) for c in components]
    return [f"{e.source} -> {e.target} ({e.where})" for e in edges if any({e.source, e.target} <= c for c in inside)]


def test_vehicle_side_never_reaches_torch_or_the_training_side(edges):
    graph = package_graph(edges)
    for package in TORCH_FREE:
        closure = {package} | reachable(graph, package)
        bad = [f"{e.source} -> {e.target} ({e.where})" for e in edges if e.source in closure and e.target in FORBIDDEN_FROM_VEHICLE]
        assert not bad, f"{package} reaches {sorted({b.split()[2] for b in bad})} through {closure - {package} or 'nothing'}: {bad}"


def test_nothing_imports_benchmarks_or_tests(edges):
    bad = [f"{e.source} -> {e.target} ({e.where})" for e in edges if e.target in NOT_IMPORTABLE]
    assert not bad, bad


def test_every_layered_package_is_scanned():
    dirs = package_dirs()
    assert set(LAYERED) <= set(dirs), sorted(set(LAYERED) - set(dirs))
    for name in LAYERED:
        assert len(list(_sources(name, dirs[name]))) >= 2, f"{name}/ holds no sources: the scan would see nothing"


def test_docs_table_matches_the_graph(edges):
    graph = package_graph(edges)
    table = docs_table()
    missing = sorted(set(LAYERED) - set(table))
    assert not missing, f"{DOCS_TABLE.name}'s package table has no row for {missing}"
    for folder, named in table.items():
        assert folder in graph, f"{DOCS_TABLE.name} names a package {folder!r} that pyproject.toml does not map"
        have = graph[folder] - {ROOT_PACKAGE}
        assert named == have, (
            f"{DOCS_TABLE.name}: `{folder}/` imports {sorted(have)} but its row names {sorted(named)} "
            f"(`python tests/test_import_graph.py` prints the graph)"
        )


# ---- the scanner itself, on sources written here -----------------------------------------------------------


def test_scanner_sees_lazy_relative_and_dynamic_imports():
    source = (
        "import numpy\n"
        "from streamdet.core.boxes import BOX_DIM\n"
        "def f():\n"
        "    import torch\n"
        "    from ..models import heads\n"
        "    from . import sibling\n"
        "    return importlib.import_module('streamdet.training.cli'), __import__('torchvision')\n"
    )
    got = sorted(imported_modules(source, "streamdet.evaluation.studies", False))
    assert got == [
        ("numpy", 1),
        ("streamdet.core.boxes", 2),
        ("streamdet.evaluation.sibling", 6),
        ("streamdet.models", 5),
        ("streamdet.training.cli", 7),
        ("torch", 4),
        ("torchvision", 7),
    ]
    # in a package's __init__, "." is the package itself
    assert list(imported_modules("from .x import y\n", "streamdet.data", True)) == [("streamdet.data.x", 1)]


def test_cycle_finder_and_reachability():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert reachable(graph, "d") == {"a", "b", "c"}
    assert cycles({"a": {"b"}, "b": set()}) == []


def main() -> None:
    edges = import_edges()
    graph = package_graph(edges)
    by_pair: dict[tuple[str, str], list[str]] = {}
    for e in edges:
        if e.target in graph:
            by_pair.setdefault((e.source, e.target), []).append(e.where)
    for (a, b), where in sorted(by_pair.items()):
        print(f"{a} -> {b}  ({len(where)}: {', '.join(where[:4])}{' ...' if len(where) > 4 else ''})")
    print("cycles:", cycles(graph) or "none")
    print("\nthe docs table's 'imports (streamdet)' column:")
    for name in sorted(graph):
        if name != ROOT_PACKAGE:
            print(f"`{name}/`: " + (", ".join(f"`{p}`" for p in sorted(graph[name] - {ROOT_PACKAGE})) or "none"))


if __name__ == "__main__":
    sys.exit(main())
