"""The expert's side of the video: receive ``us`` and ``pov``, keep the latest decoded frame of
each with its capture time on the expert's clock.

:meth:`VideoReceiver.prepare` is the expert link's media hook: before each offer it adds two
receive-only video transceivers (``us`` first, then ``pov``) offering only the configured
codec (no RTX: see :meth:`prepare`), each with our jitter buffer
(:mod:`humantele.media.jitter`), and the ``video`` data channel (id 3) on which the follower
sends each frame's :class:`~humantele.media.frameinfo.FrameInfo`. For each track a task on the
loop takes the
decoded frames (aiortc decodes in its own thread), reads the frame counter from the luma
plane's top-left corner (64 x 32 px, a fraction of a millisecond), finds the frame's capture
time (follower clock) and maps it to the expert's with the link's clock sync.

The sender's frame ``pts`` is its capture time on the 90 kHz RTP clock, and aiortc gives each
decoded frame the RTP timestamp counted from the first frame received: so the two differ by a
constant per stream, learnt from any frame whose counter reads and whose record arrived (the
"anchor"). After that every frame's capture time is known, including a frame whose counter
does not read (none with the follower's encoders; aiortc's own VP8 settings left stale blocks
in it, :mod:`humantele.media.encoders`). Nothing on the
loop converts or copies the picture: :meth:`ReceivedFrame.image` does that for whoever shows
it, in its own thread.

Recording (when ``record`` is given): every frame of both tracks as it arrived, encoded
(:class:`~humantele.media.aiortc_hooks.EncodedFrameTap` on the jitter buffer: the bytes aiortc
decodes, so no re-encoding and no copy beyond the recorder's), on ``/expert/us_video`` and
``/expert/pov_video`` with its codec, keyframe flag, RTP timestamp, receive time and, once
the stream's RTP clock is anchored, capture time (expert clock). ``humantele export`` makes
MP4 and Foxglove files of them.

Listeners (the console, only while a page is open: :meth:`VideoReceiver.listen`): each
decoded frame of a track, in order, including those the loop skipped for a newer one, with
the encoded frame it was decoded from (:class:`Encoded`, the tap's bytes: what a page's own
decoder takes). With no listener nothing is kept or called beyond the recording's tap.

Each decoded frame is shown (made the latest, timed, recorded as ``received``) when due
(:mod:`humantele.media.playout`): at once on a link that repairs no loss; while the jitter
buffer repairs packets, at a steady delay after its RTP time that covers the repairs (a
repaired frame is otherwise a gap between pictures, a freeze on a 120 ms round trip). Frame
age (``age_s``) is capture to shown at the expert ("glass to glass" without the display).
Frames whose counter does not read or whose record was lost are kept (they are the latest
picture) with an unknown age, and counted.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

import av
import numpy as np
from aiortc import RTCPeerConnection, RTCRtpSender
from aiortc.mediastreams import MediaStreamError

from humantele.media.aiortc_hooks import (
    EncodedFrameTap,
    forget_missing,
    hold_nacks,
    newest_frame,
    receive_parity,
    repeat_nacks,
    request_keyframe,
    request_retransmission,
    use_jitter_buffer,
)
from humantele.media.config import TRACKS, ExpertVideoConfig
from humantele.media.fec import ParityDecoder
from humantele.media.frameinfo import FrameInfo, FrameInfoError
from humantele.media.jitter import KEYFRAME_TESTS, BoundedJitterBuffer
from humantele.media.playout import VIDEO_RATE, Playout
from humantele.media.sender import VIDEO_CHANNEL_ID
from humantele.recording.schemas import VIDEO_TOPICS
from humantele.runtime.stats import percentile_ms
from humantele.transport.clocksync import ClockSync
from humantele.video.counter import CELL, COLS, ROWS, read_counter, unwrap

log = logging.getLogger(__name__)

Record = Callable[[str, float, dict], Any]
INFO_KEEP = 256  # frame records kept per track for matching
POLL_S = 0.01  # the jitter buffers' re-asks are looked at this often between packets (s)
NACK_REPEAT_S = 0.005  # each NACK leaves again this long after the first (repeat_nacks, s)
# A NACK for a packet of a protected stream waits for the frame's parity (hold_nacks) at most
# PARITY_HOLD_S and PARITY_HOLD_RTT_SHARE of a repair's round trip: the parity comes after
# the frame's last packet, paced about 5 ms a packet (within 20 ms of a gap in a 4-packet US
# frame); when it was lost too the repair is late by the hold (on a link of no delay a held
# NACK at 15 % loss gave up more gaps than none: tools/repair_sim.py).
PARITY_HOLD_S = 0.03
PARITY_HOLD_RTT_SHARE = 0.25


KEYFRAME_EVERY_S = 0.5  # keyframe requests of a track (PLI) at most this often
ENCODED_KEPT = 64  # encoded frames of a track awaiting their decoded frame (with a listener)


class Encoded:
    """The encoded frame a decoded frame came from: ``data`` (a VP8 frame or an H.264 access
    unit, as received), ``keyframe``, ``codec`` ('VP8' or 'H264')."""

    __slots__ = ("data", "keyframe", "codec")

    def __init__(self, data: bytes, keyframe: bool, codec: str) -> None:
        self.data = data
        self.keyframe = keyframe
        self.codec = codec


Listener = Callable[["ReceivedFrame", "Encoded | None"], Any]


class ReceivedFrame:
    """One decoded frame of a track.

    ``seq``: its number (from the counter drawn in it; None if it did not read);
    ``t_received``: when it was decoded (s, the expert's clock); ``t_capture``: its capture
    time mapped onto the expert's clock (None when unknown); ``frame``: the decoded
    ``av.VideoFrame`` (yuv420p).
    """

    __slots__ = ("track", "seq", "frame", "t_received", "t_capture", "_bgr", "_lock")

    def __init__(
        self,
        track: str,
        seq: int | None,
        frame: av.VideoFrame,
        t_received: float,
        t_capture: float | None,
    ) -> None:
        self.track = track
        self.seq = seq
        self.frame = frame
        self.t_received = t_received
        self.t_capture = t_capture
        self._bgr: np.ndarray | None = None
        self._lock = threading.Lock()

    @property
    def width(self) -> int:
        return int(self.frame.width)

    @property
    def height(self) -> int:
        return int(self.frame.height)

    @property
    def age_s(self) -> float | None:
        """Capture to decoded (s), or None when the capture time is unknown."""
        return None if self.t_capture is None else self.t_received - self.t_capture

    def image(self) -> np.ndarray:
        """The picture, (H, W, 3) uint8 BGR; converted once (a few ms: call it off the loop)."""
        with self._lock:
            if self._bgr is None:
                self._bgr = self.frame.to_ndarray(format="bgr24")
            return self._bgr


def _counter(buffer: BoundedJitterBuffer) -> Callable[[], None]:
    """Counts a NACK sent again in ``buffer``'s counters (``nacks_repeated``)."""

    def count() -> None:
        buffer.counters.nacks_repeated += 1

    return count


def parity_hold(buffer: BoundedJitterBuffer) -> Callable[[], float]:
    """How long a NACK waits for its frame's parity (s): see :data:`PARITY_HOLD_S`."""

    def hold() -> float:
        rtt = buffer.round_trip_s()
        return PARITY_HOLD_S if rtt is None else min(PARITY_HOLD_S, PARITY_HOLD_RTT_SHARE * rtt)

    return hold


def _spared(buffer: BoundedJitterBuffer) -> Callable[[int], None]:
    """Counts the lost packets a held NACK did not ask for (``fec_nacks_spared``)."""

    def count(n: int) -> None:
        buffer.counters.fec_nacks_spared += n

    return count


def luma_plane(frame: av.VideoFrame) -> np.ndarray:
    """The luma plane of a planar YUV frame (yuv420p, yuvj420p, nv12) as a height x width
    uint8 view (the plane's rows are ``line_size`` bytes, padding included)."""
    plane = frame.planes[0]
    rows = np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)
    return rows[: frame.height, : plane.width]


