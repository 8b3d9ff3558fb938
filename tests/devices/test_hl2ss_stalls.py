"""The hl2ss client against a headset that stalls without closing, and one that trickles:
every read ends by its deadline, the stall is found, the socket dropped (so the app, which
serves one client per port, can take the next) and the stream reconnected with back-off.

Stalls and back-off are timed on a clock the test drives by hand; only the socket deadlines
run on the real clock (bounded from above, never from below)."""

from __future__ import annotations

import threading
import time

import numpy as np

from humantele.tracking.hl2ss_protocol import encode_ahat_packet, read_configuration
from humantele.tracking.hl2ss_replay import AhatRecord, Hl2ssReplayServer, round_ticks
from humantele.tracking.hl2ss_source import Hl2ssFrameConfig, Hl2ssFrameSource


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def frame_packets(n: int) -> tuple[list[bytes], list[np.ndarray]]:
    rng = np.random.default_rng(5)
    irs = [rng.integers(0, 4000, (512, 512), dtype=np.uint16) for _ in range(n)]
    depth = np.full((512, 512), 600, np.uint16)
    return [encode_ahat_packet(k, depth, ir, k) for k, ir in enumerate(irs)], irs


def cfg(port: int, **kw) -> Hl2ssFrameConfig:
    base = {"host": "127.0.0.1", "port": port, "mode": 0, "ab_profile": "raw",
            "download_calibration": False, "read_timeout_s": 0.2, "stall_s": 2.0,
            "retry_s": 0.5, "retry_max_s": 2.0}  # fmt: skip
    return Hl2ssFrameConfig(**{**base, **kw})


class StallingServer(Hl2ssReplayServer):
    """Per connection: one frame, then (first connection) silence with the socket open
    until the client leaves, or ``trickle_s``: a byte of the next frame every so often;
    later connections: the next frame, then silence. Records when each client left."""

    def __init__(self, packets: list[bytes], trickle_s: float | None = None, port: int = 0):
        self.packets = packets
        self.trickle_s = trickle_s
        self.connections = 0
        self.left = threading.Event()
        super().__init__([], port=port)  # one connection at a time, as the app serves a port

    def _serve(self, conn) -> None:
        read_configuration(lambda n: self._recv_exactly(conn, n))
        k = self.connections
        self.connections += 1
        try:
            conn.sendall(self.packets[k])
            if k == 0 and self.trickle_s is not None:
                conn.settimeout(self.trickle_s)
                for b in self.packets[1]:
                    try:
                        if conn.recv(1) == b"":
                            break
                    except TimeoutError:
                        pass
                    conn.sendall(bytes([b]))
            conn.settimeout(0.1)
            while not self._stop.is_set():  # silence, open, until the client leaves
                try:
                    if conn.recv(1) == b"":
                        break
                except TimeoutError:
                    continue
            if k == 0:
                self.left.set()
        except OSError:
            if k == 0:
                self.left.set()


def test_a_stream_with_no_frame_and_no_close_is_found_dropped_and_reconnected():
    packets, irs = frame_packets(3)
    clock = Clock()
    with StallingServer(packets) as srv:
        src = Hl2ssFrameSource(cfg(srv.port), clock=clock)
        src.open()
        assert np.array_equal(src.read().ir, irs[0])
        clock.t += 1.9  # under stall_s: a timeout, still connected, not stalled
        t0 = time.monotonic()
        assert src.read() is None
        assert time.monotonic() - t0 < 3.0  # bounded by read_timeout_s (0.2 s)
        assert src.dropped == {"timeout": 1} and not src.stalled and src.stalls == 0
        clock.t += 0.1  # 2 s without a frame: the stall is found on this read
        assert src.read() is None
        assert src.stalls == 1 and src.dropped["stalled"] == 1 and src.stalled
        assert srv.left.wait(10), "the stalled socket was not closed"
        assert src.read() is None and srv.connections == 1  # back-off: not before retry_s
        clock.t += 0.5
        # reconnected after 0.5 s: the app serves one client at a time, so this frame comes
        # only because the stalled socket was closed
        g = first_frame(src)
        assert g is not None and np.array_equal(g.ir, irs[1])
        assert not src.stalled and src.reconnects == 1 and srv.connections == 2
        s = src.stats()
        assert s["stalls"] == 1 and s["reconnects"] == 1 and s["stalled"] is False
        src.close()


def first_frame(src: Hl2ssFrameSource, reads: int = 20):
    """The first frame of up to ``reads`` reads (one may end by its deadline before the
    frame is all there on a busy machine)."""
    for _ in range(reads):
        g = src.read()
        if g is not None:
            return g
    return None


def waits_for_tries(src: Hl2ssFrameSource, clock: Clock, key: str, n: int) -> list[float]:
    """The clock's steps (0.25 s) between ``n`` successive counts of ``dropped[key]``."""
    waits = []
    for _ in range(n):
        before = src.dropped.get(key, 0)
        step = 0.0
        while src.dropped.get(key, 0) == before:
            clock.t += 0.25
            step += 0.25
            src.read()
            assert step < 20
        waits.append(step)
    return waits


