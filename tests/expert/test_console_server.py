"""The console's server against sim video (real sim frames) and a session of our own: frames
reach the page in order and readable, the state says what is stale, the tools measure, save
and record, and bad input is refused and counted while the server goes on."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time

import aiohttp
import cv2
import numpy as np
import pytest

from humantele.expert.console import ConsoleConfig, ConsoleServer, SourceFrames
from humantele.expert.console.cine import CineBuffer, CineFrame
from humantele.expert.console.expert_view import PoseHistory
from humantele.expert.console.frames import _Subscribers
from humantele.expert.console.heartbeat import LoopStalls
from humantele.expert.console.hook import alignment, pressing_n
from humantele.expert.console.messages import HEADER_SIZE, parse_header
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.recording import Recorder
from humantele.recording.reader import read_recording
from humantele.video.counter import read_counter
from humantele.video.scene import DemoScene
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Session:
    """A session as the console sees it: fixed state, commands remembered."""

    def __init__(self, recorder=None) -> None:
        self.recorder = recorder
        self.commands: list[tuple] = []
        self.scan = None
        self.link = {"state": "connected", "pose_age_ms": 12.0}

    def snapshot(self) -> dict:
        return {
            "link": dict(self.link),
            "scan": self.scan,
            "force": {"measured_n": 4.0, "rendered_n": 1.5, "contact": True},
            "alignment": {"mm": 3.0, "deg": math.nan},  # a NaN must reach the page as null
        }

    def pose_at(self, t: float):  # numpy arrays, as the daemon's poses are
        return {"position": np.array([0.01, 0.02, 0.03]), "quaternion": np.array([0, 0, 0, 1.0])}

    def start_scan(self) -> int:
        self.commands.append(("scan", "start"))
        self.scan = 1
        return 1

    def stop_scan(self) -> None:
        self.commands.append(("scan", "stop"))
        self.scan = None

    def set_clutch(self, on: bool) -> None:
        self.commands.append(("clutch", on))


class ManualFrames(_Subscribers):
    """A provider whose frames the test renders from the sim sources, one at a time (each
    handed to the subscribers, as a source's thread does)."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__()
        scene = DemoScene(clock=clock)
        self.us = SimUltrasound(SimUltrasoundConfig(width=320, height=240), scene, clock=clock)
        self.pov = SimPov(SimPovConfig(width=320, height=180), scene, clock=clock)
        self.scene = scene
        self.frames: dict = {}

    def next(self, track: str):
        src = self.us if track == "us" else self.pov
        self.frames[track] = src.render(self.scene())
        self._notify(track, self.frames[track])
        return self.frames[track]

    def latest(self, track: str):
        return self.frames.get(track)


class ReceivedManualFrames(ManualFrames):
    """As received frames are: decoded 30 ms after their capture (``t_received``), there for
    the console 40 ms after it."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__(clock)
        self.clock = clock

    def next(self, track: str):
        src = self.us if track == "us" else self.pov
        f = src.render(self.scene())
        self.clock.t += 0.04
        self.frames[track] = Received(f, f.t_capture + 0.03)
        self._notify(track, self.frames[track])
        return self.frames[track]


class Received:
    def __init__(self, frame, t_received: float) -> None:
        self.__dict__.update({k: getattr(frame, k) for k in (
            "image", "seq", "t_capture", "pixel_spacing_mm", "depth_origin_row", "width",
            "height")})  # fmt: skip
        self.t_received = t_received


async def serve(frames, session, tmp_path, clock=None, on_demand=None, **cfg) -> ConsoleServer:
    config = ConsoleConfig(port=0, captures_dir=str(tmp_path / "captures"), **cfg)
    server = ConsoleServer(config, frames, session, clock=clock or FakeClock(), on_demand=on_demand)
    await server.start()
    return server


async def drawn(ws, seq: int) -> None:
    """The page's echo of an ultrasound frame it drew (the console then sends the next one
    at once, not after the in-flight bound's timeout)."""
    await ws.send_json({"type": "drawn", "track": "us", "seq": seq, "draw_to_send_ms": 0.1})


async def next_message(ws, want, timeout: float = 10.0):
    """The next message satisfying ``want(kind, data)`` (kind "frame" with the parsed header
    and the JPEG, or "json" with the object)."""
    end = asyncio.get_running_loop().time() + timeout
    while True:
        msg = await ws.receive(timeout=max(0.01, end - asyncio.get_running_loop().time()))
        if msg.type == aiohttp.WSMsgType.BINARY:
            item = ("frame", (parse_header(msg.data), msg.data[HEADER_SIZE:]))
        elif msg.type == aiohttp.WSMsgType.TEXT:
            item = ("json", json.loads(msg.data))
        else:
            raise AssertionError(f"socket ended: {msg.type}")
        if want(*item):
            return item[1]


def decode(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)


async def test_live_sim_frames_reach_the_page_readable_and_in_order(tmp_path):
    """Both tracks from sim sources in their threads: each frame the page gets decodes, is
    not black, carries its own number in the counter patch, and numbers only increase."""
    scene = DemoScene()
    frames = SourceFrames(
        {
            "us": SimUltrasound(SimUltrasoundConfig(width=320, height=240, fps=20.0), scene),
            "pov": SimPov(SimPovConfig(width=320, height=180, fps=20.0), scene),
        }
    )
    server = await serve(frames, Session(), tmp_path, clock=time.monotonic, on_demand=frames)
    try:
        assert not frames._threads  # no page, no rendering
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            seen: dict[str, list[int]] = {"us": [], "pov": []}
            while min(len(v) for v in seen.values()) < 4:
                h, jpeg = await next_message(ws, lambda k, d: k == "frame")
                img = decode(jpeg)
                assert img.shape[:2] == (h["height"], h["width"])
                assert img.mean() > 5.0  # a picture, not a black frame
                assert read_counter(img) == h["seq"]
                if h["track"] == "us":  # the scale: the sim's own pixel spacing and depth 0
                    g = frames.sources["us"].geometry
                    assert h["spacing_mm"] == pytest.approx(g.pixel_spacing_mm, rel=1e-6)
                    assert h["depth_origin_row"] == pytest.approx(g.depth_origin_row, rel=1e-6)
                else:
                    assert h["depth_origin_row"] is None
                seen[h["track"]].append(h["seq"])
            for seqs in seen.values():
                assert seqs == sorted(set(seqs))
        for _ in range(300):  # the page closed: the sources stop
            if not frames._threads:
                break
            await asyncio.sleep(0.01)
        assert not frames._threads
    finally:
        frames.stop()
        await server.stop()
    assert server.tracks["us"].frames >= 4 and server.tracks["pov"].frames >= 4


async def test_glass_to_glass_from_the_counter_the_page_read(tmp_path):
    """The page echoes the counter it read back from its canvas: the capture-to-draw figure
    is that frame's (not the header's), on the expert's clock; a counter that did not read,
    or reads a frame not sent, is counted and left out. Seen-to-draw starts at the frame's
    receipt (the receiver's decode time) when the provider gives one."""
    clock = FakeClock()
    frames = ReceivedManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock)
    sent = []
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            for _ in range(3):  # captured at t, 0.05 s apart; the page draws them at t + 0.2
                f = frames.next("us")
                await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
                sent.append(f)
                clock.t += 0.05
            clock.t = sent[-1].t_capture + 0.2
            # Frame 3's header, and the page read frame 2's counter off its canvas.
            for seq, counter in ((1, None), (2, 999), (3, sent[1].seq)):
                await ws.send_json({"type": "drawn", "track": "us", "seq": seq,
                                    "counter": counter, "draw_to_send_ms": 0.0})  # fmt: skip
            for _ in range(200):
                if server.tracks["us"].drawn == 3:
                    break
                await asyncio.sleep(0.01)
    finally:
        await server.stop()
    st = server.tracks["us"]
    assert (st.counter_read, st.counter_unread, st.counter_unmatched) == (1, 1, 1)
    assert list(st.capture_to_draw) == [pytest.approx(clock.t - sent[1].t_capture)]
    assert list(st.capture_to_seen) == [pytest.approx(0.03)]  # the receiver's decode
    receipts = [f.t_received for f in sent]
    assert list(st.seen_to_draw) == pytest.approx([clock.t - t for t in receipts])


