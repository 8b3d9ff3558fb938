"""Every place where humantele reaches into aiortc's private state, kept in this one module.

aiortc (1.16) has no supported way to do these three things, each needed for the video
(docs/video.md says why, with the measurements):

1. :func:`use_encoder`: give an ``RTCRtpSender`` our encoder. aiortc makes its own on the
   first frame, with libvpx options that leave stale blocks in a grey image (the frame counter
   failed to read on ~25 % of US frames) and bit-rate limits fixed in the module
   (``humantele.media.encoders``). Set before the sender's first frame, ours is used, and
   aiortc still drives it: keyframes on PLI/FIR (``encode(frame, force_keyframe)``) and REMB
   (``encoder.target_bitrate = ...``).
2. :func:`use_jitter_buffer`: give an ``RTCRtpReceiver`` a jitter buffer whose delay is
   bounded (``humantele.media.jitter``); aiortc's waits for a lost packet until 512 packets
   have piled up and then stays that far behind.
3. :func:`newest_frame`: the newest decoded frame of a remote track, dropping the older ones
   queued while the event loop was held up (aiortc's track has only ``recv()``, one by one).
4. :class:`EncodedFrameTap`: the encoded frames as they leave the jitter buffer for aiortc's
   decoder thread (depacketised, before decoding: a VP8 frame or an H.264 access unit in
   Annex B), with their RTP timestamp as received, for the recording. It wraps the jitter
   buffer given to :func:`use_jitter_buffer`; aiortc rewrites the frame's timestamp only after
   ``add`` returns (so a released frame object kept by ``on_release`` carries the pts its
   decoded frame will have once ``add`` has returned).
5. :func:`request_keyframe`: send a PLI for a received stream (the console forwards the
   encoded frames to a page, whose decoder must start at a keyframe; the follower's encoders
   make keyframes only when asked).
6. :func:`request_retransmission`: send a NACK for packets still missing (aiortc's receiver
   NACKs a gap when it first shows and again only when a later gap shows; on a lossy link
   the NACK or its retransmission is often lost too).
7. :func:`forget_missing`: stop aiortc's receiver asking for packets the jitter buffer gave
   up on (its NACK generator lists every packet still missing in each NACK, until 128 later
   packets have come: retransmissions of frames already dropped, on a thin link).
8. :func:`pace_sender`: pace what a sender's transport sends (``humantele.media.pacer``):
   aiortc sends each frame's packets at once, and a thin link's queue drops the burst.
9. :func:`repeat_nacks`: send each NACK a receiver sends twice, a few ms apart: a lost NACK
   is a repair asked for a round trip late, past the playout delay on a thin link.
10. :func:`protect_sender`: after each frame of a protected stream, send a parity packet
    (``humantele.media.fec``) through the same paced send; :func:`sender_ssrc` says which
    stream a sender's is.
11. :func:`receive_parity`: take the parity packets out of a receiver's transport before
    aiortc's RTP router drops them (unknown SSRC and payload type), and feed the packets
    they rebuild to the receive path as if they had arrived; :func:`hold_nacks` holds a
    NACK for a packet whose parity may still come (a rebuilt packet is not asked for).

``tests/media/test_aiortc_hooks.py`` fails if aiortc renames or retypes what these touch.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from aiortc import RTCRtpReceiver, RTCRtpSender
from aiortc.codecs.base import Encoder
from aiortc.jitterbuffer import JitterBuffer

_SENDER_ENCODER = "_RTCRtpSender__encoder"
_RECEIVER_JITTER = "_RTCRtpReceiver__jitter_buffer"
_TRACK_QUEUE = "_queue"
_RECEIVER_PLI = "_send_rtcp_pli"
_RECEIVER_NACK = "_send_rtcp_nack"
_TRANSPORT_SEND_RTP = "_send_rtp"
_RECEIVER_NACK_GENERATOR = "_RTCRtpReceiver__nack_generator"
_PACER = "_humantele_pacer"
_PARITY = "_humantele_parity"  # the ParityEncoder a transport's sends pass
_SEND_WRAPPED = "_humantele_send_wrapped"
_TRANSPORT_HANDLE_RTP = "_handle_rtp_data"
_PARITY_DECODER = "_humantele_parity_decoder"
_SENDER_SSRC = "_ssrc"
log = logging.getLogger(__name__)


class AiortcChanged(RuntimeError):
    """aiortc no longer has the private attribute a hook relies on (see the module doc)."""


def _check(obj: object, name: str, expected: tuple[type, ...] | type | None) -> None:
    if not hasattr(obj, name):
        raise AiortcChanged(f"{type(obj).__name__} has no {name} (aiortc changed)")
    value = getattr(obj, name)
    if expected is not None and not isinstance(value, expected):
        raise AiortcChanged(f"{type(obj).__name__}.{name} is a {type(value).__name__}")


def use_encoder(sender: RTCRtpSender, encoder: Encoder) -> None:
    """Make ``sender`` encode with ``encoder`` (call before its first frame)."""
    _check(sender, _SENDER_ENCODER, (type(None), Encoder))
    setattr(sender, _SENDER_ENCODER, encoder)


def sender_encoder(sender: RTCRtpSender) -> Encoder | None:
    """The encoder ``sender`` uses (None before its first frame unless one was given)."""
    _check(sender, _SENDER_ENCODER, (type(None), Encoder))
    return getattr(sender, _SENDER_ENCODER)


def use_jitter_buffer(receiver: RTCRtpReceiver, buffer: Any) -> None:
    """Make ``receiver`` assemble frames with ``buffer`` (call before packets arrive);
    ``buffer.add(packet) -> (pli, JitterFrame | None)`` as aiortc's ``JitterBuffer``."""
    _check(receiver, _RECEIVER_JITTER, JitterBuffer)
    setattr(receiver, _RECEIVER_JITTER, buffer)