def luma_patch(frame: av.VideoFrame) -> np.ndarray | None:
    """The top-left 64 x 32 px of the luma plane (a view), or None if the frame is smaller."""
    h, w = ROWS * CELL, COLS * CELL
    if frame.format.name not in ("yuv420p", "yuvj420p", "nv12") or frame.height < h:
        return None
    if frame.planes[0].width < w:
        return None
    return luma_plane(frame)[:h, :w]


class TrackStats:
    """Figures of one received track (the last ``keep`` frames)."""

    def __init__(self, keep: int = 3000) -> None:
        self.frames = 0
        self.unreadable = 0  # counter did not read
        self.no_info = 0  # capture time unknown
        self.out_of_order = 0
        self.stale_dropped = 0  # decoded frames dropped for a newer one already waiting
        self.skipped = 0  # frames the counter says were never received (lost or not sent)
        self.ages: deque[float] = deque(maxlen=keep)
        self.arrivals: deque[float] = deque(maxlen=keep)
        self.last_seq: int | None = None
        self.anchor: int | None = None  # sender's capture time minus received pts, 90 kHz
        self.anchors = 0  # times the anchor moved (a new stream, a sender's clock jump)
        self.candidates: set[int] | None = None  # anchors the last unstamped frame allows
        self.size: tuple[int, int] | None = None
        self.encoded_recorded = 0  # encoded frames queued for the recording
        self.rtp_origin: int | None = None  # aiortc's pts = RTP timestamp - origin (unwrapped)
        self.rtp_last: int | None = None

    def fps(self, now: float, window_s: float = 2.0) -> float:
        n = sum(1 for t in self.arrivals if now - t <= window_s)
        return round(n / window_s, 1)

    def as_dict(self, now: float) -> dict[str, Any]:
        a = np.asarray(self.ages, dtype=float)
        arr = np.asarray(self.arrivals, dtype=float)
        span = float(arr[-1] - arr[0]) if arr.size > 1 else 0.0
        return {
            "frames": self.frames,
            "fps": self.fps(now),
            "fps_mean": round((arr.size - 1) / span, 2) if span > 0 else None,
            "gap_max_ms": round(float(np.diff(arr).max()) * 1e3, 1) if arr.size > 1 else None,
            "age_p50_ms": percentile_ms(a, 50),
            "age_p95_ms": percentile_ms(a, 95),
            "age_max_ms": round(float(a.max()) * 1e3, 1) if a.size else None,
            "unreadable": self.unreadable,
            "no_info": self.no_info,
            "out_of_order": self.out_of_order,
            "stale_dropped": self.stale_dropped,
            "skipped": self.skipped,
            "size": list(self.size) if self.size else None,
            "encoded_recorded": self.encoded_recorded,
        }