async def test_state_marks_old_video_and_a_lost_link_as_stale(tmp_path):
    clock = FakeClock()
    frames = ManualFrames(clock)
    session = Session()
    server = await serve(frames, session, tmp_path, clock=clock, stale_after_s=1.0)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            st = await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
            assert st["alignment"] == {"mm": 3.0, "deg": None}  # NaN sent as null
            state = server.state()
            assert state["video"]["us"]["stale"] and state["video"]["us"]["age_ms"] is None
            frames.next("us")
            await next_message(ws, lambda k, d: k == "frame")
            state = server.state()
            assert not state["video"]["us"]["stale"] and state["video"]["us"]["age_ms"] == 0.0
            assert state["video"]["pov"]["stale"]  # never had a frame
            assert not state["link"]["stale"]
            clock.t += 1.5  # no new frame for 1.5 s
            state = server.state()
            assert state["video"]["us"]["stale"] and state["video"]["us"]["age_ms"] == 1500.0
            session.link = {"state": "disconnected", "pose_age_ms": 40.0}
            assert server.state()["link"]["stale"]
            session.link = {"state": "connected", "pose_age_ms": 2500.0}
            assert server.state()["link"]["stale"]
    finally:
        await server.stop()


async def test_no_page_no_video_work(tmp_path):
    """With no page open the console takes no frame at all (no subscription: the provider
    hands on nothing, nothing is encoded or kept); a page opening subscribes, its closing
    unsubscribes and empties the cine loop."""
    clock = FakeClock()
    frames = ManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock)
    try:
        for _ in range(5):
            frames.next("us")
            frames.next("pov")
        await asyncio.sleep(0.05)
        assert frames.notified == 0 and not server.stats()["subscribed"]
        assert server.tracks["us"].frames == 0 and server.tracks["us"].jpegs == 0
        assert len(server.cine) == 0
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            f = frames.next("us")
            await next_message(ws, lambda k, d: k == "frame" and d[0]["seq"] == f.seq)
            assert frames.notified == 1 and server.tracks["us"].jpegs == 1
            assert len(server.cine) == 1
        for _ in range(300):
            if not server.stats()["subscribed"]:
                break
            await asyncio.sleep(0.01)
        assert not server.stats()["subscribed"] and len(server.cine) == 0
        before = frames.notified
        for _ in range(5):
            frames.next("us")
        await asyncio.sleep(0.05)
        assert frames.notified == before and server.tracks["us"].jpegs == 1
    finally:
        await server.stop()


