"""The two video tracks over real aiortc on loopback, through a real signaling server."""

import asyncio
import contextlib
import os
import signal
import sys
from pathlib import Path

import pytest
from media_helpers import SyncErrorBound, close_video_link, small_video_config, video_follower

from humantele.media.config import ExpertVideoConfig
from humantele.media.receiver import VideoReceiver
from humantele.signaling.messages import TOKEN_ENV
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink
from waits import until

TOKEN = "video-test-token"


@pytest.fixture
async def server():
    s = SignalingServer(SignalConfig(port=0), TOKEN)
    await s.start()
    yield s
    await s.stop()


def expert_with_video(server, codec="vp8", record=None):
    holder = {}
    link = PeerLink(
        "expert",
        LinkConfig(signaling_url=server.url, room="v", token=TOKEN),
        media=lambda pc, role: holder["rx"].prepare(pc),
    )
    config = ExpertVideoConfig(enabled=True, codec=codec)
    holder["rx"] = VideoReceiver(config, link.clock, link.now, record)
    return link, holder["rx"]


@pytest.mark.parametrize("codec", ["vp8", "h264"])
async def test_both_tracks_arrive_with_counter_and_capture_time(server, codec):
    expert, rx = expert_with_video(server, codec)
    follower, tx = video_follower(server.url, "v", TOKEN)
    sync = SyncErrorBound(rx.clock)
    loop = asyncio.get_running_loop()
    tx.open()
    tx.start(loop)
    tasks = [asyncio.create_task(expert.run()), asyncio.create_task(follower.run())]
    try:
        await expert.wait_state("connected", timeout=30)
        await until(lambda: expert.clock.synced, 10)
        await until(lambda: all(rx.stats_by_track[n].frames >= 15 for n in ("us", "pov")), 30)
        for name in ("us", "pov"):
            st = rx.stats_by_track[name]
            await until(lambda n=name: rx.latest(n).seq is not None)  # its number is known
            f = rx.latest(name)
            # the counter reads on every frame, goes forward in order, and every frame after
            # the first anchored one has its capture time
            assert st.out_of_order == 0
            assert st.unreadable == 0
            assert len(st.ages) >= st.frames - 3
            # one process, one clock: an age below 0 is the clock sync's error (within half
            # the round trip of its best exchange: ms on loopback, tens of ms loaded); a wrong
            # capture time is seconds
            floor = -(sync.worst_s + 0.005)
            assert all(floor <= a < 5.0 for a in st.ages), (min(st.ages), max(st.ages), floor)
            assert f.t_capture is not None and f.t_capture <= f.t_received - floor
        assert (rx.latest("us").width, rx.latest("us").height) == (320, 240)
        assert (rx.latest("pov").width, rx.latest("pov").height) == (320, 180)
        # the decoded picture is the source's: the US image is not the POV
        img = await asyncio.to_thread(rx.latest("us").image)
        assert img.shape == (240, 320, 3)
        assert tx.stats()["us"]["sent"] >= 15 and tx.infos_sent + tx.infos_dropped >= 30
        # aiortc encoded with our encoders and assembled frames with our jitter buffers
        rx_stats, tx_stats = rx.stats(), tx.stats()
        for name in ("us", "pov"):
            assert tx_stats[name]["encoder"]["restarts"] >= 1
            assert rx_stats[name]["jitter"]["frames"] >= rx.stats_by_track[name].frames
    finally:
        await close_video_link(follower, expert, tx, rx, tasks)