def newest_frame(track: Any, frame: Any, older: list | None = None) -> tuple[Any, int]:
    """``frame`` (just taken with ``await track.recv()``) or, if newer decoded frames are
    already waiting in the track's queue, the newest of them: (frame, frames skipped). The
    frame is None if the track ended meanwhile. ``older``: the skipped frames are appended
    to it, oldest first."""
    _check(track, _TRACK_QUEUE, None)
    queue = getattr(track, _TRACK_QUEUE)
    skipped = 0
    while queue.qsize() > 0:
        newer = queue.get_nowait()
        if newer is None:  # the track ended
            return None, skipped
        skipped += 1
        if older is not None:
            older.append(frame)
        frame = newer
    return frame, skipped


def request_keyframe(receiver: RTCRtpReceiver, ssrc: int) -> Any:
    """Ask the sender of stream ``ssrc`` on ``receiver`` for a keyframe (an RTCP PLI); the
    coroutine that sends it (schedule it on the loop)."""
    _check(receiver, _RECEIVER_PLI, None)
    return getattr(receiver, _RECEIVER_PLI)(ssrc)


def request_retransmission(receiver: RTCRtpReceiver, ssrc: int, lost: list[int]) -> Any:
    """Ask the sender of stream ``ssrc`` on ``receiver`` to send packets ``lost`` (16-bit
    sequence numbers) again (an RTCP NACK); the coroutine that sends it."""
    _check(receiver, _RECEIVER_NACK, None)
    return getattr(receiver, _RECEIVER_NACK)(ssrc, sorted(lost))