async def test_freeze_cine_calipers_annotation_and_capture_are_measured_saved_recorded(
    tmp_path,
):
    clock = FakeClock()
    frames = ManualFrames(clock)
    rec = Recorder(tmp_path / "s.expert.mcap", "expert")
    session = Session(recorder=rec)
    server = await serve(frames, session, tmp_path, clock=clock)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            for _ in range(5):  # five ultrasound frames, 50 ms apart, each drawn by the page
                f = frames.next("us")
                await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
                await ws.send_json({"type": "drawn", "track": "us", "seq": f.seq,
                                    "draw_to_send_ms": 0.5})  # fmt: skip
                clock.t += 0.05
            spacing = f.pixel_spacing_mm
            await ws.send_json({"type": "freeze", "on": True})
            cine = await next_message(ws, lambda k, d: k == "json" and d["type"] == "cine")
            assert [s for s, _ in cine["frames"]] == [1, 2, 3, 4, 5]
            assert cine["frames"][-1][1] == 0.0 and cine["frames"][0][1] == pytest.approx(-0.2)
            frames.next("us")  # a live frame while frozen is not kept
            await asyncio.sleep(0.05)
            assert len(server.cine) == 5
            await ws.send_json({"type": "cine", "seq": 2})
            h, jpeg = await next_message(ws, lambda k, d: k == "frame" and d[0]["cine"])
            assert h["seq"] == 2 and read_counter(decode(jpeg)) == 2
            # A 3-4-5 caliper of 30 x 40 px: 50 px when the pixels are square.
            a, b = [100.0, 60.0], [130.0, 100.0]
            await ws.send_json({"type": "caliper", "seq": 2, "a": a, "b": b})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            want = math.hypot(30 * spacing[1], 40 * spacing[0])
            assert r["ok"] and r["of"] == "caliper" and r["mm"] == pytest.approx(want)
            # Issue 34 §4: a caliper of 110,900 mm, far outside the image, was accepted
            await ws.send_json({"type": "caliper", "seq": 2, "a": a, "b": [99000.0, 60.0]})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert not r["ok"] and "outside the" in r["detail"]
            await ws.send_json({"type": "annotation", "seq": 2, "at": [-5.0, 60.0], "text": "x"})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert not r["ok"] and "outside the" in r["detail"]
            await ws.send_json({"type": "annotation", "seq": 2, "at": a, "text": " left  kidney "})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert r["ok"] and r["detail"] == "left kidney"
            await ws.send_json({"type": "capture", "seq": 2})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert r["ok"] and r["of"] == "capture"
            await ws.send_json({"type": "capture", "seq": 99})  # not in the buffer
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert not r["ok"] and "no longer" in r["detail"]
            await ws.send_json({"type": "freeze", "on": False})
            await ws.send_json({"type": "scan", "action": "start"})
            await ws.send_json({"type": "clutch", "on": True})
            for _ in range(100):
                if len(session.commands) == 2:
                    break
                await asyncio.sleep(0.01)
    finally:
        await server.stop()
        rec.close()
    assert session.commands == [("scan", "start"), ("clutch", True)]
    saved = sorted((tmp_path / "captures").iterdir())
    assert [p.suffix for p in saved] == [".jpg", ".json"]
    info = json.loads(saved[1].read_text())
    assert info["seq"] == 2 and info["pose"]["position"] == [0.01, 0.02, 0.03]
    assert read_counter(decode(saved[0].read_bytes())) == 2  # the frame scrolled back to
    events = read_recording(tmp_path / "s.expert.mcap").samples("/expert/console")
    assert [e["event"] for e in events] == ["freeze", "caliper", "annotation", "capture", "live"]
    assert server.refused["outside_image"] == 2  # refused, not recorded
    assert events[1]["mm"] == pytest.approx(want) and events[1]["a_px"] == a
    assert events[2]["text"] == "left kidney"
    assert events[3]["file"] == saved[0].name and events[3]["position"] == [0.01, 0.02, 0.03]
    from mcap.reader import make_reader

    with open(tmp_path / "s.expert.mcap", "rb") as fh:
        attachments = list(make_reader(fh).iter_attachments())
    assert [a.name for a in attachments] == [saved[0].name]
    assert attachments[0].data == saved[0].read_bytes()


