"""One start time for several replays of one recording, each in its own process: the first
to be read claims it (``time.monotonic``, which every process of a machine shares) in a file,
the others take it from there, so the recorded devices run together from when the follower
first read any of them, however late it opens the others."""

from __future__ import annotations

import os
import time
from pathlib import Path


def shared_start(path: str | Path, now: float | None = None) -> float:
    """The start in ``path`` (s, ``time.monotonic``); claimed as ``now`` (default: the
    clock) if nobody has yet. The claim is atomic: written to a file of its own, then linked
    to ``path`` (a link fails if ``path`` exists)."""
    path = Path(path)
    start = time.monotonic() if now is None else now
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{time.monotonic_ns()}")
    tmp.write_text(repr(start))
    try:
        os.link(tmp, path)
        return start
    except FileExistsError:
        return float(path.read_text())
    finally:
        tmp.unlink(missing_ok=True)
