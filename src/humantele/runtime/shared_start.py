"""One start time for several replays of one recording, each in its own process: the first
to be read claims it (``time.monotonic``, which every process of a machine shares) in a file,
the others take it from there, so the recorded devices run together from when the follower
first read any of them, however late it opens the others."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path


class BadStartFile(ValueError):
    """The start file holds no start time of this boot (garbled, or left by an earlier run)."""


def shared_start(path: str | Path, now: float | None = None) -> float:
    """The start in ``path`` (s, ``time.monotonic``); claimed as ``now`` (default: the
    clock) if nobody has yet. The claim is atomic: written to a file of its own, then linked
    to ``path`` (a link fails if ``path`` exists). A file that holds no time, or a time after
    now (another boot's clock), is a :class:`BadStartFile`, naming it: each run gives its
    replays a new one."""
    path = Path(path)
    start = time.monotonic() if now is None else now
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{time.monotonic_ns()}")
    tmp.write_text(repr(start))
    try:
        os.link(tmp, path)
        return start
    except FileExistsError:
        text = path.read_text(errors="replace")[:40]
        try:
            claimed = float(text)
        except ValueError:
            claimed = math.nan
        if not math.isfinite(claimed) or claimed > start + 1.0:
            raise BadStartFile(
                f"{path}: {text!r} is not a start time of this machine's clock now; "
                "give the replays a new start file (or delete this one)"
            ) from None
        return claimed
    finally:
        tmp.unlink(missing_ok=True)
