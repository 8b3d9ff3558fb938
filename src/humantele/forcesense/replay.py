"""The ``replay`` force sensor backend: a device recording's raw HID reports through the real
HID reader.

Reads ``/force/hid_report`` of a file written by ``humantele devices record``
(:mod:`humantele.recording.device_file`). :class:`ReplayForceSensor` is a
:class:`~humantele.forcesense.hid.HidForceSensor` whose device hands out the recorded reports
(the bytes as the board sent them) as the board sent them (relative to ``open``), so the
board's own parser (id, version, CRC, pairs, flags; drops counted by reason) and the reader's
drain loop run as with the board. ``loop``: start again at the end; else the device goes quiet
(reads give nothing, as an idle board).

A report is due at the board's own time (its microsecond clock, in the report) on the
recording's timeline (:mod:`humantele.recording.replay_timeline`), shared with the tracker's
replay of the same file: from ``open``, counted from the recording's first message, each loop
the recording's span, so a press comes with the frames of its tip. The receive times alone
carry the recording machine's scheduling: a recorder starved for 0.5 s received half a second
of reports in one burst, which replayed at those times is a board silent for 0.5 s (its force
stale), though the board sent every 10 ms. A report that does not parse goes out with the one
before it.

``open`` raises :class:`~humantele.forcesense.base.ForceSensorUnavailable` (one line) for a
file that is not a device recording or holds no HID report; a truncated file is replayed up to
its torn tail, logged.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterator
from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel
from humantele.forcesense.base import ForceSensorUnavailable
from humantele.forcesense.hid import HidForceConfig, HidForceSensor, ReportError, parse_report
from humantele.recording.device_file import (
    HID_REPORT,
    DeviceRecording,
    DeviceRecordingError,
    Sample,
    open_recording,
)
from humantele.recording.replay_timeline import DeviceClock, ReplayTimeline, shared_timeline


class ReplayForceConfig(ConfigModel):
    """The ``replay`` force sensor backend: a device recording's HID reports."""

    backend: Literal["replay"] = "replay"
    file: str = Field(..., min_length=1, description="MCAP from `humantele devices record`")
    loop: bool = Field(False, description="start again at the end")
    pace: bool = Field(True, description="at the recorded times (False: all at once)")
    read_timeout_ms: int = Field(20, ge=0, le=1000, description="as the hid backend's")


class _ReplayHidDevice:
    """An hidapi-like device (``read(n, timeout_ms)``, ``close()``) replaying reports."""

    def __init__(
        self,
        rec: DeviceRecording,
        config: ReplayForceConfig,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
    ) -> None:
        self.rec, self.config = rec, config
        self.clock, self.sleep = clock, sleep
        self.timeline = shared_timeline(rec.path, rec.span(), clock)
        self._loop = 0
        self._start()

    def _start(self) -> None:
        self._it: Iterator[Sample] = self.rec.samples({HID_REPORT})
        self._board = DeviceClock(1e6, 1 << 32)  # the board's microseconds
        self._due = 0.0  # when self._next is due (s, this replay's clock)
        self._advance()

    def _advance(self) -> None:
        """The next report and when it is due (module docstring)."""
        s = self._next = next(self._it, None)
        if s is not None:
            t = self._board.time(s.t, _board_time_us(bytes(s.blobs.get("report", b""))))
            self._due = self.timeline.due(t, self._loop)

    def read(self, size: int, timeout_ms: int = 0) -> list[int]:
        if self._next is None and self.config.loop:
            if self.timeline.period is None:  # no span known: from where it ends, on its own
                self.timeline, self._loop = ReplayTimeline(None, self.clock), 0
            else:
                self._loop += 1
            self._start()
        s = self._next
        if s is None:  # the end: an idle board
            if timeout_ms:
                self.sleep(timeout_ms / 1000.0)
            return []
        if self.config.pace:
            wait = self._due - self.clock()
            if wait > timeout_ms / 1000.0:
                if timeout_ms:
                    self.sleep(timeout_ms / 1000.0)
                return []
            if wait > 0:
                self.sleep(wait)
        self._advance()
        return list(bytes(s.blobs.get("report", b""))[:size])

    def close(self) -> None:
        close = getattr(self._it, "close", None)
        if close is not None:
            close()
        self._next = None


def _board_time_us(report: bytes) -> int | None:
    """A good report's board time (us, wrapping at 2**32); None if it does not parse."""
    try:
        parse_report(report)
    except ReportError:
        return None
    return struct.unpack_from("<I", report, 4)[0]


class ReplayForceSensor(HidForceSensor):
    """The board's HID reader on recorded reports (see the module docstring)."""

    name = "replay force sensor"

    def __init__(self, config: ReplayForceConfig, clock=time.monotonic, sleep=time.sleep):
        super().__init__(HidForceConfig(read_timeout_ms=config.read_timeout_ms))
        self.replay = config
        self._clock, self._sleep = clock, sleep
        self.problem: str | None = None
        self._rec: DeviceRecording | None = None

    def open(self) -> None:
        if self._dev is not None:
            return
        try:
            rec = open_recording(self.replay.file)
        except DeviceRecordingError as exc:
            raise ForceSensorUnavailable(f"replay force sensor: {exc}") from None
        dev = _ReplayHidDevice(rec, self.replay, self._clock, self._sleep)
        if dev._next is None:
            dev.close()
            raise ForceSensorUnavailable(
                f"replay force sensor: {self.replay.file} holds no HID report"
                + ("" if rec.problem is None else f" ({rec.problem})")
            )
        self._rec, self._dev = rec, dev

    def read(self, t: float | None = None):
        reading = super().read(t)
        if self._rec is not None:
            self.problem = self._rec.problem
        return reading
