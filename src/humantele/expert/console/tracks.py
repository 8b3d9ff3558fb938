"""What the console knows of each video track: its last frame, when it came, its rate, and the
page's echoes of what it drew (the draw latencies and glass to glass; docs/console.md).

Times are on the expert's clock (s) unless said; ``seq`` is the frame's number.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from typing import Any

from humantele.expert.console.messages import Drawn
from humantele.runtime.stats import percentile_ms
from humantele.video.counter import unwrap

LATENCIES_KEPT = 20000
SEQS_KEPT = 256  # frames per track whose times are kept for the page's echoes


def spacing(frame: Any) -> tuple[float, float] | None:
    """A frame's (row, col) pixel spacing (mm), or None when it has none or a bad one."""
    value = getattr(frame, "pixel_spacing_mm", None)
    if value is not None and not all(math.isfinite(s) and s > 0 for s in value):
        return None
    return value


def depth0(frame: Any) -> float | None:
    """A frame's row (px) of depth 0, or None."""
    value = getattr(frame, "depth_origin_row", None)
    return None if value is None or not math.isfinite(value) else value


class TrackFigures:
    """One track: its last frame, when it came, its rate, and this page visit's figures."""

    def __init__(self) -> None:
        self.seq: int | None = None
        self.t_capture: float | None = None
        self.t_seen: float | None = None
        self.size: tuple[int, int] | None = None
        self.spacing: tuple[float, float] | None = None
        self.depth0: float | None = None
        self.times: OrderedDict[int, tuple[float, float]] = OrderedDict()  # seq -> capture, seen
        self.arrivals: deque[float] = deque(maxlen=200)
        self.frames = 0
        self.jpegs = 0  # frames JPEG-encoded for a page
        self.forwarded = 0  # encoded frames sent to pages
        self.encoded_dropped = 0  # ... not sent (a backlog, waiting for a keyframe)
        self.encode_s: deque[float] = deque(maxlen=500)
        self.capture_to_draw: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self.seen_to_draw: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self.capture_to_seen: deque[float] = deque(maxlen=LATENCIES_KEPT)  # of those drawn
        self.drawn = 0
        self.counter_read = 0  # drawn frames whose counter the page read from its canvas
        self.counter_unread = 0  # ... did not read (no counter, or a smeared one)
        self.counter_unmatched = 0  # ... read a number whose frame is not known here

    def new_visit(self) -> None:
        """Forget the last page's figures (a page opens with none open)."""
        for q in (self.capture_to_draw, self.seen_to_draw, self.capture_to_seen, self.encode_s):
            q.clear()
        self.drawn = self.counter_read = self.counter_unread = self.counter_unmatched = 0
        self.frames = self.jpegs = self.forwarded = self.encoded_dropped = 0

    def rate_hz(self, now: float, window_s: float = 2.0) -> float:
        n = sum(1 for t in self.arrivals if now - t <= window_s)
        return round(n / window_s, 1)

    def note(self, frame: Any, seen: float) -> None:
        """A new frame, ``seen`` now: its times kept for the page's echoes."""
        # When the frame was there: the receiver's decode time (the expert's receipt of a
        # received frame), else now.
        there = getattr(frame, "t_received", None)
        there = seen if there is None or not math.isfinite(there) or there > seen else there
        self.seq, self.t_capture, self.t_seen = frame.seq, frame.t_capture, seen
        self.size, self.spacing = (frame.width, frame.height), spacing(frame)
        self.depth0 = depth0(frame)
        self.times[frame.seq] = (frame.t_capture, there)
        while len(self.times) > SEQS_KEPT:
            self.times.popitem(last=False)
        self.arrivals.append(seen)
        self.frames += 1

    def on_drawn(self, m: Drawn, arrival: float, last_drawn: int) -> str | None:
        """The page drew frame ``m.seq`` (its echo came at ``arrival``; ``last_drawn``: the
        newest it drew before): the latencies noted; or why the echo is refused."""
        times = self.times.get(m.seq)
        if times is None:
            return "unknown_frame"
        if m.seq <= last_drawn:
            return "repeated_frame"
        d = m.draw_to_send_ms / 1000.0
        _, t_seen = times
        to_draw = arrival - d - t_seen
        if not -0.001 <= to_draw <= 10.0:
            return "implausible"
        self.drawn += 1
        self.seen_to_draw.append(max(0.0, to_draw))
        # Glass to glass as the page shows it: the counter read back from the page's canvas,
        # matched to that frame's capture time.
        if m.counter is None:
            self.counter_unread += 1
            return None
        drawn = self.times.get(unwrap(m.counter, m.seq))
        if drawn is None:
            self.counter_unmatched += 1
            return None
        self.counter_read += 1
        self.capture_to_draw.append(arrival - d - drawn[0])
        self.capture_to_seen.append(drawn[1] - drawn[0])
        return None

    def state(self, now: float, stale_ms: float) -> dict[str, Any]:
        """This track in the page's ``state`` message (``age_ms`` from capture)."""
        age = None if self.t_capture is None else (now - self.t_capture) * 1000.0
        return {
            "seq": self.seq,
            "age_ms": age,
            "fps": self.rate_hz(now),
            "stale": age is None or age > stale_ms,
            "size": self.size,
            "spacing": self.spacing,
            "depth0": self.depth0,
        }

    def stats(self) -> dict[str, Any]:
        """This track's figures for the expert's stats (``console.us``, ``console.pov``)."""
        return {
            "frames": self.frames,
            "jpegs": self.jpegs,
            "forwarded": self.forwarded,
            "encoded_dropped": self.encoded_dropped,
            "drawn": self.drawn,
            "encode_p50_ms": percentile_ms(self.encode_s, 50, ndigits=2),
            "seen_to_draw_p50_ms": percentile_ms(self.seen_to_draw, 50, ndigits=2),
            "seen_to_draw_p95_ms": percentile_ms(self.seen_to_draw, 95, ndigits=2),
            "capture_to_draw_p50_ms": percentile_ms(self.capture_to_draw, 50, ndigits=2),
            "capture_to_draw_p95_ms": percentile_ms(self.capture_to_draw, 95, ndigits=2),
            "capture_to_seen_p50_ms": percentile_ms(self.capture_to_seen, 50, ndigits=2),
            "capture_to_seen_p95_ms": percentile_ms(self.capture_to_seen, 95, ndigits=2),
            "counter_read": self.counter_read,
            "counter_unread": self.counter_unread,
            "counter_unmatched": self.counter_unmatched,
        }
