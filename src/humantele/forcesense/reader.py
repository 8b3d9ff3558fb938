"""The force board read at its own rate, apart from the camera, with its freshness.

:class:`ForceReader` owns a :class:`~humantele.forcesense.base.ForceSensor`, its
:class:`~humantele.forcesense.calibration.ForceCalibration` and the contact detector. Each
:meth:`ForceReader.poll` reads the board once (the newest report; the HID backend bounds the
read), turns it into force (probe frame, N) and feeds the contact detector with it. With
:meth:`ForceReader.start` a thread polls at ``rate_hz`` (the board's 100 Hz), so the force is
sampled at the board's rate whatever the camera does (the hand tracker's 5 Hz spells, a
stalled headset stream); without it (the sim clinic's board, which shows the force of the
frame's simulated world), the caller polls once per frame.

A force older than ``stale_s`` (no good reading since: the board unplugged, silent or sending
garbage) is *stale*: :meth:`ForceReader.sample` says so, the contact detector is not fed and
is reset (a press is not carried across an unplug), and the follower sends and uses no force
while it lasts (zero, ``force_tip`` None, no contact, not fed to the calibration).
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
    ) -> None:
        self.sensor = sensor
        self.calibration = calibration
        self.contact = ContactDetector(contact)
        self.rate_hz = rate_hz
        self.stale_s = stale_s
        self.clock = clock
        self.reads = 0
        self.readings = 0  # good readings
        self.bad_force = 0  # readings the calibration made non-finite
        self.errors = 0  # a backend that raised (counted; the thread goes on)
        self.stale_spells = 0  # times the force went stale
        self._force = np.zeros(3)
        self._good_at: float | None = None
        self._started_at = clock()
        self._event: ContactEvent | None = None
        self._was_stale = False
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
            if reading is not None:
                f = self.calibration.force(reading)
                if np.all(np.isfinite(f)):
                    self.readings += 1
                    self._force, self._good_at = f, now
                    event = self.contact.update(now if t is None else t, f)
                    self._event = event or self._event
                else:
                    self.bad_force += 1
            self._check_stale(now)

    def _check_stale(self, now: float) -> bool:
        since = self._good_at if self._good_at is not None else self._started_at
        stale = now - since > self.stale_s
        if stale and not self._was_stale:
            self.stale_spells += self._good_at is not None
            self.contact.reset()
        self._was_stale = stale
        return stale

    def sample(self) -> ForceSample:
        """The force now, and whether it is fresh (the last event taken)."""
        now = self.clock()
        with self._lock:
            stale = self._good_at is None or self._check_stale(now)
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
                   "age_s": None if age is None else round(age, 3),
                   "stale": self._good_at is None or age > self.stale_s}  # fmt: skip
        sensor_stats = getattr(self.sensor, "stats", None)
        if callable(sensor_stats):
            with contextlib.suppress(Exception):
                out["board"] = sensor_stats()
        return out