class EncodedFrameTap:
    """A jitter buffer (``add(packet) -> (pli, frame or None)``) that also hands each frame it
    releases to ``on_frame(data, rtp_timestamp)`` (bytes as aiortc will decode them; the RTP
    timestamp, 90 kHz, as the sender set it). ``on_frame`` runs on the event loop, inside
    aiortc's packet handler: it must only queue. Its failures are logged once and counted in
    ``tap_errors``, never raised into aiortc's receive path. ``on_frame`` may be None;
    ``on_release(frame)``, if given, gets the released frame object itself (its
    ``timestamp`` becomes the decoded frame's pts once ``add`` has returned). ``ssrc``: the
    stream's, from the last packet (for a keyframe request)."""

    def __init__(
        self,
        buffer: Any,
        on_frame: Callable[[bytes, int], Any] | None,
        on_release: Callable[[Any], Any] | None = None,
    ) -> None:
        self.buffer = buffer
        self.on_frame = on_frame
        self.on_release = on_release
        self.tapped = 0
        self.tap_errors = 0
        self.ssrc: int | None = None
        self.on_nack: Callable[[int, list[int]], Any] | None = None  # (ssrc, lost seqs)
        self.on_give_up: Callable[[list[int]], Any] | None = None  # (seqs given up)

    def poll(self) -> None:
        """Between packets: the buffer's own timed work (its re-asks, if it has a ``poll``),
        and the NACKs it gives sent."""
        poll = getattr(self.buffer, "poll", None)
        if poll is not None:
            poll()
            self._flush()

    def add(self, packet: Any) -> tuple[bool, Any]:
        self.ssrc = getattr(packet, "ssrc", None)
        pli, frame = self.buffer.add(packet)
        self._flush()
        if frame is not None:
            try:
                if self.on_release is not None:
                    self.on_release(frame)
                if self.on_frame is not None:
                    self.on_frame(frame.data, int(frame.timestamp))
                self.tapped += 1
            except Exception:  # noqa: BLE001 - the recording must never stop the video
                if not self.tap_errors:
                    log.exception("encoded frame tap failed (counting the rest)")
                self.tap_errors += 1
        return pli, frame

    def _flush(self) -> None:
        """Send the NACKs the buffer asks for and hand on the packets it gave up."""
        take = getattr(self.buffer, "take_nacks", None)
        if take is not None:
            lost = take()
            if lost and self.on_nack is not None and self.ssrc is not None:
                self.on_nack(self.ssrc, lost)
        take = getattr(self.buffer, "take_given_up", None)
        if take is not None:
            gone = take()
            if gone and self.on_give_up is not None:
                self.on_give_up(gone)

    def __getattr__(self, name: str) -> Any:  # counters, capacity... of the wrapped buffer
        return getattr(self.__dict__["buffer"], name)

    def __len__(self) -> int:
        return len(self.buffer)


def forget_missing(receiver: RTCRtpReceiver, seqs: list[int]) -> int:
    """Stop ``receiver`` asking (NACK) for packets ``seqs`` (16-bit sequence numbers); how
    many it was still asking for."""
    _check(receiver, _RECEIVER_NACK_GENERATOR, None)
    generator = getattr(receiver, _RECEIVER_NACK_GENERATOR)
    missing = getattr(generator, "missing", None)
    if not isinstance(missing, set):
        return 0
    before = len(missing)
    missing.difference_update(seqs)
    return before - len(missing)


def _count_failure(obj: Any, what: str) -> None:
    """In an ``except`` block: ``obj`` failed; logged the first time (with the traceback),
    counted in ``obj.errors`` every time."""
    if not getattr(obj, "errors", 0):
        log.exception("%s failed (counting the rest)", what)
    obj.errors = getattr(obj, "errors", 0) + 1


def _wrap_send(transport: Any) -> None:
    """Make ``transport``'s ``_send_rtp`` pass the pacer and the parity encoder set on it
    (:func:`pace_sender`, :func:`protect_sender`); once per transport."""
    _check(transport, _TRANSPORT_SEND_RTP, None)
    if getattr(transport, _SEND_WRAPPED, False):
        return
    send = getattr(transport, _TRANSPORT_SEND_RTP)

    async def paced(data: bytes) -> None:
        current = getattr(transport, _PACER, None)
        if current is not None and await current.before_send(data) is False:
            return
        await send(data)
        after = getattr(current, "after_send", None)
        if after is not None:
            after(data, send)
        parity = getattr(transport, _PARITY, None)
        if parity is not None:
            try:
                extra = parity.protect(data)
            except Exception:  # noqa: BLE001 - the parity must never stop the media
                _count_failure(parity, "parity encoder")
                extra = []
            for p in extra:
                await paced(p)  # paced and counted as media (its own SSRC, never parity'd)

    setattr(transport, _TRANSPORT_SEND_RTP, paced)
    setattr(transport, _SEND_WRAPPED, True)


