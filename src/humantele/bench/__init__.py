"""Benchmarks: `humantele bench NAME`; each module has add_arguments(parser) and run(args)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from humantele.report import write_section


def publish(
    section: str,
    md: str,
    summary: object,
    args: argparse.Namespace,
    path: Path | None = None,
    always_json: bool = False,
) -> None:
    """A bench's ending: write ``md`` as benchmark ``section``'s part of ``path``
    (docs/benchmarks.md) unless ``--no-write``, saying where unless ``--json``; then print
    ``summary`` as one JSON line, last, with ``--json`` (``always_json``: whatever the flags)."""
    as_json = getattr(args, "json", False)
    if not args.no_write:
        where = write_section(section, md, path)
        if not as_json:
            print(f"wrote {where}")
    if as_json or always_json:
        print(json.dumps(summary, default=str))


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (files only, no display); imported when a bench
    draws its chart, not when the command line is built."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_chart(fig: Any, path: Path) -> Path:
    """Write ``fig`` to ``path`` (its folder made), close it; returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    pyplot().close(fig)
    return path
