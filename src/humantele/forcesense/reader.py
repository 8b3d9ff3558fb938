"""The force board read at its own rate, apart from the camera, with its freshness.

:class:`ForceReader` owns a :class:`~humantele.forcesense.base.ForceSensor`, its
:class:`~humantele.forcesense.calibration.ForceCalibration` and the contact detector. Each
:meth:`ForceReader.poll` reads the board once (the newest report; the HID backend bounds the
read), turns it into force (probe frame, N) and feeds the contact detector with it. With
:meth:`ForceReader.start` a thread polls at ``rate_hz`` (the board's 100 Hz), so the force is
sampled at the board's rate whatever the camera does (the hand tracker's 5 Hz spells, a
stalled headset stream); without it (the sim clinic's board, which shows the force of the
frame's simulated world), the caller polls once per frame.

A force is *stale* when a read of the board gives no good reading ``stale_s`` after the last
good one (the board unplugged, silent or sending garbage): :meth:`ForceReader.sample` says so,
the contact detector is not fed and is reset (a press is not carried across an unplug), and the
follower sends and uses no force while it lasts (zero, ``force_tip`` None, no contact, not fed
to the calibration).

Staleness is decided by the reads, from the board's own evidence, not by the clock of whoever
asks: a reader thread starved by a loaded machine (it did not run for 0.2 s) finds, when it
wakes, the reports the board queued meanwhile (the HID buffer), and those are fresh evidence
that the board is alive; only a read that comes back empty past the deadline makes the force
stale (counted: ``late_polls``, reads that came more than ``stale_s`` after the previous one,
``caught_up``, those of them that found the board alive). :meth:`ForceReader.sample` between
reads gives the last read's verdict; only a reader thread that has died, or that has not read
for ``reader_silent_s`` (a wedged thread, not a busy machine's scheduling), makes it stale.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from humantele.forcesense.base import ForceSensor
from humantele.forcesense.calibration import ForceCalibration
from humantele.forcesense.contact import ContactConfig, ContactDetector, ContactEvent

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ForceSample:
    """The force as last read: ``force_probe`` (3,) N, probe frame (the last good one, even
    when stale); ``stale``: older than ``stale_s`` (or none yet); ``age_s``: since the last
    good reading (None: none yet); ``contact`` the detector's state (False when stale);
    ``event``: the last press/release since the previous sample."""

    force_probe: NDArray[np.float64]
    stale: bool
    age_s: float | None
    contact: bool
    event: ContactEvent | None


class ForceReader:
    """See the module docstring. ``clock``: monotonic seconds (tests drive it by hand)."""

    def __init__(
        self,
        sensor: ForceSensor,
        calibration: ForceCalibration,
        contact: ContactConfig | None = None,
        rate_hz: float = 100.0,
        stale_s: float = 0.2,
        clock: Callable[[], float] = time.monotonic,
        reader_silent_s: float = 2.0,
    ) -> None:
        self.sensor = sensor
        self.calibration = calibration
        self.contact = ContactDetector(contact)
        self.rate_hz = rate_hz
        self.stale_s = stale_s
        self.reader_silent_s = max(reader_silent_s, stale_s)
        self.clock = clock
        self.reads = 0
        self.readings = 0  # good readings
        self.bad_force = 0  # readings the calibration made non-finite
        self.errors = 0  # a backend that raised (counted; the thread goes on)
        self.stale_spells = 0  # times the force went stale
        self.late_polls = 0  # reads more than stale_s after the previous one (reader starved)
        self.caught_up = 0  # late reads that found a good report: the board was alive
        self._force = np.zeros(3)
        self._good_at: float | None = None
        self._started_at = clock()
        self._event: ContactEvent | None = None
        self._was_stale = False
        self._polled_at: float | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- reading --------------------------------------------------------------------------
    def poll(self, t: float | None = None) -> None:
        """Read the board once; ``t``: the time to stamp and feed the detector with (s;
        default this reader's clock)."""
        try:
            reading = self.sensor.read(t)
        except Exception:  # noqa: BLE001 - a backend's fault must not stop the force
            self.errors += 1
            if self.errors in (1, 10, 100, 1000):
                log.exception("force sensor read failed (%d so far)", self.errors)
            reading = None
        now = self.clock()
        with self._lock:
            self.reads += 1
            late = self._polled_at is not None and now - self._polled_at > self.stale_s
            self.late_polls += late
            self._polled_at = now
            good = False
            if reading is not None:
                f = self.calibration.force(reading)
                if np.all(np.isfinite(f)):
                    good = True
                    self.readings += 1
                    self.caught_up += late
                    self._force, self._good_at = f, now
                    event = self.contact.update(now if t is None else t, f)
                    self._event = event or self._event
                else:
                    self.bad_force += 1
            since = self._good_at if self._good_at is not None else self._started_at
            self._set_stale(not good and now - since > self.stale_s)

    def _set_stale(self, stale: bool) -> bool:
        if stale and not self._was_stale:
            self.stale_spells += self._good_at is not None
            self.contact.reset()
        self._was_stale = stale
        return stale

    def _stale_now(self, now: float) -> bool:
        """The last read's verdict; stale too when the reader thread is gone or has not read
        for ``reader_silent_s`` (its reads, not its scheduling, decide otherwise)."""
        if self._good_at is None:
            return True
        if self._thread is not None and (
            not self._thread.is_alive()
            or self._polled_at is None
            or now - self._polled_at > self.reader_silent_s
        ):
            return self._set_stale(True)
        return self._was_stale

    def sample(self) -> ForceSample:
        """The force as the last read left it, and whether it is fresh (the last event
        taken)."""
        now = self.clock()
        with self._lock:
            stale = self._stale_now(now)
            event, self._event = self._event, None
            age = None if self._good_at is None else now - self._good_at
            return ForceSample(self._force.copy(), stale, age,
                               self.contact.in_contact and not stale, event)  # fmt: skip

    # --- the thread -----------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Poll at ``rate_hz`` in a thread (started by the caller's thread: it inherits its
        scheduling)."""
        if self._thread is not None:
            return
        self._started_at = self.clock()
        self._thread = threading.Thread(target=self._run, name="humantele-force", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.poll()
            next_t += period
            now = time.monotonic()
            if next_t < now - period:  # fell behind: no catching up
                next_t = now
            self._stop.wait(max(0.0, next_t - now))

    def stop(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(2.0)

    def stats(self) -> dict:
        with self._lock:
            now = self.clock()
            age = None if self._good_at is None else now - self._good_at
            out = {"reads": self.reads, "readings": self.readings, "bad_force": self.bad_force,
                   "errors": self.errors, "stale_spells": self.stale_spells,
                   "late_polls": self.late_polls, "caught_up": self.caught_up,
                   "age_s": None if age is None else round(age, 3),
                   "stale": self._stale_now(now)}  # fmt: skip
        sensor_stats = getattr(self.sensor, "stats", None)
        if callable(sensor_stats):
            with contextlib.suppress(Exception):
                out["board"] = sensor_stats()
        return out
