"""A seqlock over a float64 array in ``multiprocessing.shared_memory``: one writer, many readers.

Slot 0 is the sequence counter: odd while the writer is writing, even when the data is
consistent. A reader copies the data and retries if the counter moved or was odd, so it never
sees half of one write and half of another, and the writer never waits (the 1 kHz side never
blocks on the daemon). Values are float64; small integers (counters, flags) are exact.
"""

from __future__ import annotations

import time
from multiprocessing import shared_memory

import numpy as np
from numpy.typing import NDArray


class SeqlockArray:
    """``n`` float64 values in shared memory behind a sequence counter.

    Create with ``name=None`` (the owner; ``unlink()`` when done) or attach by ``name``.
    Only one process/thread may write; ``read()`` is safe from anywhere.
    """

    def __init__(self, n: int, name: str | None = None) -> None:
        self.n = n
        size = 8 * (n + 1)
        self.owner = name is None
        self._shm = shared_memory.SharedMemory(name=name, create=self.owner, size=size)
        self._a = np.ndarray((n + 1,), dtype=np.float64, buffer=self._shm.buf)
        if self.owner:
            self._a[:] = 0.0
        self.retries = 0

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, values: NDArray[np.float64] | list[float] | tuple, start: int = 0) -> None:
        """Write ``values`` at data offset ``start`` as one consistent update (nothing once
        the block is closed: its reader is gone)."""
        a = self._a
        if a is None:
            return
        seq = a[0]
        a[0] = seq + 1.0  # odd: writing
        a[1 + start : 1 + start + len(values)] = values
        a[0] = seq + 2.0  # even: consistent

    def read(self, timeout_s: float = 0.01) -> NDArray[np.float64]:
        """A consistent copy of the data; TimeoutError if the writer holds it odd too long, or
        if the block was closed meanwhile (by another thread: there is nothing to read)."""
        a = self._a
        if a is None:
            raise TimeoutError("shared memory block closed")
        deadline = None
        while True:
            s1 = a[0]
            data = a[1:].copy()
            if s1 == a[0] and not int(s1) & 1:
                return data
            self.retries += 1
            now = time.monotonic()
            if deadline is None:
                deadline = now + timeout_s
            elif now > deadline:
                raise TimeoutError("seqlock: writer did not finish a write in time")

    def try_read(self, attempts: int = 3) -> NDArray[np.float64] | None:
        """A consistent copy of the data, or None while a write is in progress; never waits.

        For the real-time reader: a SCHED_FIFO servo must not spin on a lower-priority writer
        that was preempted half-way through a write (priority inversion); it keeps its last
        copy and reads again next tick.
        """
        a = self._a
        for _ in range(attempts):
            s1 = a[0]
            data = a[1:].copy()
            if s1 == a[0] and not int(s1) & 1:
                return data
            self.retries += 1
        return None

    @property
    def sequence(self) -> int:
        """The write counter (2 per completed write)."""
        return int(self._a[0])

    def close(self) -> None:
        self._a = None  # type: ignore[assignment]  # release the buffer export before closing
        self._shm.close()

    def unlink(self) -> None:
        try:
            self._shm.unlink()
        except FileNotFoundError:
            pass