async def test_bad_pages_are_refused_and_counted_and_the_server_goes_on(tmp_path):
    clock = FakeClock()
    frames = ManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock, page_rate_hz=50.0)
    url = server.ws_url
    async with aiohttp.ClientSession() as http:
        with pytest.raises(aiohttp.WSServerHandshakeError) as other:
            async with http.ws_connect(url, headers={"Origin": "http://evil.example"}):
                pass
        assert other.value.status == 403
    async with aiohttp.ClientSession() as http:
        resp = await http.get(server.address, headers={"Host": f"rebind.example:{server.port}"})
        assert resp.status == 403  # DNS rebinding: a loopback server answering another name
        resp = await http.get(server.address)
        assert resp.status == 200 and "console" in await resp.text()
        assert "frame-ancestors 'none'" in resp.headers["Content-Security-Policy"]
        async with http.ws_connect(url, origin=server.address.rstrip("/")) as ws:
            with pytest.raises(aiohttp.WSServerHandshakeError) as second:
                async with http.ws_connect(url):
                    pass
            assert second.value.status == 409
            for bad in (
                "not json",
                json.dumps({"type": "launch"}),
                json.dumps({"type": "caliper", "seq": 1, "a": [0, 0], "b": [1e308, 0]}),
                json.dumps({"type": "annotation", "seq": 1, "at": [0, 0], "text": "x" * 500}),
                json.dumps({"type": "drawn", "track": "us", "seq": 12345, "draw_to_send_ms": 1}),
                json.dumps({"type": "scan", "action": "start", "extra": 1}),
            ):
                await ws.send_str(bad)
            await ws.send_bytes(b"\x00\x01")
            for _ in range(200):  # a flood: beyond the budget, dropped and counted
                await ws.send_str("{}")
            await ws.send_str("y" * 20000)  # too big: the socket is closed
            msg = await ws.receive(timeout=5)
            while msg.type not in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                msg = await ws.receive(timeout=5)
        for _ in range(100):
            if not server.clients:
                break
            await asyncio.sleep(0.01)
        async with http.ws_connect(url) as ws:  # the tab closed: a new console is let in
            frames.next("us")
            h, _ = await next_message(ws, lambda k, d: k == "frame")
            assert h["track"] == "us"
    await server.stop()
    r = server.refused
    assert r["origin"] == 1 and r["host"] == 1 and r["second_console"] == 1
    assert r["malformed"] >= 5 and r["unknown_frame"] == 1 and r["flood"] > 0


async def test_a_slow_page_gets_the_newest_frame_not_a_queue(tmp_path):
    """At most two frames of a track go to a page before it says it drew one; the others
    wait, newest wins, so a slow page is never behind by a socket full of frames."""
    clock = FakeClock()
    frames = ManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock)
    server.in_flight_timeout_s = 60.0  # a page that echoes nothing: not within this test
    rendered = [frames.next("us") for _ in range(6)]
    frames.frames.clear()
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            got = []
            for i, f in enumerate(rendered):
                frames.frames["us"] = f
                frames._notify("us", f)
                while server.tracks["us"].jpegs != i + 1:  # the server has encoded it
                    await asyncio.sleep(0.005)
            while len(got) < 2:
                h, _ = await next_message(ws, lambda k, d: k == "frame")
                got.append(h["seq"])
            assert got == [1, 2]  # then nothing until the page draws
            with pytest.raises(asyncio.TimeoutError):
                await next_message(ws, lambda k, d: k == "frame", timeout=0.2)
            await ws.send_json({"type": "drawn", "track": "us", "seq": 2, "draw_to_send_ms": 0})
            h, _ = await next_message(ws, lambda k, d: k == "frame")
            assert h["seq"] == 6  # the newest, frames 3-5 skipped
        assert server.coalesced >= 3
        assert server.tracks["us"].drawn == 1
    finally:
        await server.stop()


def test_console_is_served_on_loopback_only():
    with pytest.raises(ValueError, match="loopback only"):
        ConsoleConfig(host="0.0.0.0")
    assert ConsoleConfig(host="::1").host == "::1"


def test_cine_buffer_keeps_the_last_seconds_and_holds_still_when_frozen():
    cine = CineBuffer(seconds=10.0, max_frames=1000)
    for i in range(1, 301):  # 15 s at 20 fps
        cine.add(CineFrame(i, i * 0.05, b"j", 4, 4, (0.3, 0.3)))
    idx = cine.index()
    assert idx[-1][0] == 300 and idx[-1][1] - idx[0][1] <= 10.0 and len(idx) == 201
    cine.add(CineFrame(300, 99.0, b"j", 4, 4, None))  # not newer: ignored
    assert cine.newest().t_capture == 15.0
    cine.freeze()
    cine.add(CineFrame(301, 15.05, b"j", 4, 4, None))
    assert cine.newest().seq == 300 and cine.get(100) is not None
    cine.resume()
    cine.add(CineFrame(302, 15.1, b"j", 4, 4, None))
    assert cine.newest().seq == 302
    small = CineBuffer(seconds=10.0, max_frames=3)
    for i in range(1, 6):
        small.add(CineFrame(i, i * 0.05, b"j", 4, 4, None))
    assert [s for s, _ in small.index()] == [3, 4, 5]


def test_alignment_and_pose_history():
    a = Pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    s = math.sin(math.radians(10) / 2)
    b = Pose([0.003, 0.004, 0.0], [0.0, 0.0, s, math.cos(math.radians(10) / 2)])
    al = alignment(a, b)
    assert al["mm"] == pytest.approx(5.0) and al["deg"] == pytest.approx(10.0)
    h = PoseHistory(seconds=1.0)
    for i in range(30):
        h.add(i * 0.1, Pose([i * 0.001, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]))
    assert h.at(2.52).position[0] == pytest.approx(0.025)
    assert h.at(1.0) is None  # older than the history keeps
    assert h.at(10.0) is None  # nothing near


