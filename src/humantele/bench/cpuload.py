"""Busy-loop processes that starve the CPU during a benchmark (``--load``).

:func:`cpu_load` starts ``n`` processes at normal priority that each keep one core busy until
the block ends, ``until`` (monotonic s) passes, or the process that started them dies.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import time
from collections.abc import Iterator


def burn(parent: int, until: float) -> None:
    """Keep one core busy until ``until`` (monotonic) or the parent's death."""
    n = 0
    while True:
        n += 1
        if n % 200000 == 0 and (os.getppid() != parent or time.monotonic() > until):
            return


@contextlib.contextmanager
def cpu_load(n: int, until: float) -> Iterator[list[mp.Process]]:
    """``n`` busy-loop processes for the block (stopped by ``until`` at the latest)."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=burn, args=(os.getpid(), until), daemon=True) for _ in range(n)]
    try:
        for p in procs:
            p.start()
        yield procs
    finally:
        for p in procs:
            if p.pid is not None:
                p.terminate()
                p.join(5)