async def _spawn_follower(url: str, room: str) -> asyncio.subprocess.Process:
    env = {**os.environ, TOKEN_ENV: TOKEN}
    child = Path(__file__).with_name("video_child.py")
    return await asyncio.create_subprocess_exec(
        sys.executable, str(child), url, room,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip


def _alive_children(pid: int) -> set[int]:
    """Live (not zombie) processes whose parent is ``pid``."""
    out = set()
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                out.add(int(d))
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
async def test_tracks_come_back_after_the_follower_process_is_killed_and_restarted(server):
    expert, rx = expert_with_video(server)
    run = asyncio.create_task(expert.run())
    procs = []
    try:
        procs.append(await _spawn_follower(server.url, "v"))
        await expert.wait_state("connected", timeout=60)
        await until(lambda: all(rx.stats_by_track[n].frames >= 10 for n in ("us", "pov")), 60)
        first = {n: rx.latest(n) for n in ("us", "pov")}

        video_procs = _alive_children(procs[0].pid)  # the follower's video process (and tracker)
        assert video_procs
        procs[0].send_signal(signal.SIGKILL)
        await procs[0].wait()
        # nothing of the killed follower lives on (the video process notices and ends)
        await until(lambda: not any(_alive(p) for p in video_procs), 30)
        await expert.wait_state("disconnected", "connecting", timeout=15)
        frames_before = {n: rx.stats_by_track[n].frames for n in ("us", "pov")}

        procs.append(await _spawn_follower(server.url, "v"))
        await expert.wait_state("connected", timeout=60)
        tracks = ("us", "pov")
        more = frames_before
        await until(lambda: all(rx.stats_by_track[n].frames >= more[n] + 10 for n in tracks))
        assert rx.tracks_started == 4  # two tracks on each of the two peer connections
        for name in ("us", "pov"):
            f = rx.latest(name)
            assert f is not first[name] and f.seq is not None
            assert f.age_s is not None and 0.0 <= f.age_s < 5.0
    finally:
        for p in procs:
            if p.returncode is None:
                p.kill()
                await p.wait()
        await expert.close()
        await rx.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(run, 5)


@pytest.mark.slow
async def test_us_image_follows_the_probe_through_the_video_process(server):
    """The sim world's probe on the kidney, then lifted off the skin: the decoded US image at
    the expert goes from an image to dark (the sources run in the video process)."""
    from humantele.video.scene import DEFAULT_PATIENT, DemoScene, SceneSnapshot

    expert, rx = expert_with_video(server)
    follower, tx = video_follower(server.url, "v", TOKEN, small_video_config(process=True))
    demo = DemoScene()
    lifted = {"on": False}

    async def world() -> None:  # the follower's tick publishing the sim world
        while True:
            s = demo()
            if lifted["on"]:  # no contact: the probe 5 cm above the skin, no force
                tip = s.T_world_tip
                tip = type(tip)(tip.position + [0.0, 0.05, 0.0], tip.quaternion)
                s = SceneSnapshot(s.t, DEFAULT_PATIENT, tip, 0.0, s.T_world_head)
            tx.publish_scene(s)
            await asyncio.sleep(0.01)

    await asyncio.to_thread(tx.open)
    tx.start(asyncio.get_running_loop())
    tasks = [asyncio.create_task(t) for t in (expert.run(), follower.run(), world())]

    async def us_brightness(after_seq: int) -> tuple[int, float]:
        await until(lambda: (f := rx.latest("us")) is not None and (f.seq or 0) > after_seq + 5)
        f = rx.latest("us")
        img = await asyncio.to_thread(f.image)
        return f.seq, float(img[40:, :].mean())  # below the counter

    try:
        await expert.wait_state("connected", timeout=60)
        seq, on = await us_brightness(0)
        lifted["on"] = True
        _, off = await us_brightness(seq)
        assert on > 20.0 and off < 0.5 * on, (on, off)
    finally:
        tasks[2].cancel()
        await close_video_link(follower, expert, tx, rx, tasks)


async def test_a_listener_gets_each_decoded_frame_with_the_encoded_frame_it_came_from(server):
    """The console's forwarding: with no listener nothing is kept; a listener gets every
    decoded frame in order with its encoded frame; after a keyframe request a keyframe comes,
    and a fresh decoder fed the encoded frames from it gives the very pictures the expert
    decoded (the page's decoder shows what the cine and captures keep)."""
    import av
    import numpy as np

    expert, rx = expert_with_video(server, "vp8")
    follower, tx = video_follower(server.url, "v", TOKEN)
    loop = asyncio.get_running_loop()
    tx.open()
    tx.start(loop)
    tasks = [asyncio.create_task(expert.run()), asyncio.create_task(follower.run())]
    got: list = []
    try:
        await expert.wait_state("connected", timeout=30)
        await until(lambda: rx.stats_by_track["us"].frames >= 10, 30)
        assert not rx._released["us"] and not rx.listeners["us"]
        rx.listen("us", lambda f, enc: got.append((f, enc)))
        assert rx.request_keyframe("us")
        await until(lambda: any(e is not None and e.keyframe for _, e in got), 20)
        start = next(i for i, (_, e) in enumerate(got) if e is not None and e.keyframe)
        await until(lambda: len(got) >= start + 12, 20)
        rx.unlisten("us", got.append)  # (not the listener: nothing happens)
        frames = got[start : start + 12]
        seqs = [f.seq for f, _ in frames]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
        assert all(e is not None for _, e in frames)
        decoder = av.CodecContext.create("vp8", "r")
        for f, enc in frames:
            (mine,) = decoder.decode(av.Packet(enc.data))
            a = mine.to_ndarray(format="yuv420p")
            b = f.frame.to_ndarray(format="yuv420p")
            assert np.array_equal(a, b), f.seq
    finally:
        rx.listeners["us"].clear()
        await close_video_link(follower, expert, tx, rx, tasks)
