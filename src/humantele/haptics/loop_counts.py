"""Counts that say why a fixed-rate loop (the servo's, the loop bench's bare one) ran late,
with O(1) work a tick and nothing timed that the kernel can count instead.

:class:`LongPeriods`: each period over 1.5 T (an overrun) put down to one cause: the work of
the tick before it ran over T/2 (``work``: the loop's own), the sleep woke over T/2 after the
time it asked (``wake``: the kernel's timer and scheduler, another task on the CPU), or
neither (``other``: the thread lost the CPU while it spun or worked, or the causes added up).
:class:`ThreadCounts`: the calling thread's page faults and context switches
(``getrusage(RUSAGE_THREAD)``, Linux) and the process's garbage collections (``gc.callbacks``)
since it was made.
"""

from __future__ import annotations

import gc
import resource

RUSAGE_THREAD = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)


class LongPeriods:
    """Overruns (periods over 1.5 ``period``, s) by cause; see the module docstring."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.over_us = 1.5e6 * period  # as PeriodTiming counts its overruns, to the bit
        self.half = 0.5 * period
        self.work = self.wake = self.other = 0
        self.work_max_s = 0.0  # the longest tick's work (s)

    def add(self, period_s: float, work_s: float, late_s: float) -> None:
        """A period of ``period_s`` ended; the tick before it worked ``work_s`` and the sleep
        in it woke ``late_s`` after the time it asked for (0: no sleep)."""
        if work_s > self.work_max_s:
            self.work_max_s = work_s
        if period_s * 1e6 > self.over_us:
            if work_s > self.half:
                self.work += 1
            elif late_s > self.half:
                self.wake += 1
            else:
                self.other += 1


class ThreadCounts:
    """Page faults and context switches of the calling thread, and garbage collections of the
    process, since construction. Call :meth:`close` to stop counting collections."""

    def __init__(self) -> None:
        self.collections = 0
        gc.callbacks.append(self._on_gc)
        self._base = self._now()

    def _on_gc(self, phase: str, info: dict) -> None:  # noqa: ARG002 - gc's signature
        if phase == "start":
            self.collections += 1

    @staticmethod
    def _now() -> tuple[int, int, int, int]:
        r = resource.getrusage(RUSAGE_THREAD)
        return (r.ru_minflt, r.ru_majflt, r.ru_nvcsw, r.ru_nivcsw)

    def counts(self) -> dict[str, int]:
        """``minor_faults``, ``major_faults``, ``voluntary_switches``, ``involuntary_switches``
        since construction (this thread), ``gc_collections`` (the process)."""
        now = self._now()
        names = ("minor_faults", "major_faults", "voluntary_switches", "involuntary_switches")
        out = {k: b - a for k, a, b in zip(names, self._base, now, strict=True)}
        out["gc_collections"] = self.collections
        return out

    def close(self) -> None:
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
