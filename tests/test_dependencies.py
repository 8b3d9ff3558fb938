"""The dependencies as declared (issue 22 item 5): every third-party module the package imports
comes from a distribution pyproject.toml declares, with bounds, and every declared one is
imported or says in pyproject why it stays."""

from __future__ import annotations

import ast
import functools
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src" / "humantele"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
# Declared and not imported, each with its reason in pyproject's comments.
NOT_IMPORTED = {"pyusb"}
# Imported and not declared: part of a declared one.
PART_OF = {
    "pydantic-core": "pydantic (pydantic pins its own core exactly)",
    "zstandard": "mcap (its compression; recording.writer falls back without it)",
    "pillow": "highdicom (it requires it; archive.objects takes its sRGB ICC profile)",
    "requests": "dicomweb-client (its HTTP session; archive.send gives it the TLS files)",
}


def _name(req: str) -> str:
    return re.split(r"[<>=!~;\[ ]", req, maxsplit=1)[0].lower().replace("_", "-")


def declared() -> dict[str, str]:
    return {_name(r): r for r in PYPROJECT["project"]["dependencies"]}


def imported_top_modules() -> set[str]:
    out: set[str] = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                out |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                out.add(node.module.split(".")[0])
    return {m for m in out if m not in sys.stdlib_module_names and m != "humantele"}


@functools.cache
def _packages() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


def distributions(module: str) -> set[str]:
    dists = _packages().get(module, [])
    return {d.lower().replace("_", "-") for d in dists}


@pytest.fixture(scope="module")
def imported_modules() -> set[str]:
    """:func:`imported_top_modules`, read once for the two tests that need it (1.5 CPU-s a
    read: every source file parsed)."""
    return imported_top_modules()


def test_every_imported_module_is_declared(imported_modules):
    deps = declared()
    undeclared = {
        m: sorted(distributions(m)) or "not installed"
        for m in sorted(imported_modules)
        if not distributions(m) & (set(deps) | set(PART_OF))
    }
    assert not undeclared, f"imported but not in [project.dependencies]: {undeclared}"


def test_every_declared_dependency_is_imported_or_says_why_not(imported_modules):
    imported = set()
    for m in imported_modules:
        imported |= distributions(m)
    unused = set(declared()) - imported
    assert unused == NOT_IMPORTED, unused
    text = (REPO / "pyproject.toml").read_text()
    for name in NOT_IMPORTED:
        assert re.search(rf"# {name}: .*stays", text), f"pyproject says nothing on {name}"


def test_every_dependency_has_both_bounds():
    for req in declared().values():
        assert ">=" in req and "<" in req.replace("<=", ""), f"{req}: give a lower and an upper"
    assert "<5" in declared()["opencv-contrib-python-headless"]