def test_received_frames_number_and_time_the_receivers_frames():
    """The adapter over the WebRTC receiver: the counter's number, else the next one; the
    capture time, else the decode time; spacing on the ultrasound only; one object per frame."""
    from types import SimpleNamespace

    from humantele.expert.console.frames import ReceivedFrames

    img = np.zeros((48, 64, 3), np.uint8)

    def frame(seq, t_capture, t_received):
        return SimpleNamespace(seq=seq, t_capture=t_capture, t_received=t_received,
                               width=64, height=48, image=lambda: img)  # fmt: skip

    latest = {"us": None, "pov": None}
    rf = ReceivedFrames(SimpleNamespace(latest=lambda t: latest[t]), (0.3, 0.4))
    assert rf.latest("us") is None
    latest["us"] = frame(7, 10.0, 10.05)
    a = rf.latest("us")
    assert (a.seq, a.t_capture, a.pixel_spacing_mm, a.width) == (7, 10.0, (0.3, 0.4), 64)
    assert rf.latest("us") is a and a.image is img
    latest["us"] = frame(None, None, 10.2)  # the counter did not read, no capture time
    b = rf.latest("us")
    assert (b.seq, b.t_capture) == (8, 10.2)
    latest["pov"] = frame(3, 9.0, 9.1)
    assert rf.latest("pov").pixel_spacing_mm is None


def test_console_config_checks_the_pixel_spacing():
    assert ConsoleConfig(us_pixel_spacing_mm=(0.39, 0.39)).us_pixel_spacing_mm == (0.39, 0.39)
    for bad in ((0.0, 0.3), (math.nan, 0.3), (50.0, 0.3)):
        with pytest.raises(ValueError, match="pixel spacing|finite"):
            ConsoleConfig(us_pixel_spacing_mm=bad)


def test_force_along_the_beam_is_the_pressing_force():
    """A probe pointing down (beam, tip +z, along world -y), pressed into the patient: the
    patient pushes it up and a little sideways; along the beam that is +8 N pressing, the
    sideways push left out; pulled away from the patient it is negative."""
    down = Pose([0.1, 0.2, 0.0], quat_from_axis_angle((1.0, 0.0, 0.0), math.pi / 2))
    assert pressing_n(down.inverse().rotate([3.0, 8.0, 0.0])) == pytest.approx(8.0)
    assert pressing_n(down.inverse().rotate([0.0, -2.0, 1.0])) == pytest.approx(-2.0)


async def test_captures_are_capped_in_rate_and_in_disk_use(tmp_path):
    """A page asking for captures as fast as it can: 10 at once, then ``captures_per_minute``;
    the others refused with the reason, counted and in the page's state. A captures folder at
    its budget refuses every capture."""
    clock = FakeClock()
    frames = ManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock, captures_per_minute=6.0)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            f = frames.next("us")
            await next_message(ws, lambda k, d: k == "frame" and d[0]["seq"] == f.seq)
            results = []
            for _ in range(25):
                await ws.send_json({"type": "capture", "seq": f.seq})
                results.append(
                    await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
                )
            state = await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
    finally:
        await server.stop()
    ok = [r for r in results if r["ok"]]
    assert 10 <= len(ok) <= 11  # the burst (and at most one more refilled meanwhile)
    refusal = next(r for r in results if not r["ok"])
    assert "captures a minute" in refusal["detail"] and "refused this run" in refusal["detail"]
    assert server.refused["capture_rate"] == 25 - len(ok)
    assert len(list((tmp_path / "captures").glob("*.jpg"))) == len(ok)
    assert state["captures"]["refused"] >= 1
    assert server.stats()["captures_refused"] == 25 - len(ok)

    # The folder already holds more than the budget (another run's captures): refused.
    (tmp_path / "captures" / "capture-old.jpg").write_bytes(b"\0" * 200_000)
    server = await serve(frames, Session(), tmp_path, clock=clock, captures_max_mb=0.2)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            f = frames.next("us")
            await next_message(ws, lambda k, d: k == "frame" and d[0]["seq"] == f.seq)
            await ws.send_json({"type": "capture", "seq": f.seq})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
    finally:
        await server.stop()
    assert not r["ok"] and "captures_max_mb" in r["detail"]
    assert server.refused["capture_disk"] == 1


async def test_pings_clicks_and_their_answers(tmp_path):
    """A ping is answered at once with the expert's clock; each click with an id gets its own
    answer (two quick ones both come back); the state carries the expert's clock."""
    clock = FakeClock(123.5)
    session = Session()
    server = await serve(ManualFrames(clock), session, tmp_path, clock=clock)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            state = await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
            assert state["t"] == 123.5
            await ws.send_json({"type": "ping", "n": 7})
            pong = await next_message(ws, lambda k, d: k == "json" and d["type"] == "pong")
            assert pong.pop("stall_ms") >= 0  # how long the loop was held: below
            assert pong == {"type": "pong", "n": 7, "t": 123.5}
            await ws.send_json({"type": "scan", "action": "start", "id": 1})
            await ws.send_json({"type": "clutch", "on": True, "id": 2})
            await ws.send_json({"type": "scan", "action": "stop", "id": 3})
            await ws.send_json({"type": "freeze", "on": True, "id": 4})
            got = {}
            while len(got) < 4:
                r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
                got[r["id"]] = (r["of"], r["ok"], r["detail"])
            await ws.send_json({"type": "ping", "n": -1})  # refused, counted
            await ws.send_json({"type": "capture", "seq": 1, "id": 5, "clip_s": 99.0})
            for _ in range(100):
                if server.refused["malformed"] >= 2:
                    break
                await asyncio.sleep(0.01)
    finally:
        await server.stop()
    assert got == {
        1: ("scan", True, "scan 1 started"),
        2: ("clutch", True, "held"),
        3: ("scan", True, "scan stopped"),
        4: ("freeze", True, "frozen"),
    }
    assert server.refused["malformed"] == 2  # a clip of over 60 s is not asked for