def pace_sender(sender: RTCRtpSender, pacer: Any) -> None:
    """Make every RTP and RTCP packet ``sender``'s transport sends (its own and any other
    sender's on the same transport, as with BUNDLE) wait ``await pacer.before_send(data)``
    first (the plain packet, before SRTP), and not be sent if that returns False; after it
    is sent, ``pacer.after_send(data, send)`` (if the pacer has it) may send it again with
    ``send``, the transport's own. Once per transport; a later call gives it this ``pacer``
    instead."""
    transport = sender.transport
    _wrap_send(transport)
    setattr(transport, _PACER, pacer)


def protect_sender(sender: RTCRtpSender, encoder: Any) -> None:
    """After each RTP packet ``sender``'s transport sends (any sender's on it), send the
    packets ``encoder.protect(data)`` returns (``humantele.media.fec.ParityEncoder``: a
    parity at a protected frame's end) through the same paced send (the pacer, if any, counts
    them against its rate). None: no parity. Once per transport; a later call replaces it."""
    transport = sender.transport
    _wrap_send(transport)
    setattr(transport, _PARITY, encoder)


def sender_ssrc(sender: RTCRtpSender) -> int:
    """The SSRC of the media stream ``sender`` sends."""
    _check(sender, _SENDER_SSRC, int)
    return int(getattr(sender, _SENDER_SSRC))


def receive_parity(receiver: RTCRtpReceiver, decoder: Any) -> None:
    """Make ``receiver``'s transport (and so every receiver's on it, as with BUNDLE) hand each
    plain RTP packet it receives to ``decoder`` (``humantele.media.fec.ParityDecoder``):
    parity packets (``fec.is_parity``) to ``decoder.parity(data)`` instead of aiortc's router
    (which drops them), the others to aiortc first and then to ``decoder.packet(data)``; the
    packets either returns (rebuilt) go to aiortc's receive path as if they had arrived, with
    the arrival time of the packet that let them be rebuilt. Call before packets arrive, on
    each transport the receiver may use (the expert offers: with BUNDLE the first
    transceiver's carries all). The decoder's failures are logged once and counted in
    ``decoder.errors``, never raised into aiortc."""
    from humantele.media.fec import is_parity

    transport = receiver.transport
    _check(transport, _TRANSPORT_HANDLE_RTP, None)
    if getattr(transport, _PARITY_DECODER, None) is None:
        handle = getattr(transport, _TRANSPORT_HANDLE_RTP)

        async def handled(data: bytes, arrival_time_ms: int) -> None:
            current = getattr(transport, _PARITY_DECODER, None)
            parity = is_parity(data)
            if not parity:
                await handle(data, arrival_time_ms)
            if current is None:
                return
            try:
                rebuilt = current.parity(data) if parity else current.packet(data)
            except Exception:  # noqa: BLE001 - the parity must never stop the media
                _count_failure(current, "parity decoder")
                return
            for p in rebuilt:
                await handle(p, arrival_time_ms)

        setattr(transport, _TRANSPORT_HANDLE_RTP, handled)
    setattr(transport, _PARITY_DECODER, decoder)


HOLD_STEP_S = 0.005  # a held NACK looks again this often whether its parity came (s)


