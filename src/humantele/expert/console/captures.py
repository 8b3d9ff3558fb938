"""Captured frames on disk: the JPEG the sonographer saw and a JSON side file with its pose,
and, when asked, a clip of the cine's last seconds (``....mp4``, H.264) beside them.

Files are named by the capture's wall-clock time (UTC) and frame number, never by anything
about the patient: ``capture-20261123T101500Z-000123.jpg``, ``....json`` and ``....mp4``. A
file that exists is never overwritten (a numbered suffix is added).

:class:`SessionItems` is the session's list of captures and measurements (calipers, notes)
that the console page shows, so the sonographer reviews them before the session ends.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

MAX_ITEMS = 500  # the list the page is sent keeps the newest


def save_capture(
    directory: Path, seq: int, jpeg: bytes, info: dict[str, Any], clip_frames: int = 0
) -> Path:
    """Write ``jpeg`` and ``info`` (JSON) into ``directory`` (made if needed); the JPEG's
    path. With ``clip_frames``, the JSON names the clip to come beside it (``clip``: file,
    frames). OSError when it cannot be written."""
    directory.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = f"capture-{stamp}-{seq:06d}"
    for n in range(1000):
        name = base if n == 0 else f"{base}-{n}"
        path = directory / f"{name}.jpg"
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            continue
        with os.fdopen(fd, "wb") as f:
            f.write(jpeg)
        if clip_frames:
            info = {**info, "clip": {"file": clip_path(path).name, "frames": clip_frames}}
        path.with_suffix(".json").write_text(json.dumps(info, indent=1), encoding="utf-8")
        return path
    raise OSError(f"no free capture file name for {base} in {directory}")


def clip_path(still: Path) -> Path:
    """Where the clip of a capture goes: beside its JPEG, ``.mp4``."""
    return still.with_suffix(".mp4")


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