def test_loop_stalls_keep_the_longest_hold_of_the_last_second():
    """The daemon's own measure of its loop's holds (s, its monotonic clock): the longest of
    the last second, a hold going on now included; forgotten a second after."""
    stalls = LoopStalls(monotonic=lambda: 0.0)
    stalls.due = 10.05  # the watcher slept at 10.0 for 50 ms
    assert stalls.longest(10.02) == 0.0
    assert stalls.longest(10.75) == pytest.approx(0.7)  # held now, not yet noted
    stalls.note(0.7, 10.75)  # the watcher woke 0.7 s late
    stalls.note(0.004, 10.804)
    stalls.due = 11.85  # (the watcher woke on time since)
    assert stalls.longest(11.3) == pytest.approx(0.7)
    assert stalls.longest(11.76) == pytest.approx(0.004)  # the hold was more than 1 s ago
    assert stalls.longest(12.9) == pytest.approx(1.05)  # the watcher has not woken since


async def test_a_pong_after_a_hold_between_two_pings_says_how_long_it_was(tmp_path):
    """A loop held 0.4 s between two pings: the next pong says so (a page pinging twice a
    second would otherwise see the daemon as quick as ever)."""
    clock = FakeClock(5.0)
    server = await serve(ManualFrames(clock), Session(), tmp_path, clock=clock)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
            await asyncio.sleep(0.2)  # the watcher runs
            time.sleep(0.4)  # the loop held, no ping waiting
            await ws.send_json({"type": "ping", "n": 1})
            pong = await next_message(ws, lambda k, d: k == "json" and d["type"] == "pong")
            assert pong["n"] == 1 and pong["stall_ms"] >= 350, pong
    finally:
        await server.stop()


async def test_capture_keeps_a_clip_listed_with_the_measurements(tmp_path):
    """Capture with clip_s: the still, then the cine's last seconds up to that frame as an MP4
    beside it (written off the loop), listed with the session's calipers and notes; the page
    can fetch both with the run's key, nothing else and not without it."""
    from humantele.export.clip import write_clip  # noqa: F401 - needs PyAV (the export extra)

    clock = FakeClock()
    frames = ManualFrames(clock)
    rec = Recorder(tmp_path / "s.expert.mcap", "expert")
    server = await serve(frames, Session(recorder=rec), tmp_path, clock=clock, clip_seconds=1.0)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            for _ in range(30):  # 1.5 s of frames at 20 fps, each drawn by the page
                f = frames.next("us")
                await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
                await drawn(ws, f.seq)
                clock.t += 0.05
            await ws.send_json({"type": "caliper", "seq": 20, "a": [10.0, 10.0],
                                "b": [40.0, 50.0], "id": 1})  # fmt: skip
            await ws.send_json({"type": "annotation", "seq": 20, "at": [5.0, 5.0],
                                "text": "gallbladder", "id": 2})  # fmt: skip
            await ws.send_json({"type": "capture", "seq": 25, "clip_s": 5.0, "id": 3})
            clip = await next_message(
                ws, lambda k, d: k == "json" and d["type"] == "result" and d["of"] == "clip", 60
            )
            items = await next_message(
                ws, lambda k, d: k == "json" and d["type"] == "items"
                and any(i.get("clip") for i in d["items"]),
            )  # fmt: skip
            base = server.address + "captures/"
            still, mp4 = items["items"][-1]["file"], items["items"][-1]["clip"]
            async with http.get(f"{base}{mp4}?key={server.key}") as r:
                got = (r.status, await r.read())
            async with http.get(f"{base}{still}") as r:
                no_key = r.status
            async with http.get(f"{base}capture-other.jpg?key={server.key}") as r:
                unknown = r.status
    finally:
        await server.stop()
        rec.close()
    assert clip["ok"] and clip["id"] == 3
    kinds = [(i["kind"], i["seq"]) for i in items["items"]]
    assert kinds == [("caliper", 20), ("note", 20), ("capture", 25)]
    cap = items["items"][-1]
    # The clip's last second (clip_seconds caps the page's 5 s) up to frame 25: 21 frames.
    assert cap["clip_frames"] == 21 and cap["clip_s"] == pytest.approx(1.0, abs=0.01)
    saved = sorted(p.name for p in (tmp_path / "captures").iterdir())
    assert saved == sorted([still, still.replace(".jpg", ".json"), mp4])
    assert got[0] == 200 and got[1] == (tmp_path / "captures" / mp4).read_bytes()
    assert no_key == 401 and unknown == 404
    import av

    with av.open(str(tmp_path / "captures" / mp4)) as c:
        n = sum(1 for _ in c.decode(video=0))
    assert n == 21
    info = json.loads((tmp_path / "captures" / still.replace(".jpg", ".json")).read_text())
    assert info["clip"] == {"file": mp4, "frames": 21}
    events = read_recording(tmp_path / "s.expert.mcap").samples("/expert/console")
    assert [e["event"] for e in events] == ["caliper", "annotation", "capture", "clip"]
    assert events[3]["file"] == mp4 and events[3]["still"] == still and events[3]["frames"] == 21