def test_reconnects_back_off_while_the_headset_is_gone_and_reset_after_a_frame():
    packets, irs = frame_packets(3)
    clock = Clock()
    srv = StallingServer(packets)
    port = srv.port
    src = Hl2ssFrameSource(cfg(port), clock=clock)
    src.open()
    assert src.read() is not None
    srv.close()  # the app is gone: it closed the stream, and its port refuses
    assert src.read() is None and src.dropped == {"disconnected": 1}
    clock.t += 2.0
    assert src.stalled  # 2 s without a frame, whatever the reason
    # the first try (0.5 s after the loss, due), then each failed try doubles the wait: 1, 2,
    # then 2 (the cap)
    assert waits_for_tries(src, clock, "reconnect_failed", 4) == [0.25, 1.0, 2.0, 2.0]
    with StallingServer(packets[1:], port=port) as again:  # the app is back
        clock.t += 2.0
        g = first_frame(src)
        assert g is not None and np.array_equal(g.ir, irs[1]) and not src.stalled
        clock.t += 2.0  # it stalls: dropped, and the next try comes after retry_s again
        assert first_frame(src, 1) is None and src.stalls == 1
        n = again.connections
        clock.t += 0.5
        assert first_frame(src) is not None and again.connections == n + 1
    src.close()


def test_a_trickling_server_cannot_hold_a_read_and_is_dropped_as_a_stall():
    packets, irs = frame_packets(2)
    clock = Clock()
    with StallingServer(packets, trickle_s=0.05) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, read_timeout_s=0.3), clock=clock)
        src.open()
        assert src.read() is not None
        t0 = time.monotonic()
        assert src.read() is None  # a byte every 50 ms: the packet never completes
        elapsed = time.monotonic() - t0
        assert elapsed < 5.0, elapsed  # the deadline (0.3 s), not 1 MiB at 20 B/s
        assert src.dropped == {"timeout": 1}
        clock.t += 2.0  # bytes came, no frame: a stall
        assert src.read() is None and src.stalls == 1 and src.dropped["stalled"] == 1
        assert srv.left.wait(10)
        src.close()


def test_a_replayed_headset_runs_on_from_its_epoch_and_drops_what_it_could_not_send():
    """With an epoch the replayed headset's world runs on as a real one's (and as the board's
    replay from the same epoch): a client joins at the frame of now, and frames that could not
    be sent in their time (a server starved under load, a client reading late) are dropped at
    the sensor, never sent late: the frames keep time with the board's reports."""
    depth = np.full((512, 512), 600, np.uint16)
    ir = np.zeros((512, 512), np.uint16)
    records = [AhatRecord(k, depth, ir, k) for k in range(450)]  # 10 s at 45 Hz
    epoch = time.monotonic() - 3.0  # the clinic has run for 3 s
    with Hl2ssReplayServer([records], rate_hz=45.0, repeat=True, epoch=epoch) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, read_timeout_s=5.0, stall_s=30.0))
        src.open()
        try:
            first = first_frame(src)
            assert first is not None
            joined = src.last_timestamp
            assert joined >= 3.0 * 45 - 1  # the frame of now, not the first
            time.sleep(1.0)  # the client reads late: the server cannot send meanwhile
            stamps = []
            for _ in range(30):
                if src.read() is not None:
                    stamps.append(src.last_timestamp)
            assert srv.dropped_late >= 20, srv.dropped_late  # not sent late, dropped
            assert max(stamps) >= joined + 45  # the frames went on with the clock
        finally:
            src.close()


def test_a_looped_replay_from_its_epoch_keeps_its_clock_running_across_the_loop():
    """Looped from an epoch, the replayed headset's timestamps go on at the recording's
    spacing past the turn's end (a headset's clock never goes back: a press replayed after the
    loop would otherwise be stamped before the frames it follows)."""
    depth = np.full((512, 512), 600, np.uint16)
    ir = np.zeros((512, 512), np.uint16)
    step = 222_222  # 45 Hz in 100 ns ticks
    records = [AhatRecord(5_000_000 + k * step, depth, ir, k) for k in range(10)]
    assert round_ticks(records) == 10 * step
    with Hl2ssReplayServer([records], rate_hz=45.0, repeat=True, loop=True,
                           epoch=time.monotonic()) as srv:  # fmt: skip
        src = Hl2ssFrameSource(cfg(srv.port, read_timeout_s=5.0, stall_s=30.0))
        src.open()
        try:
            stamps = []
            while len(stamps) < 25:  # two and a half rounds
                if src.read() is not None:
                    stamps.append(src.last_timestamp)
        finally:
            src.close()
    gaps = np.diff(stamps)
    assert np.all(gaps > 0), stamps  # never back, at the loop's start neither
    assert np.all(gaps % step == 0), gaps  # the recording's spacing (a frame dropped late: 2)
