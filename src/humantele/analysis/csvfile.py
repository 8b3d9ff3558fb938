"""The researchers' CSV files (scores, questionnaires): rows with their place, checked cells.

Errors are :class:`humantele.config.ConfigError` naming the file, the row and the column.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from pathlib import Path

from humantele.config import ConfigError


def csv_rows(
    path: str | Path, what: str
) -> tuple[list[str], Iterator[tuple[int, str, dict[str, str]]]]:
    """The stripped header and the rows as ``(row number, "path: row N", row)``.

    ``what`` names the contents in the error for an unreadable file ("scores", "responses").
    A row with more cells than the header is a ConfigError.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror or exc}") from exc
    reader = csv.DictReader(text.splitlines())
    header = [h.strip() for h in reader.fieldnames or []]
    reader.fieldnames = header

    def rows() -> Iterator[tuple[int, str, dict[str, str]]]:
        for row_no, row in enumerate(reader, start=2):
            where = f"{path}: row {row_no}"
            if None in row:
                raise ConfigError(f"{where}: more cells than header columns")
            yield row_no, where, row

    return header, rows()


def number_cell(
    value: str | None, where: str, column: str, lo: float, hi: float, integer: bool
) -> float:
    """The cell as a finite number in [lo, hi] (a whole number if ``integer``)."""
    text = (value or "").strip()
    try:
        number = float(text)
    except ValueError:
        raise ConfigError(f"{where}: column {column!r}: {text!r} is not a number") from None
    if not math.isfinite(number) or not lo <= number <= hi or (integer and number != int(number)):
        kind = "an integer" if integer else "a number"
        bounds = "-".join(f"{b:g}" if isinstance(b, float) else str(b) for b in (lo, hi))
        raise ConfigError(f"{where}: column {column!r}: {text!r} is not {kind} {bounds}")
    return number
