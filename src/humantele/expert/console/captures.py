"""Captured frames on disk: the JPEG the sonographer saw and a JSON side file with its pose,
and, when asked, a clip of the cine's last seconds (``....mp4``, H.264) beside them.

Files are named by the capture's wall-clock time (UTC) and frame number, never by anything
about the patient: ``capture-20261123T101500Z-000123.jpg``, ``....json`` and ``....mp4``. A
file that exists is never overwritten (a numbered suffix is added). Each is written whole or
not at all (:mod:`humantele.runtime.files`): a capture is its JPEG and its JSON, or nothing;
the JSON names the clip only once the clip is there whole (:func:`name_clip`). On a full disk
a capture leaves no file, and :class:`FailureLog` says it once, not once a capture.

:class:`SessionItems` is the session's list of captures and measurements (calipers, notes)
that the console page shows, so the sonographer reviews them before the session ends.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from humantele.runtime.files import replace_whole, write_new

MAX_ITEMS = 500  # the list the page is sent keeps the newest


def save_capture(directory: Path, seq: int, jpeg: bytes, info: dict[str, Any]) -> Path:
    """Write ``jpeg`` and ``info`` (its JSON side file) into ``directory`` (made if needed),
    both whole or neither; the JPEG's path. OSError when they cannot be written (nothing
    left)."""
    directory.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = f"capture-{stamp}-{seq:06d}"
    side = json.dumps(info, indent=1).encode()
    for n in range(1000):
        name = base if n == 0 else f"{base}-{n}"
        path = directory / f"{name}.jpg"
        if path.with_suffix(".json").exists():
            continue
        try:
            write_new(path, jpeg)
        except FileExistsError:
            continue
        try:
            write_new(path.with_suffix(".json"), side)
        except OSError:
            with contextlib.suppress(OSError):
                path.unlink()
            raise
        return path
    raise OSError(f"no free capture file name for {base} in {directory}")


def name_clip(still: Path, clip: Any) -> Any:
    """Name the clip written whole beside ``still`` in the still's JSON (``clip``: file,
    frames), replaced in one step; ``clip`` (an export.clip.ClipInfo) returned. OSError when
    it cannot be (the clip removed: a capture's files are whole and named, or not there)."""
    side = still.with_suffix(".json")
    try:
        info = json.loads(side.read_text(encoding="utf-8"))
        info["clip"] = {"file": clip.path.name, "frames": clip.frames}
        replace_whole(side, json.dumps(info, indent=1).encode())
    except (OSError, ValueError) as exc:
        with contextlib.suppress(OSError):
            clip.path.unlink()
        raise OSError(f"clip not named in {side.name}: {exc}") from exc
    return clip


def clip_path(still: Path) -> Path:
    """Where the clip of a capture goes: beside its JPEG, ``.mp4``."""
    return still.with_suffix(".mp4")


class FailureLog:
    """Says a run of failures (captures or clips not saved: a full disk) once: the first at
    ERROR, the ones after it at DEBUG, and at INFO when one succeeds again, with the count.
    ``failed`` counts them all (the stats have them)."""

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self.log = logger
        self.what = what
        self.failed = 0
        self._in_a_row = 0

    def failure(self, detail: object) -> None:
        self.failed += 1
        self._in_a_row += 1
        if self._in_a_row == 1:
            self.log.error("console: %s not saved: %s (said once until one is saved again)",
                           self.what, detail)  # fmt: skip
        else:
            self.log.debug("console: %s not saved: %s", self.what, detail)

    def success(self) -> None:
        if self._in_a_row > 1:
            self.log.info("console: %s saved again after %d not saved", self.what,
                          self._in_a_row)  # fmt: skip
        self._in_a_row = 0


class SessionItems:
    """The session's captures and measurements, newest last: dicts with ``n`` (1, 2, ...),
    ``kind`` (``capture``, ``caliper``, ``note``), ``seq`` and ``t_capture`` (s, the expert's
    clock) of the frame, and the kind's fields (``file``, ``clip``; ``mm``; ``text``)."""

    def __init__(self, max_items: int = MAX_ITEMS) -> None:
        self.max_items = max_items
        self._items: list[dict[str, Any]] = []
        self._n = 0

    def add(self, kind: str, seq: int, t_capture: float, **fields: Any) -> dict[str, Any]:
        """A new item (returned: a clip written later is added to it in place)."""
        self._n += 1
        item = {"n": self._n, "kind": kind, "seq": seq, "t_capture": t_capture, **fields}
        self._items.append(item)
        del self._items[: -self.max_items]
        return item

    def list(self) -> list[dict[str, Any]]:
        return [dict(i) for i in self._items]

    def clip_names(self) -> set[str]:
        return {i["clip"] for i in self._items if i.get("clip")}
