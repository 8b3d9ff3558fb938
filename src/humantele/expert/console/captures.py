"""Captured frames on disk: the JPEG the sonographer saw and a JSON side file with its pose.

Files are named by the capture's wall-clock time (UTC) and frame number, never by anything
about the patient: ``capture-20261123T101500Z-000123.jpg`` and ``....json``. A file that
exists is never overwritten (a numbered suffix is added).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any


def save_capture(directory: Path, seq: int, jpeg: bytes, info: dict[str, Any]) -> Path:
    """Write ``jpeg`` and ``info`` (JSON) into ``directory`` (made if needed); the JPEG's
    path. OSError when it cannot be written."""
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
        path.with_suffix(".json").write_text(json.dumps(info, indent=1), encoding="utf-8")
        return path
    raise OSError(f"no free capture file name for {base} in {directory}")