async def test_a_clip_counts_in_the_disk_budget(tmp_path):
    """A capture whose clip would not fit the captures budget is refused whole, with the
    reason (a still alone would have fitted)."""
    clock = FakeClock()
    frames = ManualFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock, clip_seconds=5.0)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            for _ in range(40):
                f = frames.next("us")
                await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
                await drawn(ws, f.seq)
                clock.t += 0.05
            frame_bytes = len(server.cine.get(f.seq).jpeg)
            # Room for a still and a few frames, not for 40.
            server.config.captures_max_mb = (frame_bytes * 5 + 2048) / 1e6
            await ws.send_json({"type": "capture", "seq": f.seq, "clip_s": 5.0, "id": 1})
            r1 = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            await ws.send_json({"type": "capture", "seq": f.seq, "id": 2})  # a still: fits
            r2 = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
    finally:
        await server.stop()
    assert not r1["ok"] and "captures_max_mb" in r1["detail"] and r1["id"] == 1
    assert r2["ok"] and r2["id"] == 2
    assert server.refused["capture_disk"] == 1


async def test_a_page_that_reads_late_gets_a_state_and_a_frame_a_second_till_it_catches_up(
    tmp_path,
):
    """The page's ping says how late it reads what it is sent: more than a second, and the
    states and frames wait (the newest sent once a second) while the answers to its clicks and
    pings still go; caught up, they flow again. The server's own time is the test's, held
    still while the held messages are counted (not the machine's speed)."""
    clock, mono = FakeClock(50.0), FakeClock(1000.0)
    frames = ManualFrames(clock)
    config = ConsoleConfig(port=0, captures_dir=str(tmp_path / "captures"))
    server = ConsoleServer(config, frames, Session(), clock=clock, monotonic=mono)
    await server.start()

    def kinds(got: list) -> list[str]:
        return [m["type"] if isinstance(m, dict) else m[0]["track"] for m in got]

    async def collect(held_at_least: int) -> list:
        """Messages sent until the server has held ``held_at_least`` more of them."""
        got, goal = [], server.events["held_page_behind"] + held_at_least
        t0 = time.monotonic()
        while server.events["held_page_behind"] < goal:
            assert time.monotonic() - t0 < 30.0, ("nothing held", kinds(got))
            with contextlib.suppress(TimeoutError):
                got.append(await next_message(ws, lambda k, d: True, timeout=0.1))
        return got

    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
            await ws.send_json({"type": "ping", "n": 1, "behind_ms": 5000.0})  # reads 5 s late
            await next_message(ws, lambda k, d: k == "json" and d["type"] == "pong")
            frames.next("us")
            await ws.send_json({"type": "scan", "action": "start", "id": 9})
            first = await collect(20)  # the word of a ping holds 2 s: still within it
            mono.t += 1.05
            frames.next("us")
            second = await collect(10)
            mono.t += 1.0  # 2.05 s since the ping: its word lapsed, the next ping's holds
            await ws.send_json({"type": "ping", "n": 2, "behind_ms": 20.0})  # caught up
            state = await next_message(ws, lambda k, d: k == "json" and d["type"] == "state")
            frames.next("us")
            frame = await next_message(ws, lambda k, d: k == "frame")
            states = 0
            while states < 5:  # twenty a second again
                await next_message(ws, lambda k, d: k == "json" and d["type"] == "state", 1.0)
                states += 1
    finally:
        await server.stop()
    assert ("result", 9) in [(m.get("type"), m.get("id")) for m in first if isinstance(m, dict)]
    # Twenty states a second and the frames were due; the newest of each once a second.
    assert kinds(first).count("state") == 1 and kinds(first).count("us") <= 1, kinds(first)
    assert kinds(second).count("state") == 1 and kinds(second).count("us") <= 1, kinds(second)
    assert state["t"] == 50.0 and frame[0]["track"] == "us"


