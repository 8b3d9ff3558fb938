"""No import circles among humantele's modules (issue 22 §1), so the cuts stay cut; and
every import points down the layers of docs/architecture.md, "Packages and their layers"
(issue 33), read from the ``layers`` block there.

The imports are read from the sources with :mod:`ast` (nothing is imported). Every import
counts, wherever it is written:

- ``top``: at module level (class bodies and ``try``/``if`` blocks included), run at import;
- ``function``: inside a function or method (a deferred import: still a dependency, and a
  circle through it is only hidden until the function runs);
- ``typing``: under ``if TYPE_CHECKING:`` (a circle of types: the modules still know each
  other, which is what the cut is for).

Importing ``a.b.c`` also runs the package ``a.b``'s ``__init__``: an edge to the package is
added for each import of a submodule, so a circle through an ``__init__`` is found too.

``python tests/test_import_cycles.py`` prints the circles with each edge's kind and line.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "humantele"
ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


@dataclass(frozen=True)
class Edge:
    """``source`` imports ``target`` (both dotted module names) at ``line`` as ``kind``."""

    source: str
    target: str
    kind: str  # "top", "function" or "typing"
    line: int


def module_names(src: Path, package: str) -> dict[str, Path]:
    """Dotted name -> file of every module of ``package`` under ``src`` (a package is its
    ``__init__.py``)."""
    out = {}
    for path in sorted((src / package).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST) -> list[tuple[ast.Import | ast.ImportFrom, str]]:
    """Every import statement with its kind."""
    found: list[tuple[ast.Import | ast.ImportFrom, str]] = []

    def visit(node: ast.AST, kind: str) -> None:
        for child in ast.iter_child_nodes(node):
            k = kind
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                k = "function" if kind == "top" else kind
            if isinstance(child, ast.Import | ast.ImportFrom):
                found.append((child, k))
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for stmt in child.body:
                    visit_stmt(stmt, "typing")
                for stmt in child.orelse:
                    visit_stmt(stmt, k)
                continue
            visit(child, k)

    def visit_stmt(stmt: ast.stmt, kind: str) -> None:
        if isinstance(stmt, ast.Import | ast.ImportFrom):
            found.append((stmt, kind))
        visit(stmt, kind)

    visit(tree, "top")
    return found


def _known(name: str, modules: dict[str, Path]) -> str | None:
    """The longest prefix of ``name`` that is one of ``modules``."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def _with_packages(target: str, package: str) -> list[str]:
    """``target`` and the packages importing it runs (``a.b.c`` -> ``a.b.c``, ``a.b``)."""
    parts = target.split(".")
    out = [target]
    while len(parts) > 2:  # the top package's __init__ is left out: every module has it
        parts.pop()
        out.append(".".join(parts))
    return out if target.startswith(package) else []


