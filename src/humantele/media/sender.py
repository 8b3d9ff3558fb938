"""The follower's side of the video: one capture thread per source, one track per source on
every peer connection, frames handed over through a latest-frame slot, the POV degraded first.

Per source, a capture (:class:`~humantele.media.capture.VideoCapture`, its own thread, or in
the video process, :mod:`humantele.media.process`) reads the source (which blocks like a
camera), scales, stamps and converts it to YUV 4:2:0 and puts the frame in a
:class:`~humantele.media.slot.LatestSlot`, recording its timestamps. On each new peer connection
:meth:`VideoSender.attach` puts a fresh :class:`SlotTrack` on each video transceiver of the
expert's offer (first ``us``, then ``pov``) and opens the ``video`` data channel (id 3,
unordered, no retransmissions); a track's ``recv()`` (called by aiortc's sender when the
encoder is ready) takes the newest frame, never an old one, and sends its
:class:`~humantele.media.frameinfo.FrameInfo`. Frame ``pts`` is the capture time on a 90 kHz
clock, so the RTP timestamps keep the capture spacing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import av
from aiortc import MediaStreamTrack, RTCPeerConnection
from aiortc.sdp import SessionDescription

from humantele.media.aiortc_hooks import pace_sender, protect_sender, sender_ssrc, use_encoder
from humantele.media.capture import (
    CapturedFrame,
    Record,
    VideoCapture,
)
from humantele.media.config import TRACKS, FollowerVideoConfig
from humantele.media.encoders import ENCODERS, make_encoder
from humantele.media.fec import ParityEncoder
from humantele.media.frameinfo import FrameInfo
from humantele.media.pacer import PACE_FACTOR, Pacer
from humantele.media.policy import POV_OFF_PERIOD_S, DegradationPolicy, Health, split_budget
from humantele.runtime.child import Restarter
from humantele.video.sources import make_video_source

if TYPE_CHECKING:
    from humantele.video.scene import Scene

log = logging.getLogger(__name__)

VIDEO_CHANNEL_ID = 3  # the link's channels are 0-2
MAX_INFO_BUFFERED = 4096  # bytes of frame records allowed to wait in the channel
# The parity's share of the US's budget before it is measured: a US frame at the 500 kbit/s
# floor is 3-4 packets and gets one parity (docs/video.md, issue 31's sixth pass)
PARITY_SHARE_START = 0.3
PARITY_SHARE_MIN_BYTES = 100_000  # protected bytes before the measured share is used

# The link is short when the expert's estimate (REMB sum) is below this share of what the
# tracks actually sent over the last check: its estimator then says the link is overused (it
# bids 0.85 of the rate received); above it, the estimate may just not have grown yet (a
# session's start) or the tracks send less than their targets (a starved capture).
SHORT_FRACTION = 0.95
# The estimate is stale, not the link, when it is below this share of what reached the expert
# over the last check: aiortc's estimator sets its estimate to the rate it receives 3 s after
# the first packet, and lowers it to 0.85 of that rate on each overuse, so a session whose US
# starts dark (the probe not yet on the patient: ~40 kbit/s) starts from ~40 kbit/s and climbs
# 8 % a second (~40 s to 1 Mbit/s). Measured at 15 % loss: the REMB sum at 145-200 kbit/s
# for the whole scan while 600 kbit/s got through; spent as the link, it halved the US frame
# rate at its floor bit rate and turned the POV off. A stale estimate stays stale until it has
# climbed to what gets through, or falls again in step with it (a fresh overuse).
STALE_FRACTION = 0.5
# The tracks are application-limited when they sent less than this share of what their
# encoders were asked for: then the estimate follows what they send, not the link.
APP_LIMITED_FRACTION = 0.5


class SlotTrack(MediaStreamTrack):
    """A video track that gives the newest captured frame each time the encoder asks."""

    kind = "video"

    def __init__(
        self, name: str, capture: VideoCapture, on_sent: Callable[[str, CapturedFrame], None]
    ) -> None:
        super().__init__()
        self.name = name
        self.capture = capture
        self.on_sent = on_sent
        self._last = capture.slot.number  # start with the next frame, not an old one

    async def recv(self) -> av.VideoFrame:
        if self.readyState != "live":
            from aiortc.mediastreams import MediaStreamError

            raise MediaStreamError
        self._last, cf = await self.capture.slot.get_newer(self._last)
        self.capture.sent += 1
        self.on_sent(self.name, cf)
        return cf.frame


def offered_codecs(pc: RTCPeerConnection) -> list[str | None]:
    """The codec each video m-line of the remote offer puts first (its MIME type, e.g.
    ``video/VP8``; None when it offers none we encode), in m-line order."""
    out: list[str | None] = []
    if pc.remoteDescription is None:
        return out
    for media in SessionDescription.parse(pc.remoteDescription.sdp).media:
        if media.kind == "video":
            mimes = [c.mimeType for c in media.rtp.codecs]
            out.append(next((m for m in mimes if m.lower() in ENCODERS), None))
    return out


def link_estimate(
    remb: float, last_remb: float | None, delivered: float | None, stale: bool
) -> tuple[float, bool]:
    """What the link carries (kbit/s) and whether the REMB sum ``remb`` is stale, given the
    sum at the last check (``last_remb``), what reached the expert since (``delivered``, None
    at the first check) and whether the estimate was stale then. Stale below
    :data:`STALE_FRACTION` of what got through; no longer once it has grown to
    :data:`SHORT_FRACTION` of it, or fell since the last check to within that band (aiortc
    lowers its estimate only on an overuse, to 0.85 of what it receives: a real one). A stale
    estimate is no bound: the link is what got through."""
    if delivered is None or delivered <= 0:
        return remb, False
    if remb < STALE_FRACTION * delivered:
        stale = True
    elif remb >= SHORT_FRACTION * delivered or (last_remb is not None and remb < last_remb):
        stale = False
    return (max(remb, delivered) if stale else remb), stale


class VideoSender:
    """The follower's two tracks. ``scene`` feeds the sim sources; ``record(topic, t, payload)``
    records (any thread), ``clock`` is the follower's (ClockSync's) clock."""

    def __init__(
        self,
        config: FollowerVideoConfig,
        scene: Scene | None = None,
        record: Record | None = None,
        patient: Any = None,
    ) -> None:
        self.config = config
        self.record = record
        self.policy = DegradationPolicy(config.degrade)
        sources = {"us": config.us, "pov": config.pov}
        rates = {"us": config.record_us_hz, "pov": config.record_pov_hz}
        self.process: Any = None
        self.restarter: Restarter | None = None  # of the video process, once it runs
        if config.process:  # the sources in a video process (humantele.media.process)
            from humantele.media.process import ProcessVideo

            specs = {}
            for name in TRACKS:
                c = sources[name]
                w, h = c.width, c.height
                if getattr(c, "backend", "") != "sim":  # a device may give another size
                    w, h = max(w, 1920), max(h, 1080)
                specs[name] = {
                    "config": c, "stamp_counter": config.stamps(name), "fps": float(c.fps) or 30.0,
                    "record_hz": rates[name], "jpeg_quality": config.jpeg_quality,
                    "size": (w, h),
                }  # fmt: skip
            self.process = ProcessVideo(specs, patient, record, config.process_nice)
            self.captures: dict[str, Any] = self.process.captures
            self.restarter = Restarter("video", self._restart_process, first_s=1.0, max_s=30.0)
        else:
            self.captures = {
                name: VideoCapture(
                    name,
                    make_video_source(sources[name], scene),
                    stamp_counter=config.stamps(name),
                    record=record,
                    record_hz=rates[name],
                    jpeg_quality=config.jpeg_quality,
                )
                for name in TRACKS
            }
        self.pov_fps = float(self.captures["pov"].source.fps)
        self.us_fps = float(self.captures["us"].source.fps)
        self.infos_sent = 0
        self.infos_dropped = 0
        self.attached = 0
        self.link: dict[str, Any] = {}  # the last link_report
        self._sent_at: tuple[float, int] | None = None  # (t s, bytes sent) at the last check
        self._remb_kbps: float | None = None  # the REMB sum at the last check
        self.remb_stale = False  # the REMB sum is stale: the link is what got through
        self.link_trusted = False  # the last check measured the link (caps and levels)
        self._asked_kbps = 0.0  # the encoders' targets summed at the last check
        self._channel: Any = None
        self.pacer: Pacer | None = None  # the current peer connection's
        self.parity: ParityEncoder | None = None  # the current peer connection's (config fec)
        self._senders: dict[str, Any] = {}
        self._encoders: dict[str, Any] = {}  # the current peer connection's, per track
        self._last_counts: dict[str, int] = {"captured": 0, "sent": 0}
        self._last_check: float | None = None
        self._started = False
        self._closed = False
        self._policy_t, self._policy_late = -math.inf, 0  # the last check: time, late ticks
        self._policy_frames = 0  # tracker frames measured by the last check
        self._tracker_measured = False  # the tracker measured in the window before the last

    def publish_scene(self, snapshot: Any) -> None:
        """The sim world's latest snapshot, for the video process (threads call ``scene``)."""
        if self.process is not None:
            self.process.publish_scene(snapshot)

    def open(self) -> None:
        """Open both sources (blocks); VideoSourceUnavailable names the one that failed."""
        if self.process is not None:
            from humantele.media.process import VideoProcessDied

            try:
                self.process.open()
            except VideoProcessDied as exc:  # started anyway: the restarter brings it back
                log.error("video: %s", exc)
            return
        opened = []
        try:
            for cap in self.captures.values():
                cap.open()
                opened.append(cap)
        except BaseException:
            for cap in opened:
                with contextlib.suppress(Exception):
                    cap.source.close()
            raise

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._closed:  # closed while opening: the daemon is stopping
            return
        for cap in self.captures.values():
            cap.start(loop)
        self._started = True

    async def _restart_process(self) -> None:
        """A new video process for the dead one, off the loop (it takes seconds to open)."""
        await asyncio.to_thread(self.process.restart)

    async def settle(self) -> None:
        """After :meth:`close`: a restart in flight has ended (it saw the close)."""
        if self.restarter is not None:
            await self.restarter.close()

    def close(self) -> None:
        self._closed = True
        if self.restarter is not None:
            self.restarter.closed = True  # no new restart; one in flight sees the close
        if self.process is not None:
            self.process.close()
        else:
            for cap in self.captures.values():
                cap.stop()
        self._started = False

    # --- per peer connection ------------------------------------------------------------------

    def attach(self, pc: RTCPeerConnection) -> None:
        """On a new peer connection (after the expert's offer is set, before the answer): the
        ``video`` channel, and a fresh track on each video transceiver the offer has."""
        self._channel = pc.createDataChannel(
            "video", negotiated=True, id=VIDEO_CHANNEL_ID, ordered=False, maxRetransmits=0
        )
        self._senders, self._encoders = {}, {}
        self.pacer = Pacer(
            self._pace_rate, rtt_s=self._rtt_s, loss=lambda: self.link.get("loss"),
            duplicate=self.config.duplicate_repairs,
        )  # fmt: skip
        protected: set[int] = set()  # the SSRCs whose frames get a parity
        self.parity = None
        if self.config.fec:
            self.parity = ParityEncoder(protected.__contains__, group=self.config.fec_group)
        self._sent_at = None
        self._remb_kbps, self.remb_stale, self._asked_kbps = None, False, 0.0
        videos = [t for t in pc.getTransceivers() if t.kind == "video"]
        limits = {"us": self.config.us_bitrate, "pov": self.config.pov_bitrate}
        for name, transceiver, mime in zip(TRACKS, videos, offered_codecs(pc), strict=False):
            transceiver.sender.replaceTrack(SlotTrack(name, self.captures[name], self._on_sent))
            transceiver.direction = "sendonly"
            self._senders[name] = transceiver.sender
            if mime is not None:  # our encoder, with this track's bit-rate limits
                src = self.config.us if name == "us" else self.config.pov
                size = (int(src.width), int(src.height))  # opened at it: smaller is live
                self._encoders[name] = make_encoder(mime, limits[name], max_size=size)
                use_encoder(transceiver.sender, self._encoders[name])
            pace_sender(transceiver.sender, self.pacer)
            if self.parity is not None and (name == "us" or self.config.fec_pov):
                protected.add(sender_ssrc(transceiver.sender))
                protect_sender(transceiver.sender, self.parity)
        self.attached += 1

    def parity_share(self) -> float:
        """The parity's bytes over the media bytes they protect (0 without parity; before
        :data:`PARITY_SHARE_MIN_BYTES` are protected, :data:`PARITY_SHARE_START`): the share
        of the US's budget left for the parity, which the expert's estimate (REMB, of the
        media streams) does not count."""
        if self.parity is None:
            return 0.0
        c = self.parity.counters
        if c.protected_bytes < PARITY_SHARE_MIN_BYTES:
            return PARITY_SHARE_START
        return min(1.0, c.parity_bytes / c.protected_bytes)

    def _rtt_s(self) -> float | None:
        """The link's round trip (s) as the encoders were last told it, or None."""
        rtts = [e.rtt_s for e in list(self._encoders.values()) if getattr(e, "rtt_s", None)]
        return max(rtts) if rtts else None

    def _pace_rate(self) -> float:
        """The pacer's rate (bit/s): :data:`~humantele.media.pacer.PACE_FACTOR` times the
        encoders' targets summed."""
        return PACE_FACTOR * sum(e.target_bitrate for e in list(self._encoders.values()))

    def _on_sent(self, name: str, cf: CapturedFrame) -> None:
        ch = self._channel
        if ch is None or ch.readyState != "open" or ch.bufferedAmount > MAX_INFO_BUFFERED:
            self.infos_dropped += 1
        else:
            try:
                ch.send(FrameInfo(name, cf.seq, cf.t_capture).encode())
                self.infos_sent += 1
            except Exception:
                self.infos_dropped += 1
        if self.record is not None:
            self.record(
                "/follower/video_frame",
                cf.t_capture,
                {"stream": name, "seq": cf.seq, "event": "sent", "width": cf.width,
                 "height": cf.height},
            )  # fmt: skip

    # --- the degradation policy -------------------------------------------------------------

    async def loss(self) -> float | None:
        """The worst fraction lost the expert reports (RTCP) for either track, or None."""
        return (await self.link_report())["loss"]

    async def link_report(self) -> dict[str, Any]:
        """What the link carries, from the expert's RTCP: ``loss`` (the worst fraction lost of
        either track's last receiver report, or None), ``rtt_s`` (the round trip aiortc
        measures from them, or None), ``jitter_s`` (the worst interarrival jitter, s, or None),
        ``link_kbps`` (the expert's REMB of both tracks, summed, kbit/s; None until both
        came), ``bytes_sent`` (both tracks' RTP bytes sent so far)."""
        worst = rtt = jitter = None
        sent = 0
        for sender in list(self._senders.values()):
            try:
                report = await sender.getStats()
            except Exception:
                continue
            for s in report.values():
                if getattr(s, "type", "") == "outbound-rtp":
                    sent += int(getattr(s, "bytesSent", 0) or 0)
                if getattr(s, "type", "") != "remote-inbound-rtp":
                    continue
                f = getattr(s, "fractionLost", None)  # RTCP's 8-bit fraction, /256
                if f is not None:
                    worst = f / 256.0 if worst is None else max(worst, f / 256.0)
                r = getattr(s, "roundTripTime", None)
                if r is not None and math.isfinite(r) and r >= 0:
                    rtt = r if rtt is None else max(rtt, r)
                j = getattr(s, "jitter", None)  # RTP clock units (90 kHz)
                if j is not None and j >= 0:
                    j = j / 90_000.0
                    jitter = j if jitter is None else max(jitter, j)
        rembs = [e.remb for e in self._encoders.values()]
        link = sum(rembs) / 1000.0 if len(rembs) == 2 and None not in rembs else None
        return {"loss": worst, "rtt_s": rtt, "jitter_s": jitter, "link_kbps": link,
                "bytes_sent": sent}  # fmt: skip

    def _spend_link(self, t: float, report: dict[str, Any]) -> None:
        """The link's budget split between the tracks (:func:`split_budget`): each encoder's
        share and floor, the levels it allows; each encoder told the round trip. The link is
        the expert's REMB sum, or what reached it when that estimate is stale
        (:func:`link_estimate`). Only a measured link (``link_trusted``: the estimate not
        stale, the tracks not application-limited, what got through known) caps the encoders
        and lowers levels; otherwise each encoder follows the estimate up to its track's start
        rate (an estimate can be as wrong upwards: measured 4.4 Mbit/s for the POV on a 1.5
        Mbit/s link), never below its floor, and levels may only climb."""
        for enc in self._encoders.values():
            if report["rtt_s"] is not None:
                enc.rtt_s = report["rtt_s"]
        remb = report["link_kbps"]
        if remb is None or not self.config.degrade.follow_link:
            return
        # what the tracks actually sent since the last check (kbit/s; a starved capture or
        # encoder sends less than its target, and the expert's estimate follows that)
        prev, self._sent_at = self._sent_at, (t, report["bytes_sent"])
        sending = None
        if prev is not None and t > prev[0] and report["bytes_sent"] >= prev[1]:
            sending = (report["bytes_sent"] - prev[1]) * 8 / 1000.0 / (t - prev[0])
        # what reached the expert of it: its estimate counts received bytes, and random loss
        # is not a short link (the stepped policy lowers the POV on loss)
        delivered = None if sending is None else sending * (1.0 - (report["loss"] or 0.0))
        link, self.remb_stale = link_estimate(remb, self._remb_kbps, delivered, self.remb_stale)
        self._remb_kbps = remb
        us_l, pov_l = self.config.us_bitrate, self.config.pov_bitrate
        p = self.policy
        budget = split_budget(link, us_l.min_kbps, us_l.max_kbps, pov_l.max_kbps,
                              p.link_level, p.link_us_level)  # fmt: skip
        short = delivered is not None and link < SHORT_FRACTION * delivered
        # the tracks sent far less than their encoders were asked for (a dark US, a starved
        # capture): neither the estimate nor what got through measured the link
        asked, self._asked_kbps = self._asked_kbps, sum(
            e.target_bitrate for e in self._encoders.values()) / 1000.0  # fmt: skip
        limited = sending is not None and sending < APP_LIMITED_FRACTION * asked
        self.link_trusted = delivered is not None and not (self.remb_stale or limited)
        p.apply_link(t, budget, short and self.link_trusted)
        us, pov = self._encoders.get("us"), self._encoders.get("pov")
        if not self.link_trusted:  # no bound measured: no more than each track's start rate
            for enc, lim in ((us, us_l), (pov, pov_l)):
                if enc is not None:
                    enc.set_budget(lim.start_kbps * 1000)
            return
        if us is not None:  # the parity rides on the same link: the US's share pays for it
            us_kbps = max(budget.us_floor_kbps, budget.us_kbps / (1.0 + self.parity_share()))
            us.set_budget(int(us_kbps * 1000), int(budget.us_floor_kbps * 1000))
        if pov is not None:
            pov.set_budget(int(max(budget.pov_kbps, 50.0) * 1000), int(min(
                budget.pov_kbps, pov_l.min_kbps) * 1000))  # fmt: skip

    def tick(
        self, t: float, late_ticks: int, tracker_frames: int = 0, tracker_hz: float = 0.0
    ) -> None:
        """From the daemon's tick (``t``: its monotonic clock, s; ``late_ticks``: its count so
        far): a dead video process restarted (:class:`~humantele.runtime.child.Restarter`);
        once a second, the degradation policy (:meth:`check`) in a task, with the tracker's
        frames measured (``tracker_frames``, a count so far) against its rate (Hz): not in the
        window the tracker started measuring in (its start is not contention)."""
        if self.restarter is not None and self._started:
            self.restarter.check(t, self.process.alive, self.process.exitcode)
        if t - self._policy_t < 1.0:
            return
        dt = 1.0 if self._policy_t == -math.inf else t - self._policy_t
        late = (late_ticks - self._policy_late) / dt
        frames = tracker_frames - self._policy_frames
        first = self._policy_t == -math.inf
        # A window in which the tracker started measuring (the sensing process came up, or
        # back) is not contention: a ratio only once it measured through a whole window.
        steady = frames > 0 and self._tracker_measured and not first
        ratio = frames / (tracker_hz * dt) if steady and tracker_hz > 0 else None
        self._tracker_measured = frames > 0
        self._policy_t, self._policy_late = t, late_ticks
        self._policy_frames = tracker_frames
        task = asyncio.ensure_future(self.check(t, late, ratio))
        task.add_done_callback(_log_check_error)

    async def check(
        self, t: float, late_ticks_per_s: float, tracker_ratio: float | None = None
    ) -> int:
        """Once a second: the policy's inputs over the last window; applies the POV level and
        the US rate. US delivery is of the frames published (a US rate the policy lowered is
        not the encoder falling behind)."""
        us = self.captures["us"]
        published = us.published - self._last_counts["captured"]
        sent = us.sent - self._last_counts["sent"]
        self._last_counts = {"captured": us.published, "sent": us.sent}
        delivery = min(1.0, sent / published) if published >= 5 and self._senders else None
        report = await self.link_report()
        self.link = report
        health = Health(delivery, report["loss"], late_ticks_per_s, tracker_ratio)
        p = self.policy
        before = (p.pov_level, p.us_rate_level)
        p.update(t, health)
        self._spend_link(t, report)
        level = p.pov_level
        if (level, p.us_rate_level) != before:
            why = p.reason or "recovered"
            log.warning("video: POV level %d -> %d, US level %d -> %d (%s)", before[0], level,
                        before[1], p.us_rate_level, why)  # fmt: skip
        pov = self.captures["pov"]
        pov.scale = p.pov_scale
        factor = p.pov_rate_factor
        if p.pov_off:
            pov.max_fps = 1.0 / POV_OFF_PERIOD_S
        else:
            pov.max_fps = None if factor >= 1.0 else self.pov_fps * factor
        us_factor = self.policy.us_rate_factor
        us.max_fps = None if us_factor >= 1.0 else self.us_fps * us_factor
        return level

    def process_stats(self) -> dict[str, Any]:
        """The video process: alive, its state (``running``, ``down: ...``, ``restarting``),
        restarts, CPU seconds."""
        p, r = self.process, self.restarter
        assert p is not None and r is not None
        alive = p.alive
        state = r.state(time.monotonic(), alive) if self._started or r.closed else "starting"
        return {"alive": alive, "state": state, "restarts": r.restarts, "pid": p.pid,
                "cpu_s": p.cpu_seconds()}  # fmt: skip

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "process": None if self.process is None else self.process_stats(),
            "pov_level": self.policy.pov_level,
            "us_level": self.policy.us_rate_level,
            "pov_level_changes": self.policy.changes,
            "link_level_changes": self.policy.link_changes,
            "link": {
                k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.link.items()
            },  # fmt: skip
            "pov_level_reason": self.policy.reason,
            "remb_stale": self.remb_stale,
            "link_trusted": self.link_trusted,
            "infos_sent": self.infos_sent,
            "infos_dropped": self.infos_dropped,
            "pacer": None if self.pacer is None else self.pacer.figures(),
            "fec": None if self.parity is None else self.parity.counters.as_dict(),
        }
        for name, cap in self.captures.items():
            prep = sorted(cap.prepare_times)
            out[name] = {
                "captured": cap.captured,
                "sent": cap.sent,
                "overwritten": cap.slot.overwritten,
                "rate_skipped": cap.rate_skipped,
                "errors": cap.errors,
                "prepare_ms_p50": round(1e3 * prep[len(prep) // 2], 2) if prep else None,
                "invalid_scene": cap.source.counters.invalid,
            }
            encoder = self._encoders.get(name)
            if encoder is not None:
                out[name]["encoder"] = encoder.figures()
        return out


def _log_check_error(task: asyncio.Future) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("video: the degradation check failed: %s", task.exception())