class EncodedFrames(ManualFrames):
    """As the expert's receiver gives frames: decoded (an I420 ``av_frame``) with the encoded
    frame each came from (here a stand-in: its number as bytes), and keyframes on request."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__(clock)
        self.keyframe_requests = 0
        self.key_next = False

    def request_keyframe(self, track: str) -> bool:
        self.keyframe_requests += 1
        self.key_next = True
        return True

    def push(self, track: str = "us", key: bool | None = None):
        import av

        from humantele.media.receiver import Encoded

        src = self.us if track == "us" else self.pov
        f = src.render(self.scene())
        frame = Received(f, f.t_capture + 0.01)
        frame.av_frame = av.VideoFrame.from_ndarray(f.image, format="bgr24").reformat(
            format="yuv420p"
        )
        key = self.key_next if key is None else key
        self.key_next = False
        self.frames[track] = frame
        for fn in self.subscribers[track]:
            fn(frame, Encoded(b"vp8:%d" % f.seq, key, "VP8"))
        return frame


async def test_webcodecs_pages_get_the_encoded_frames_in_order_from_a_keyframe(tmp_path):
    """The webcodecs transport: the page gets the encoded frames themselves, from a keyframe
    (asked for when it opens), in order and none replaced by a newer one; the expert encodes
    no JPEG; the cine loop keeps the decoded frames and makes a JPEG of the one asked for,
    the very picture (its counter)."""
    clock = FakeClock()
    frames = EncodedFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock, transport="webcodecs")
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            hello = await next_message(ws, lambda k, d: k == "json" and d["type"] == "hello")
            assert hello["transport"] == "webcodecs" and frames.keyframe_requests >= 1
            frames.key_next = False
            first = frames.push(key=False)  # before a keyframe: not sent, a keyframe asked
            assert frames.keyframe_requests >= 2
            sent = [frames.push() for _ in range(6)]  # the first is the keyframe asked for
            got = []
            while len(got) < 6:
                h, data = await next_message(ws, lambda k, d: k == "frame")
                got.append((h["seq"], h["encoded"], h["keyframe"], data))
            assert [g[0] for g in got] == [f.seq for f in sent]
            assert all(g[1] for g in got) and got[0][2] and not any(g[2] for g in got[1:])
            assert [g[3] for g in got] == [b"vp8:%d" % f.seq for f in sent]
            assert server.tracks["us"].jpegs == 0 and server.tracks["us"].encoded_dropped == 1
            assert server.cine.get(first.seq) is not None  # decoded: in the cine all the same
            await ws.send_json({"type": "freeze", "on": True})
            await ws.send_json({"type": "cine", "seq": sent[2].seq})
            h, jpeg = await next_message(ws, lambda k, d: k == "frame" and d[0]["cine"])
            assert h["seq"] == sent[2].seq and read_counter(decode(jpeg)) == sent[2].seq
    finally:
        await server.stop()


async def test_the_other_transports_on_request_and_sim_video_is_jpeg(tmp_path):
    """The default (webcodecs): the encoded frames; ``?transport=jpeg`` asks JPEGs made from
    the decoded planes; a provider without encoded frames (sim) gives JPEG whatever the page
    asks."""
    clock = FakeClock()
    frames = EncodedFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock)
    try:
        async with aiohttp.ClientSession() as http:
            async with http.ws_connect(server.ws_url) as ws:
                hello = await next_message(ws, lambda k, d: k == "json" and d["type"] == "hello")
                assert hello["transport"] == "webcodecs"
            while server.clients:
                await asyncio.sleep(0.01)
            async with http.ws_connect(server.ws_url + "&transport=jpeg") as ws:
                hello = await next_message(ws, lambda k, d: k == "json" and d["type"] == "hello")
                assert hello["transport"] == "jpeg"
                f = frames.push()
                h, jpeg = await next_message(ws, lambda k, d: k == "frame")
                assert not h["encoded"] and read_counter(decode(jpeg)) == f.seq == h["seq"]
    finally:
        await server.stop()
    sim = ManualFrames(clock)
    server = await serve(sim, Session(), tmp_path, clock=clock)
    try:
        async with aiohttp.ClientSession() as http:
            async with http.ws_connect(server.ws_url + "&transport=webcodecs") as ws:
                hello = await next_message(ws, lambda k, d: k == "json" and d["type"] == "hello")
                assert hello["transport"] == "jpeg"
    finally:
        await server.stop()


async def test_a_webcodecs_page_that_falls_behind_gets_the_newest_from_a_keyframe(tmp_path):
    """A page that has not drawn the last 8 frames it was sent gets no more (its socket is
    not a buffer); once it has drawn them it gets the newest, from a keyframe."""
    clock = FakeClock()
    frames = EncodedFrames(clock)
    server = await serve(frames, Session(), tmp_path, clock=clock, transport="webcodecs")
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            await next_message(ws, lambda k, d: k == "json" and d["type"] == "hello")
            sent = [frames.push(key=i == 0) for i in range(12)]
            await ws.send_json({"type": "drawn", "track": "us", "seq": sent[0].seq,
                                "draw_to_send_ms": 0})  # fmt: skip
            while not server.tracks["us"].drawn:
                await asyncio.sleep(0.005)
            asked = frames.keyframe_requests
            more = [frames.push(key=False) for _ in range(3)]  # 11 undrawn: held back
            got = []
            while len(got) < 12:
                h, _ = await next_message(ws, lambda k, d: k == "frame")
                got.append(h["seq"])
            assert got == [f.seq for f in sent]
            assert server.tracks["us"].encoded_dropped == 3 and frames.keyframe_requests == asked
            await ws.send_json({"type": "drawn", "track": "us", "seq": sent[-1].seq,
                                "draw_to_send_ms": 0})  # fmt: skip
            while server.tracks["us"].drawn < 2:
                await asyncio.sleep(0.005)
            frames.push(key=False)  # caught up: a keyframe is asked for, this one dropped
            assert frames.keyframe_requests == asked + 1
            key = frames.push()
            h, _ = await next_message(ws, lambda k, d: k == "frame")
            assert h["seq"] == key.seq and h["keyframe"] and more[-1].seq < key.seq
    finally:
        await server.stop()
