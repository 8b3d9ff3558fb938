"""The one force sensor interface, shared by the real and the simulated backends.

A :class:`ForceSensor` gives :class:`~humantele.forcesense.readings.ForceReading` s (the Hall
readings of the board, mT); a :class:`~humantele.forcesense.calibration.ForceCalibration`
turns them into force (probe frame, N). Backends (``sim``, ``hid``) are picked by the
``backend`` field of their configuration in :mod:`humantele.forcesense.sensors`
(:func:`~humantele.forcesense.sensors.make_force_sensor`), as haptic devices, frame sources
and video sources are.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from humantele.forcesense.readings import ForceReading


class ForceSensorUnavailable(RuntimeError):
    """No force sensor board could be opened; the message says what was looked for."""


class ForceSensor(ABC):
    """Readings from the force sensor board or a simulation; same methods for all backends.

    ``open()`` raises :class:`ForceSensorUnavailable` when the board cannot be opened;
    ``read(t)`` returns the newest reading stamped ``t`` (s; None: the source's own time), or
    None when none came (a backend counts what it drops); ``close()`` releases the board, safe
    to call twice. ``read`` never raises for a bad report.
    """

    name: str = "force sensor"

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def read(self, t: float | None = None) -> ForceReading | None: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> ForceSensor:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
