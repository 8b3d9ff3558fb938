"""Markdown reports: tables, and named sections of a file (``docs/benchmarks.md``).

Used by the benchmarks and the analysis. Each benchmark owns the text between
``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``; rerunning one benchmark replaces only
its own section, so the file keeps every other figure.
"""

from __future__ import annotations

import os
import platform
import re
import time
from pathlib import Path

DOCS_DIR = Path(__file__).resolve().parents[2] / "docs"
BENCHMARKS_MD = DOCS_DIR / "benchmarks.md"

_HEADER = """# Benchmarks

Written by `humantele bench ...`; each section is replaced when its benchmark is rerun.
Figures are medians and ratios measured in one run on the machine named in the section.
"""


def machine_line() -> str:
    """A short description of where and when the figures were measured."""
    return (
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on "
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}."
    )


def write_section(name: str, markdown: str, path: Path | None = None) -> Path:
    """Replace (or append) benchmark ``name``'s section in docs/benchmarks.md; returns the path."""
    path = Path(path) if path is not None else BENCHMARKS_MD
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text(encoding="utf-8") if path.exists() else _HEADER
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{begin}\n{markdown.strip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(text):
        text = pattern.sub(lambda _m: block, text)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """A GitHub markdown table; floats are printed as given (format them before)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def section_rows(name: str, width: int, path: Path | None = None) -> list[list[str]]:
    """The body rows (cells stripped) of the tables with ``width`` columns in benchmark
    ``name``'s section of ``path`` (docs/benchmarks.md): what a benchmark keeps of its earlier
    runs when it rewrites its section. Header rows (the line above a ``|---|`` rule) are not
    rows; a missing file or section gives none."""
    path = Path(path) if path is not None else BENCHMARKS_MD
    try:
        text = path.read_text(encoding="utf-8")
    except OSError:
        return []
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    if begin not in text:
        return []
    rows: list[list[str]] = []
    previous: list[str] | None = None
    for line in text.split(begin, 1)[1].split(end, 1)[0].splitlines():
        line = line.strip()
        if not line.startswith("|"):
            previous = None
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if all(c and set(c) <= set("-:") for c in cells):  # the rule under a header
            if rows and rows[-1] is previous:
                rows.pop()
        elif len(cells) == width:
            rows.append(cells)
        previous = cells
    return rows