def import_edges(src: Path = SRC, package: str = PACKAGE) -> list[Edge]:
    """Every import of one of ``package``'s modules by another, with its kind and line."""
    modules = module_names(src, package)
    edges: list[Edge] = []
    for name, path in modules.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node, kind in _imports(tree):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    anchor = name.split(".")
                    if not is_pkg:
                        anchor = anchor[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            for t in targets:
                known = _known(t, modules)
                if known is None:
                    continue
                for target in _with_packages(known, package):
                    if target != name and not name.startswith(target + "."):
                        edges.append(Edge(name, target, kind, node.lineno))
    return edges


def import_cycles(edges: list[Edge]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))

    def strong(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return sorted(out)


def describe(cycles: list[list[str]], edges: list[Edge]) -> str:
    """One block per circle: its modules and the imports that join them."""
    lines = []
    for comp in cycles:
        members = set(comp)
        lines.append(f"circle of {len(comp)}: {', '.join(comp)}")
        for e in sorted(set(edges), key=lambda e: (e.source, e.target, e.line)):
            if e.source in members and e.target in members:
                lines.append(f"  {e.source}:{e.line} -> {e.target} ({e.kind})")
    return "\n".join(lines) if lines else "no import circles"


@pytest.fixture(scope="module")
def edges() -> list[Edge]:
    """humantele's import edges, read once for the two checks of the real sources (1.7 CPU-s
    each)."""
    return import_edges()


def test_no_import_cycles(edges: list[Edge]) -> None:
    cycles = import_cycles(edges)
    assert not cycles, describe(cycles, edges)


def test_the_finder_finds_circles_of_each_kind(tmp_path: Path) -> None:
    """A package with one circle per kind (and one through a package's ``__init__``): each is
    found, and a package without circles has none."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "from pkg import b\n",
        "b.py": "import pkg.a\n",
        "c.py": "def f():\n    from pkg.d import x\n",
        "d.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import c\nx = 1\n",
        "e.py": "from pkg.sub.f import y\n",
        "sub/__init__.py": "from pkg import e\n",
        "sub/f.py": "y = 1\n",
        "g.py": "import os\nfrom pkg.sub import f\n",
    }
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    edges = import_edges(tmp_path, "pkg")
    kinds = {(e.source, e.target): e.kind for e in edges}
    assert kinds[("pkg.c", "pkg.d")] == "function"
    assert kinds[("pkg.d", "pkg.c")] == "typing"
    assert kinds[("pkg.a", "pkg.b")] == "top"
    assert import_cycles(edges) == [
        ["pkg.a", "pkg.b"],
        ["pkg.c", "pkg.d"],
        ["pkg.e", "pkg.sub"],  # pkg.sub.f's import runs pkg/sub/__init__.py
    ]
    for rel in ("b.py", "d.py", "sub/__init__.py"):
        (pkg / rel).write_text("")
    assert import_cycles(import_edges(tmp_path, "pkg")) == []


def read_layers(text: str) -> list[list[str]]:
    """The ``layers`` block of docs/architecture.md: its lines' packages, top line first
    (each line ``label: pkg pkg ...``)."""
    block = text.split("```layers\n", 1)[1].split("```", 1)[0]
    return [line.split(":", 1)[1].split() for line in block.splitlines() if line.strip()]


def package_of(module: str) -> str:
    """``humantele.media.sender`` -> ``media``; ``humantele.demo`` -> ``demo``."""
    return module.split(".")[1] if module.count(".") else module


def layer_violations(edges: list[Edge], layers: list[list[str]]) -> list[str]:
    """Imports between packages that do not point to a lower line of ``layers``."""
    level = {p: len(layers) - i for i, line in enumerate(layers) for p in line}
    out = []
    for e in sorted(set(edges), key=lambda e: (e.source, e.target, e.line)):
        a, b = package_of(e.source), package_of(e.target)
        if a == b or e.target == PACKAGE or e.source == PACKAGE:
            continue
        if level.get(a) is None or level.get(b) is None or level[b] >= level[a]:
            out.append(f"{e.source}:{e.line} -> {e.target} ({e.kind}): {a} -> {b}")
    return out


def test_imports_point_down_the_layers(edges: list[Edge]) -> None:
    """Every package is on one line of the layers, and imports only packages below it."""
    layers = read_layers(ARCHITECTURE.read_text(encoding="utf-8"))
    listed = [p for line in layers for p in line]
    assert len(listed) == len(set(listed)), "a package is on two lines of the layers"
    packages = {package_of(m) for m in module_names(SRC, PACKAGE) if m != PACKAGE}
    assert packages == set(listed), (
        f"not in the layers: {sorted(packages - set(listed))}; "
        f"no such package: {sorted(set(listed) - packages)}"
    )
    bad = layer_violations(edges, layers)
    assert not bad, "imports that point up or sideways:\n" + "\n".join(bad)


def test_the_layer_check_finds_an_upward_import() -> None:
    """An import of a package on a higher line, or on the same line, is reported; one of a
    lower line is not."""
    layers = [["top"], ["mid", "side"], ["low"]]
    edge = lambda a, b: Edge(f"humantele.{a}.x", f"humantele.{b}.y", "function", 1)  # noqa: E731
    assert layer_violations([edge("top", "mid"), edge("mid", "low")], layers) == []
    assert len(layer_violations([edge("low", "top")], layers)) == 1
    assert len(layer_violations([edge("mid", "side")], layers)) == 1


# What a module must not load, as the cuts left it: the video process's module (and its
# capture types) no aiortc, aiohttp or the sender; the console's hook not the daemon; the sim
# clinic (which the sensing child loads) not the sensing pipeline.
NOT_LOADED = {
    "humantele.media.process": ("aiortc", "aiohttp", "humantele.media.sender"),
    "humantele.media.capture": ("aiortc", "aiohttp"),
    "humantele.expert.console.hook": ("humantele.expert.daemon",),
    "humantele.follower.sim_clinic": ("humantele.follower.sensing",),
}


@pytest.mark.e2e  # runs a Python process per module (the fast lane leaves it out)
@pytest.mark.parametrize("module", sorted(NOT_LOADED))
def test_a_module_loads_only_what_it_needs(module: str) -> None:
    code = (
        f"import sys, {module}; "
        f"print(','.join(m for m in {NOT_LOADED[module]!r} if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "", f"{module} loads {out.stdout.strip()}"


if __name__ == "__main__":
    all_edges = import_edges()
    print(describe(import_cycles(all_edges), all_edges))
    bad = layer_violations(all_edges, read_layers(ARCHITECTURE.read_text(encoding="utf-8")))
    print("\n".join(bad) or "every import points down the layers")
