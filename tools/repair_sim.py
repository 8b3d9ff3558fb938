"""The US track's loss repair on a simulated lossy link, on a simulated clock (no CPU in it).

Issue 31's rural link (60 +- 20 ms one way, 3 % loss each way, the playout delay at its 250 ms
cap) froze the US 3-7 times a run:
a repair lost (its NACK or its retransmission) is a gap the expert's jitter buffer gives up,
a keyframe request and a freeze. On the shared machine a study's figures are mostly the CPU's
(docs/video.md, "Fifth pass"); this runs the repair path alone, with the real parts on a
hand-driven clock: the expert's ``BoundedJitterBuffer`` and aiortc's ``NackGenerator`` (the
NACK at each new gap, packets given up taken out of it), ``aiortc_hooks.repeat_nacks`` (each
NACK twice), and the follower's ``Pacer`` (no resend within 3/4 of a round trip; each
retransmission twice on a lossy link); with parity (``humantele.media.fec``, issue 31's
sixth pass) the follower's ``ParityEncoder`` after each frame (a parity per ``--fec-group``
packets) and the expert's ``ParityDecoder`` with ``aiortc_hooks.hold_nacks`` (a NACK for a
packet whose parity may still come waits for it, at most 30 ms). Modelled: the sender (20
fps, ``--packets`` a delta frame, three times that a keyframe, answered to a PLI after the
previous keyframe is a round trip old) and the link (each packet and each RTCP packet lost
with ``--loss`` each way, independently; one-way delay ``--delay-ms`` plus a jitter of
``--jitter-ms`` s.d. drawn every 50 ms, first in first out). A frame shows ``--playout-ms``
after its capture, or when the buffer releases it if later (in order). Not modelled: the
link's rate and queue, the playout delay's own adaptation, the POV.

    python tools/repair_sim.py --seconds 600 --seeds 1,2,3

prints, per variant (``--variants base,fec``: some only), the gaps given up, keyframe
requests, frozen share (a gap between released frames over max(3 frame intervals, 1
interval + 150 ms), as the study counts), the frame age p95 (capture to release), the
packets rebuilt from a parity and the parity's share of the bytes, summed or pooled over
the seeds.
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import itertools
import random
import struct

import numpy as np
from aiortc.rtcrtpreceiver import NackGenerator
from aiortc.rtp import RtpPacket

from humantele.media.aiortc_hooks import hold_nacks, repeat_nacks
from humantele.media.fec import ParityDecoder, ParityEncoder, is_parity
from humantele.media.jitter import BoundedJitterBuffer, vp8_is_keyframe
from humantele.media.pacer import Pacer
from humantele.media.receiver import parity_hold

FPS = 20.0
SSRC = 0x1234
KEY = b"\x00\x00\x00\x9d\x01\x2a" + bytes(4)  # a VP8 keyframe's first bytes (RFC 6386 9.1)
DELTA = b"\x01" + bytes(9)


class Sim:
    def __init__(
        self, args: argparse.Namespace, seed: int, dup: bool, renack: bool, fec: bool = False
    ) -> None:
        self.rng = random.Random(seed)
        self.a = args
        self.now = 0.0
        self.events: list = []
        self.order = itertools.count()
        self.last_arrival = {"fwd": 0.0, "rev": 0.0}
        self.jitter = {"fwd": (-1.0, 0.0), "rev": (-1.0, 0.0)}  # (drawn at, value)
        self.history: dict[int, tuple[int, bool, bytes]] = {}  # seq -> (ts, marker, data)
        self.seq = 0
        self.want_key = True
        self.last_key = -1.0
        rtt = 2 * args.delay_ms / 1e3
        self.pacer = Pacer(lambda: 1e12, clock=lambda: self.now, sleep=self.sleep,
                           rtt_s=lambda: rtt, duplicate=dup)  # fmt: skip
        self.buffer = BoundedJitterBuffer(vp8_is_keyframe, 0.1, clock=lambda: self.now,
                                          rtt=lambda: rtt)  # fmt: skip
        self.nacks = NackGenerator()
        self.rtcp = self  # the receiver whose _send_rtcp_nack repeat_nacks wraps
        if renack:
            repeat_nacks(self, 0.005, sleep=self.sleep)
        self.parity = self.decoder = None
        if fec:
            group = getattr(args, "fec_group", 8)
            self.parity = ParityEncoder(lambda ssrc: ssrc == SSRC, group=group)
            self.decoder = ParityDecoder(lambda: self.now, self.on_parity_event)
            hold = parity_hold(self.buffer)  # as the expert's receiver
            hold_nacks(self, self.decoder, hold, self.spared, sleep=self.sleep)
        self.released: list[tuple[float, float]] = []  # (release time, capture time)
        self.plis = 0

    # --- the clock ------------------------------------------------------------------------
    def at(self, t: float, what: str, data: object = None) -> None:
        heapq.heappush(self.events, (t, next(self.order), what, data))

    def sleep(self, s: float) -> asyncio.Future:
        fut = asyncio.get_running_loop().create_future()
        self.at(self.now + s, "wake", fut)
        return fut

    # --- the link -------------------------------------------------------------------------
    def cross(self, way: str, what: str, data: object) -> None:
        if self.rng.random() < self.a.loss / 100.0:
            return
        drawn, value = self.jitter[way]
        if self.now - drawn >= 0.05:
            value = self.rng.gauss(0.0, self.a.jitter_ms / 1e3)
            self.jitter[way] = (self.now, value)
        t = max(self.now + max(0.0, self.a.delay_ms / 1e3 + value), self.last_arrival[way])
        self.last_arrival[way] = t
        self.at(t, what, data)

    # --- the follower ---------------------------------------------------------------------
    async def send_rtp(self, data: bytes) -> None:  # the transport's own send
        self.cross("fwd", "rtp", data)

    async def paced(self, data: bytes) -> None:  # as aiortc_hooks.pace_sender's wrapper
        if await self.pacer.before_send(data) is False:
            return
        await self.send_rtp(data)
        self.pacer.after_send(data, self.send_rtp)
        if self.parity is not None:
            for p in self.parity.protect(data):
                await self.paced(p)

    def rtp(self, seq: int) -> bytes:
        ts, marker, payload = self.history[seq]
        header = struct.pack("!BBHII", 0x80, 96 | (marker << 7), seq & 0xFFFF, ts, SSRC)
        return header + payload

    async def frame(self, k: int) -> None:
        key = self.want_key and self.now - self.last_key >= 2 * self.a.delay_ms / 1e3
        if key:
            self.want_key, self.last_key = False, self.now
        n = self.a.packets * (3 if key else 1)
        ts = int(k * 90_000 / FPS) & 0xFFFFFFFF
        for i in range(n):
            first = (KEY if key else DELTA) if i == 0 else bytes(10)
            self.history[self.seq] = (ts, i == n - 1, first + bytes(1000))
            await self.paced(self.rtp(self.seq))
            self.seq += 1
        self.at(self.now + 1 / FPS, "frame", k + 1)

    async def on_nack(self, lost: list[int]) -> None:  # aiortc's sender: _retransmit each
        for seq in lost:
            if seq in self.history:
                await self.paced(self.rtp(seq))

    # --- the expert -----------------------------------------------------------------------
    async def _send_rtcp_nack(self, media_ssrc: int, lost: list[int]) -> None:
        self.cross("rev", "nack", list(lost))

    def spared(self, n: int) -> None:
        self.buffer.counters.fec_nacks_spared += n

    def on_parity_event(self, ssrc: int, what: str, seq: int) -> None:
        if what == "recovered":
            self.buffer.note_rebuilt(seq)

    async def on_rtp(self, data: bytes) -> None:  # as aiortc_hooks.receive_parity's wrapper
        if self.decoder is not None and is_parity(data):
            rebuilt = self.decoder.parity(data)
        else:
            await self.on_media(data)
            rebuilt = [] if self.decoder is None else self.decoder.packet(data)
        for p in rebuilt:
            await self.on_media(p)

    async def on_media(self, data: bytes) -> None:
        seq, ts = struct.unpack("!HI", data[2:8])
        p = RtpPacket(payload_type=96, marker=data[1] >> 7, sequence_number=seq,
                      timestamp=ts, ssrc=SSRC)  # fmt: skip
        p._data = data[12:]
        if self.nacks.add(p):
            await self.rtcp._send_rtcp_nack(SSRC, sorted(self.nacks.missing))
        pli, frame = self.buffer.add(p)
        await self.after_buffer(pli, frame)

    async def after_buffer(self, pli: bool, frame: object) -> None:
        lost = self.buffer.take_nacks()
        if lost:
            await self.rtcp._send_rtcp_nack(SSRC, lost)
        self.nacks.missing.difference_update(self.buffer.take_given_up())
        if pli:
            self.plis += 1
            self.cross("rev", "pli", None)
        if frame is not None:
            self.released.append((self.now, frame.timestamp / 90_000))

    async def run(self, seconds: float) -> dict:
        self.at(0.0, "frame", 0)
        self.at(0.0, "poll", None)
        while self.events:
            t, _, what, data = heapq.heappop(self.events)
            if t > seconds:
                break
            self.now = t
            if what == "wake":
                data.set_result(None)
            elif what == "frame":
                await self.frame(data)
            elif what == "rtp":
                await self.on_rtp(data)
            elif what == "nack":
                await self.on_nack(data)
            elif what == "pli":
                self.want_key = True
            elif what == "poll":  # the expert's receiver polls its buffers every 10 ms
                self.buffer.poll()
                await self.after_buffer(False, None)
                self.at(t + 0.01, "poll", None)
            for _ in range(3):  # let the copies' tasks run to their next sleep
                await asyncio.sleep(0)
        return self.figures(seconds)

    def figures(self, seconds: float) -> dict:
        # shown at the playout delay after capture, or when released if later, in order
        shown, last = [], 0.0
        for r, c in self.released:
            last = max(last, r, c + self.a.playout_ms / 1e3)
            shown.append((last, c))
        t = np.array([s for s, _ in shown])
        gaps = np.diff(t)
        typical = float(np.median(gaps))
        thr = max(3 * typical, typical + 0.15)
        frozen = float(gaps[gaps > thr].sum()) / seconds
        ages = np.array([s - c for s, c in shown])
        c = self.buffer.counters
        parity = self.parity.counters if self.parity is not None else None
        return {"given_up": c.gaps_given_up, "plis": self.plis, "repairs": c.repairs,
                "renacks": c.renacks, "frozen": frozen, "ages": ages,
                "dups": self.pacer.dups, "dup_bytes": self.pacer.dup_bytes,
                "recovered": c.fec_recovered, "nacks_spared": c.fec_nacks_spared,
                "parity_bytes": parity.parity_bytes if parity else 0,
                "bytes": sum(len(self.rtp(s)) for s in self.history)}  # fmt: skip


# name: (retransmissions twice, NACKs twice, parity per frame)
VARIANTS = {"base": (False, False, False), "rtx twice": (True, False, False),
            "nack twice": (False, True, False), "both": (True, True, False),
            "fec": (False, False, True), "fec+both": (True, True, True)}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=600.0)
    p.add_argument("--seeds", default="1,2,3")
    p.add_argument("--delay-ms", type=float, default=60.0)
    p.add_argument("--jitter-ms", type=float, default=20.0)
    p.add_argument("--loss", type=float, default=3.0, help="percent, each way")
    p.add_argument("--packets", type=int, default=6, help="packets of a delta frame")
    p.add_argument("--playout-ms", type=float, default=250.0,
                   help="frames show this long after capture unless released later")  # fmt: skip
    p.add_argument("--fec-group", type=int, default=8, help="packets per parity (fec)")
    p.add_argument("--variants", default=",".join(VARIANTS), help="which to run (names)")
    a = p.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    print(f"{a.seconds:.0f} s x {len(seeds)} seeds, {a.delay_ms:.0f} +- {a.jitter_ms:.0f} ms, "
          f"{a.loss:g} % loss each way, {a.packets} packets a frame")  # fmt: skip
    for name in a.variants.split(","):
        dup, renack, fec = VARIANTS[name]
        runs = [asyncio.run(Sim(a, s, dup, renack, fec).run(a.seconds)) for s in seeds]
        ages = np.concatenate([r["ages"] for r in runs])
        per_min = 60.0 / (a.seconds * len(seeds))
        each = ", ".join(f"{100 * r['frozen']:.2f}" for r in runs)
        print(f"{name:11s} gaps given up {sum(r['given_up'] for r in runs) * per_min:5.2f}/min, "
              f"PLIs {sum(r['plis'] for r in runs) * per_min:5.2f}/min, frozen "
              f"{100 * np.mean([r['frozen'] for r in runs]):4.2f} % "
              f"({each}), age p95 "
              f"{1e3 * np.percentile(ages, 95):.0f} ms, repairs "
              f"{sum(r['repairs'] for r in runs)}, copies "
              f"{100 * sum(r['dup_bytes'] for r in runs) / sum(r['bytes'] for r in runs):.2f} "
              f"% of the bytes, rebuilt {sum(r['recovered'] for r in runs)}, parity "
              f"{100 * sum(r['parity_bytes'] for r in runs) / sum(r['bytes'] for r in runs):.1f}"
              " % of the bytes")  # fmt: skip


if __name__ == "__main__":
    main()