def hold_nacks(
    receiver: RTCRtpReceiver,
    decoder: Any,
    hold_s: float | Callable[[], float],
    on_held: Callable[[int], Any] | None = None,
    sleep: Callable[[float], Awaitable[object]] = asyncio.sleep,
) -> None:
    """Make every NACK ``receiver`` sends leave out the packets ``decoder.recovered(ssrc,
    seq)`` (rebuilt from a parity) and hold back, up to ``hold_s`` (s, or a function giving
    it at each NACK; in a task), those for
    which ``decoder.awaits_parity(ssrc, seq)`` (a protected stream whose parity covering
    them has not come yet: aiortc NACKs a gap at once, a few ms before the frame's parity
    arrives); then ask for those still not rebuilt. ``on_held(n)``: after each hold, the
    packets it spared asking for. Wrap after :func:`repeat_nacks` (its copies then carry
    only what is still missing)."""
    _check(receiver, _RECEIVER_NACK, None)
    send = getattr(receiver, _RECEIVER_NACK)
    tasks: set[asyncio.Task] = set()

    def wanted(ssrc: int, lost: list[int]) -> list[int]:
        return [s for s in lost if not decoder.recovered(ssrc, s)]

    async def later(ssrc: int, held: list[int], hold: float) -> None:
        waited = 0.0
        while waited < hold and any(decoder.awaits_parity(ssrc, s) for s in held):
            step = min(HOLD_STEP_S, hold - waited)
            await sleep(step)
            waited += step
        still = wanted(ssrc, held)
        if on_held is not None:
            on_held(len(held) - len(still))
        if still:
            try:
                await send(ssrc, still)
            except Exception:  # noqa: BLE001 - a closed connection: nothing to ask
                return

    async def held_back(ssrc: int, lost: list[int]) -> None:
        try:
            lost = wanted(ssrc, lost)
            hold = float(hold_s() if callable(hold_s) else hold_s)
            held = [s for s in lost if decoder.awaits_parity(ssrc, s)] if hold > 0 else []
        except Exception:  # noqa: BLE001 - a decoder fault: ask as aiortc would
            log.exception("NACK hold failed; asking at once")
            held, hold = [], 0.0
        now = [s for s in lost if s not in held]
        if now:
            await send(ssrc, now)
        if held:
            task = asyncio.ensure_future(later(ssrc, held, hold))
            tasks.add(task)
            task.add_done_callback(tasks.discard)

    held_back.held_tasks = tasks  # type: ignore[attr-defined] - for tests, to wait for holds
    if hasattr(send, "tasks"):  # repeat_nacks's copies, still there to wait for
        held_back.tasks = send.tasks  # type: ignore[attr-defined]
    setattr(receiver, _RECEIVER_NACK, held_back)


def repeat_nacks(
    receiver: RTCRtpReceiver,
    after_s: float,
    on_repeat: Callable[[], Any] | None = None,
    sleep: Callable[[float], Awaitable[object]] = asyncio.sleep,
) -> None:
    """Make every NACK ``receiver`` sends (aiortc's own at a new gap, and
    :func:`request_retransmission`'s) leave a second time ``after_s`` (s) after the first, in
    a task (the receive path does not wait); ``on_repeat()`` after each copy sent. The sender
    answers the copy only if the first was lost (``humantele.media.pacer`` does not repeat a
    retransmission within a round trip)."""
    _check(receiver, _RECEIVER_NACK, None)
    send = getattr(receiver, _RECEIVER_NACK)
    tasks: set[asyncio.Task] = set()

    async def copy(media_ssrc: int, lost: list[int]) -> None:
        await sleep(after_s)
        try:
            await send(media_ssrc, lost)
        except Exception:  # noqa: BLE001 - a closed connection: the copy is only a copy
            return
        if on_repeat is not None:
            on_repeat()

    async def twice(media_ssrc: int, lost: list[int]) -> None:
        await send(media_ssrc, lost)
        task = asyncio.ensure_future(copy(media_ssrc, list(lost)))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    twice.tasks = tasks  # type: ignore[attr-defined] - for tests, to wait for the copies
    setattr(receiver, _RECEIVER_NACK, twice)
