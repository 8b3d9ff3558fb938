"""How far behind the headset's stream a client has fallen: the queue a slow link builds.

The hl2ss app never waits for the network before taking the next frame: its sensor loop
(``ResearchMode_ExecuteSensorLoop``) hands every frame to a Media Foundation sink writer made
with ``MF_SINK_WRITER_DISABLE_THROTTLING`` (``custom_sink_writers.cpp``), whose sink sends
each encoded frame with a blocking ``WSASend`` (``send_multiple`` in ``server.cpp``). A link
slower than the stream therefore queues frames in the app, without a bound and without
dropping any: each frame arrives later than the last. Reading the newest frame cannot help
(the queue is on the headset, before the link); dropping the connection does (the app's
sensor loop ends and its encoder, with the queue, is destroyed: ``Execute_Mode0``).

:class:`BacklogMonitor` measures that queue from the frames' own timestamps (the headset's
clock, 100 ns ticks) against their arrival on the client's clock: the offset ``arrival -
device time`` is the unknown clock offset plus the frame's transit; its least value over the
connection is the transit of a frame that did not wait, so ``offset - least`` is how long a
frame waited. The least value may rise by ``drift`` per second (the clocks' relative drift,
100 ppm at most for crystal clocks), so a clock that drifts is not taken for a queue; a
device time that goes back (a replay starting again) starts it again. Only for a reader that
takes the newest frame: one that reads every frame in order measures its own lag too.
"""

from __future__ import annotations


class BacklogMonitor:
    """Says when ``persist`` frames in a row each waited more than ``max_s`` (s) longer than
    the quickest frame (one late frame is the client's own stall: the frames after it, read
    newest first, are fresh again; a queue on the headset makes every frame late)."""

    def __init__(self, max_s: float, drift: float = 1e-4, persist: int = 3):
        self.max_s = max_s
        self.drift = drift
        self.persist = persist
        self._run = 0
        self._least: float | None = None
        self._last_arrival = 0.0
        self._last_device: float | None = None
        self.backlog_s = 0.0  # the last frame's wait beyond the quickest (s)

    def late(self, device_time_s: float, arrival_s: float) -> bool:
        """Take one frame (its device time and arrival, s); True when it waited too long."""
        offset = arrival_s - device_time_s
        if self._last_device is not None and device_time_s < self._last_device:
            self._least = None  # the device's time went back: another stream (a replay's loop)
        self._last_device = device_time_s
        if self._least is None:
            self._least = offset
        else:
            self._least += self.drift * max(0.0, arrival_s - self._last_arrival)
            self._least = min(self._least, offset)
        self._last_arrival = arrival_s
        self.backlog_s = offset - self._least
        self._run = self._run + 1 if self.backlog_s > self.max_s else 0
        return self._run >= self.persist