class VideoReceiver:
    """The expert's two tracks; ``clock`` is the link's ClockSync, ``now`` the expert's clock,
    ``record(topic, t, payload)`` records (None: no recording); ``recording()`` says whether a
    recording is open (then, with ``record_encoded``, each new connection's frames are
    recorded encoded; default: whenever ``record`` is given)."""

    def __init__(
        self,
        config: ExpertVideoConfig,
        clock: ClockSync,
        now: Callable[[], float] = time.monotonic,
        record: Record | None = None,
        recording: Callable[[], bool] | None = None,
    ) -> None:
        self.config = config
        self.recording = recording or (lambda: record is not None)
        self.clock = clock
        self.now = now
        self.record = record
        self.stats_by_track = {name: TrackStats() for name in TRACKS}
        self.infos_bad = 0
        self.tracks_started = 0
        self._latest: dict[str, ReceivedFrame | None] = dict.fromkeys(TRACKS)
        self._infos: dict[str, OrderedDict[int, float]] = {n: OrderedDict() for n in TRACKS}
        self._seq_at: dict[str, OrderedDict[int, int]] = {n: OrderedDict() for n in TRACKS}
        self._events = {name: asyncio.Event() for name in TRACKS}
        self._pc: RTCPeerConnection | None = None
        self._jitter: dict[str, BoundedJitterBuffer] = {}  # the current connection's
        self._playout: dict[str, Playout] = {}  # the current connection's
        self._tasks: set[asyncio.Task] = set()
        self.listeners: dict[str, list[Listener]] = {n: [] for n in TRACKS}
        self._released: dict[str, deque[Any]] = {n: deque(maxlen=ENCODED_KEPT) for n in TRACKS}
        self._taps: dict[str, EncodedFrameTap] = {}
        self._receivers: dict[str, Any] = {}
        self._keyframe_asked: dict[str, float] = dict.fromkeys(TRACKS, -math.inf)
        self.keyframes_requested = 0
        self._parity: ParityDecoder | None = None  # the current connection's (config fec)

    # --- listeners (the console's forwarding) -------------------------------------------------

    def listen(self, track: str, fn: Listener) -> None:
        """Call ``fn(frame, encoded)`` on the loop for each decoded frame of ``track`` from
        now on (see the module doc)."""
        if fn not in self.listeners[track]:
            self.listeners[track].append(fn)

    def unlisten(self, track: str, fn: Listener) -> None:
        with contextlib.suppress(ValueError):
            self.listeners[track].remove(fn)
        if not self.listeners[track]:
            self._released[track].clear()

    def request_keyframe(self, track: str) -> bool:
        """Ask the follower for a keyframe of ``track`` (at most every
        ``KEYFRAME_EVERY_S``); whether a request went out."""
        now = self.now()
        tap, receiver = self._taps.get(track), self._receivers.get(track)
        if tap is None or receiver is None or tap.ssrc is None:
            return False
        if now - self._keyframe_asked[track] < KEYFRAME_EVERY_S:
            return False
        self._keyframe_asked[track] = now
        self.keyframes_requested += 1
        self._spawn(request_keyframe(receiver, tap.ssrc))
        return True

    # --- what the console reads ---------------------------------------------------------------

    def latest(self, track: str) -> ReceivedFrame | None:
        """The newest decoded frame of ``track`` ('us' or 'pov'), or None before the first."""
        return self._latest[track]

    async def wait_frame(self, track: str, timeout: float | None = None) -> ReceivedFrame:
        """The next frame of ``track`` (TimeoutError after ``timeout`` s)."""
        ev = self._events[track]
        await asyncio.wait_for(ev.wait(), timeout)
        frame = self._latest[track]
        assert frame is not None
        return frame

    # --- per peer connection ------------------------------------------------------------------

    def prepare(self, pc: RTCPeerConnection) -> None:
        """Before the offer on a new peer connection: two recvonly video transceivers offering
        the configured codec, the ``video`` channel, and a task per received track."""
        if not self.config.enabled:
            return
        self._pc = pc
        for name in TRACKS:  # a new follower process numbers its frames from 1 again
            self.stats_by_track[name].last_seq = None
            self.stats_by_track[name].anchor = None  # and its RTP timestamps start anew
            self.stats_by_track[name].rtp_origin = None
            self._infos[name].clear()
            self._seq_at[name].clear()
            self._released[name].clear()
        # The codec alone, without RTX: aiortc routes an RTX packet by its payload type when
        # its SSRC is unknown, and with two video tracks sharing that payload type it drops
        # every retransmission. Without RTX a retransmission is the original packet, routed
        # by its SSRC (docs/video.md, "Loss").
        codec = f"video/{self.config.codec}"
        prefs = [c for c in RTCRtpSender.getCapabilities("video").codecs
                 if c.mimeType.lower() == codec]  # fmt: skip
        names = {}
        parity = ParityDecoder(self.now, self._on_parity) if self.config.fec else None
        self._parity = parity
        for name in TRACKS:
            transceiver = pc.addTransceiver("video", direction="recvonly")
            transceiver.setCodecPreferences(prefs)
            buffer = BoundedJitterBuffer(
                KEYFRAME_TESTS[self.config.codec],
                self.config.loss_wait_ms / 1000.0,
                # a prior for a repair's round trip until the buffer has measured some: the
                # clock sync's shortest recent one (its longest is a lost ping's SCTP
                # retransmission, >= 1 s, on any lossy link: docs/video.md "Loss")
                rtt=lambda: getattr(self.clock, "rtt", None),
            )
            record = self.record is not None and self.config.record_encoded and self.recording()
            tap = EncodedFrameTap(
                buffer,
                self._encoded_recorder(name) if record else None,
                self._releaser(name),
            )
            tap.on_nack = self._renacker(transceiver.receiver)
            tap.on_give_up = functools.partial(forget_missing, transceiver.receiver)
            if self.config.repeat_nacks:
                repeat_nacks(transceiver.receiver, NACK_REPEAT_S, _counter(buffer))
            if parity is not None:  # (each transport: BUNDLE later keeps the first one's)
                receive_parity(transceiver.receiver, parity)
                hold = parity_hold(buffer)
                hold_nacks(transceiver.receiver, parity, hold, _spared(buffer))
                buffer.nack_hold = hold  # a repair's time includes the hold
            use_jitter_buffer(transceiver.receiver, tap)
            self._taps[name] = tap
            self._receivers[name] = transceiver.receiver
            self._jitter[name] = buffer
            names[id(transceiver.receiver)] = name
        channel = pc.createDataChannel(
            "video", negotiated=True, id=VIDEO_CHANNEL_ID, ordered=False, maxRetransmits=0
        )
        channel.on("message", lambda data: self._on_info(pc, data))

        def on_track(track: Any) -> None:
            for t in pc.getTransceivers():
                if t.receiver.track is track and id(t.receiver) in names:
                    self._spawn(self._consume(pc, names[id(t.receiver)], track))

        pc.on("track", on_track)
        with contextlib.suppress(RuntimeError):  # no running loop: no re-asks between packets
            asyncio.get_running_loop()
            self._spawn(self._poll_taps(pc))

    async def _poll_taps(self, pc: RTCPeerConnection) -> None:
        """Every :data:`POLL_S` while ``pc`` is the connection: each jitter buffer's timed
        work between packets (its re-asks for packets still missing)."""
        while pc is self._pc:
            for tap in list(self._taps.values()):
                try:
                    tap.poll()
                except Exception:
                    log.exception("video: jitter buffer poll failed")
            await asyncio.sleep(POLL_S)

    def _on_parity(self, ssrc: int, what: str, seq: int) -> None:
        """The parity decoder's events, counted in the stream's jitter counters; a packet
        about to be fed rebuilt is noted in its jitter buffer (not a repair)."""
        for name, tap in self._taps.items():
            if tap.ssrc == ssrc and name in self._jitter:
                buffer = self._jitter[name]
                if what == "recovered":
                    buffer.note_rebuilt(seq)
                elif what == "parity":
                    buffer.counters.fec_parity += 1
                elif what == "unrecoverable":
                    buffer.counters.fec_unrecoverable += 1
                return

    def _releaser(self, name: str) -> Callable[[Any], None]:
        """The tap's ``on_release`` for track ``name``: keep the released frame for the
        listeners (only while there is one)."""
        released, listeners = self._released[name], self.listeners[name]

        def on_release(frame: Any) -> None:
            if listeners:
                released.append(frame)

        return on_release

    def _encoded_for(self, name: str, pts: Any) -> Encoded | None:
        """The encoded frame whose (mapped) timestamp is ``pts``, dropping older ones."""
        released = self._released[name]
        while released:
            jf = released[0]
            if pts is None or jf.timestamp > pts:
                return None
            released.popleft()
            if jf.timestamp == pts:
                data = bytes(jf.data)
                return Encoded(data, KEYFRAME_TESTS[self.config.codec](data), self.config.codec)
        return None

    def _renacker(self, receiver: Any) -> Callable[[int, list[int]], None]:
        """The tap's NACK callback: ask the follower again for packets still missing."""

        def on_nack(ssrc: int, lost: list[int]) -> None:
            self._spawn(request_retransmission(receiver, ssrc, lost))

        return on_nack

    def _encoded_recorder(self, name: str) -> Callable[[bytes, int], None]:
        """The tap's callback for track ``name``: record the encoded frame (see module doc)."""
        st = self.stats_by_track[name]
        topic = VIDEO_TOPICS[name]
        codec = self.config.codec
        is_key = KEYFRAME_TESTS[codec]

        def on_frame(data: bytes, rtp_timestamp: int) -> None:
            t = self.now()
            # aiortc's TimestampMapper: pts counts from the first frame it decodes (this one
            # when st.rtp_origin is None), unwrapping the 32-bit RTP timestamp
            if st.rtp_origin is None:
                st.rtp_origin = rtp_timestamp
            elif st.rtp_last is not None and rtp_timestamp < st.rtp_last:
                st.rtp_origin -= 1 << 32
            st.rtp_last = rtp_timestamp
            payload: dict[str, Any] = {
                "data": data,
                "codec": codec,
                "keyframe": is_key(data),
                "rtp_timestamp": rtp_timestamp,
            }
            if st.anchor is not None:
                t_capture = self.clock.to_local(
                    (rtp_timestamp - st.rtp_origin + st.anchor) / VIDEO_RATE
                )
                if t_capture is not None:
                    payload["t_capture"] = t_capture
            assert self.record is not None
            self.record(topic, t, payload)
            st.encoded_recorded += 1

        return on_frame

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def close(self) -> None:
        for task in list(self._tasks):
            task.cancel()
            with contextlib.suppress(BaseException):
                await task

    def _on_info(self, pc: RTCPeerConnection, data: object) -> None:
        if pc is not self._pc:
            return
        try:
            info = FrameInfo.decode(data)  # type: ignore[arg-type]
        except FrameInfoError:
            self.infos_bad += 1
            return
        infos = self._infos[info.track]
        infos[info.seq] = info.t_capture
        seq_at = self._seq_at[info.track]
        seq_at[int(round(info.t_capture * VIDEO_RATE))] = info.seq
        while len(infos) > INFO_KEEP:
            infos.popitem(last=False)
        while len(seq_at) > INFO_KEEP:
            seq_at.popitem(last=False)
        latest = self._latest[info.track]
        if latest is not None and latest.seq == info.seq and latest.t_capture is None:
            self.stats_by_track[info.track].no_info -= 1  # the record came after its frame
            self._set_capture(latest, info.t_capture)

    def _anchor_from_records(self, name: str, pts: int) -> int | None:
        """The anchor from the records alone (frames without a counter: a real source's,
        which the follower leaves unaltered): each frame allows the anchors that put its pts
        on a recorded capture time (within 2 ticks); capture times are irregular, so the
        anchors two frames in a row allow meet in one. None until they do."""
        st = self.stats_by_track[name]
        allowed = {k - pts + d for k in self._seq_at[name] for d in (-2, -1, 0, 1, 2)}
        prev, st.candidates = st.candidates, allowed
        if prev is None:
            return None
        both = allowed & prev
        # the same anchor within the tolerance appears up to 5 times: one cluster, its middle
        if both and max(both) - min(both) <= 4:
            st.candidates = None
            return int(round((max(both) + min(both)) / 2))
        st.candidates = both or allowed  # still ambiguous: the next frame narrows it
        return None

    def _set_capture(self, f: ReceivedFrame, t_follower: float) -> None:
        f.t_capture = self.clock.to_local(t_follower)
        if f.t_capture is not None:
            self.stats_by_track[f.track].ages.append(f.age_s)

    async def _consume(self, pc: RTCPeerConnection, name: str, track: Any) -> None:
        """Take the decoded frames of ``track`` and show each when due
        (:class:`~humantele.media.playout.Playout`: at once on a link that repairs nothing,
        else at a steady delay); of frames due together (the loop was held up) only the newest
        (the older ones to the listeners alone, if any)."""
        self.tracks_started += 1
        playout = self._playout[name] = Playout()
        pending: deque[tuple[float, Any]] = deque()  # (due, frame), in order
        recv: asyncio.Future | None = None  # kept across waits: no frame lost to a timeout
        try:
            while pc is self._pc:
                wait = None if not pending else max(0.0, pending[0][0] - self.now())
                if wait is None or wait > 0:
                    if recv is None:
                        recv = asyncio.ensure_future(track.recv())
                    done, _ = await asyncio.wait({recv}, timeout=wait)
                    if recv in done:
                        try:
                            got = recv.result()
                        except MediaStreamError:
                            return
                        recv = None
                        older: list[Any] = []
                        frame, _ = newest_frame(track, got, older)
                        if frame is None:  # the track ended
                            return
                        now = self.now()
                        buffer = self._jitter.get(name)
                        if buffer is not None:
                            c = buffer.counters
                            playout.note_repairs(c.repairs + c.late_repairs, now)
                        for f in (*older, frame):
                            pending.append((playout.due(f.pts, now), f))
                if pc is not self._pc:
                    return
                self._show_due(name, pending)
        finally:
            if recv is not None:
                recv.cancel()

    def _show_due(self, name: str, pending: deque[tuple[float, Any]]) -> None:
        """Show the newest of the ``pending`` frames now due; the older due ones go to the
        listeners alone (if any)."""
        now, due = self.now(), []
        while pending and pending[0][0] <= now:
            due.append(pending.popleft()[1])
        if not due:
            return
        self.stats_by_track[name].stale_dropped += len(due) - 1
        try:
            for old in due[:-1] if self.listeners[name] else ():
                self._on_frame(name, old, skipped=True)
            self._on_frame(name, due[-1])
        except Exception:
            log.exception("video %s: frame handling failed", name)

    def _on_frame(self, name: str, frame: av.VideoFrame, skipped: bool = False) -> None:
        """Number and time a decoded frame; the newest of the track unless ``skipped`` (a
        newer one waits: then only the listeners get it)."""
        t = self.now()
        st = self.stats_by_track[name]
        if not skipped:
            st.frames += 1
            st.arrivals.append(t)
            st.size = (frame.width, frame.height)
        patch = luma_patch(frame)
        value = None if patch is None else read_counter(patch)
        seq = None
        if value is not None:
            seq = unwrap(value, st.last_seq if st.last_seq is not None else value)
        pts = frame.pts
        t_follower = None if seq is None else self._infos[name].get(seq)
        if t_follower is not None and pts is not None:
            # pts is the RTP timestamp from the first frame received (90 kHz), the sender's
            # capture time plus a constant: one frame whose counter reads anchors them all
            anchor = int(round(t_follower * VIDEO_RATE)) - int(pts)
            if st.anchor is None or abs(anchor - st.anchor) > 2:
                st.anchors += st.anchor is not None
                st.anchor = anchor
        elif st.anchor is None and pts is not None and value is None:
            st.anchor = self._anchor_from_records(name, int(pts))  # a frame with no counter
        if t_follower is None and st.anchor is not None and pts is not None:
            t_follower = (int(pts) + st.anchor) / VIDEO_RATE
            if seq is None:  # the counter did not read (a codec smear): the record says which
                key, seq_at = int(pts) + st.anchor, self._seq_at[name]
                seq = next((seq_at[k] for k in (key, key - 1, key + 1) if k in seq_at), None)
        if value is None:
            st.unreadable += 1
        if seq is not None:
            if st.last_seq is not None:
                if seq <= st.last_seq:
                    st.out_of_order += 1
                else:
                    st.skipped += seq - st.last_seq - 1
            st.last_seq = seq if st.last_seq is None else max(seq, st.last_seq)
        received = ReceivedFrame(name, seq, frame, t, None)
        if t_follower is not None:
            self._set_capture(received, t_follower)
        elif not skipped:
            st.no_info += 1
        if self.listeners[name]:
            encoded = self._encoded_for(name, frame.pts)
            for fn in list(self.listeners[name]):
                try:
                    fn(received, encoded)
                except Exception:
                    log.exception("video %s: a listener failed", name)
        if skipped:
            return
        self._latest[name] = received
        ev, self._events[name] = self._events[name], asyncio.Event()
        ev.set()
        if self.record is not None and self.config.record_frames and seq is not None:
            payload: dict[str, Any] = {"stream": name, "seq": seq, "event": "received"}
            if received.age_s is not None:
                payload["age_s"] = received.age_s
            self.record("/expert/video_frame", t, payload)

    def stats(self) -> dict[str, Any]:
        now = self.now()
        out: dict[str, Any] = {name: s.as_dict(now) for name, s in self.stats_by_track.items()}
        for name, buffer in self._jitter.items():
            out[name]["jitter"] = buffer.counters.as_dict()
        for name, playout in self._playout.items():
            out[name]["playout_ms"] = round(playout.delay_s * 1e3, 1)
            out[name]["playout_max_ms"] = round(playout.delay_max_s * 1e3, 1)
        if self._parity is not None:
            out["fec"] = {**self._parity.figures(), "errors": getattr(self._parity, "errors", 0)}
        out["infos_bad"] = self.infos_bad
        out["tracks_started"] = self.tracks_started
        return out
