"""The console tells the truth when its expert daemon is slow: the console's server runs on an
event loop of its own (a thread here, as the expert daemon's loop), which the scenario holds up
on purpose, periodically (a loaded daemon) and for as long as it likes (a stalled one). The
page must say "slow (N ms)" and never "lost contact" while the socket is open, grey what is
stale, say when a click is not acknowledged and when it cannot be sent; a picture is live only
when it was captured less than the stale bound ago; and the first screen explains an empty
picture."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np

from humantele.expert.console.frames import _Subscribers
from humantele.video.base import VideoFrame
from procgroups import descendants

SNAPSHOT_JS = """() => {
  const $ = (id) => document.getElementById(id);
  const shown = (id) => $(id).hidden ? null : $(id).textContent;
  return {
    lost: shown('lost'), slow: shown('slow'),
    expert: document.querySelector('#chip-expert .v').textContent,
    expert_level: $('chip-expert').dataset.level,
    chips_stale: [...document.querySelectorAll('#chips li')]
      .filter((l) => l.dataset.stale === 'true').map((l) => l.id),
    us_stale: $('us-box').dataset.stale, us_overlay: shown('us-stale'),
    us_info: $('us-info').textContent, empty: shown('us-empty'),
    frames: consoleApp.frames.us, tool: $('tool-result').textContent,
    control: $('control-result').textContent, frozen: consoleApp.frozen,
  };
}"""


class Frames(_Subscribers):
    """A frame provider: a US and a POV frame every 100 ms (a grey picture with a moving bar),
    captured ``capture_delay_s`` before they are there (a late source), none while ``off``;
    each new one also to the console's subscription (as the expert's sources give them)."""

    def __init__(self) -> None:
        super().__init__()
        self.off = True
        self.capture_delay_s = 0.0
        self.period_s = 0.1  # s between frames
        self.scale = 1  # times the pictures' width and height
        self._latest: dict = {}
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            if self.off:
                continue
            self._seq += 1
            for track, (w, h) in (("us", (320, 240)), ("pov", (320, 180))):
                w, h = w * self.scale, h * self.scale
                img = np.full((h, w, 3), 90, np.uint8)
                x = (self._seq * 7) % w
                img[:, x : x + 12] = 220
                spacing = (0.2, 0.2) if track == "us" else None
                t = time.monotonic() - self.capture_delay_s
                self._latest[track] = VideoFrame(img, self._seq, t, spacing)
                self._notify(track, self._latest[track])

    def latest(self, track: str):
        return None if self.off else self._latest.get(track)

    def stop(self) -> None:
        self._stop.set()


def renderers() -> list[int]:
    """This scenario's Chromium renderer processes (the console's page is the only page)."""
    out = []
    for pid in descendants(os.getpid()):
        with contextlib.suppress(OSError):
            if b"--type=renderer" in Path(f"/proc/{pid}/cmdline").read_bytes():
                out.append(pid)
    return out


class Starved:
    """The page's renderer given ``share`` of the time: stopped (SIGSTOP) for the rest of every
    ``period_s``, as a busy machine's scheduler leaves a browser. Not Chromium's CPU throttling
    (``Emulation.setCPUThrottlingRate``): it spins the page's thread in a signal handler (its
    renderer took 0.78 of a core throttled 100 times, 0.30 not), and on a busy machine its
    throttling thread gets too little time to throttle (one core busy: the page took 8-11 s
    to fall behind, then 32-54 s until the daemon held its messages and it caught up, spinning
    all along; this phase was 45-50 CPU-s of the scenario's 46-50). A stopped process spends
    nothing and falls behind whatever the machine does (the scenario: 8-9 CPU-s quiet, 7-8
    with a core busy). Use as ``async with``."""

    def __init__(self, share: float, period_s: float = 0.1) -> None:
        self.share, self.period_s = share, period_s
        self.pids: list[int] = []
        self._task: asyncio.Task | None = None

    def _signal(self, sig: int) -> None:
        for pid in self.pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)

    async def _cycle(self) -> None:
        while True:
            self._signal(signal.SIGSTOP)
            await asyncio.sleep((1.0 - self.share) * self.period_s)
            self._signal(signal.SIGCONT)
            await asyncio.sleep(self.share * self.period_s)

    async def __aenter__(self) -> Starved:
        self.pids = renderers()
        assert self.pids, "no renderer process to starve"
        self._task = asyncio.create_task(self._cycle())
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._signal(signal.SIGCONT)


class Session:
    """The session as the console sees it: the link, the probe's contact, commands."""

    def __init__(self) -> None:
        self.recorder = None
        self.link = "connecting"
        self.contact = False
        self.scan = None
        self.commands: list = []

    def snapshot(self) -> dict:
        up = self.link == "connected"
        return {
            "link": {"state": self.link, "pose_age_ms": 20.0 if up else None},
            "calibration": {"state": "calibrating", "landmark": "xiphoid", "last": None},
            "alignment": None,
            "servo": {"alive": True, "rate_hz": 1000.0, "fault": ""},
            "recording": {"on": False, "error": None, "written": 0},
            "scan": self.scan,
            "clutch": {"on": False, "engaged": False},
            "force": {
                "measured_n": 6.0 if self.contact else 0.0,
                "rendered_n": 0.0,
                "contact": self.contact,
            },  # fmt: skip
        }

    def pose_at(self, t: float):
        return None

    def start_scan(self) -> int:
        self.scan = 1
        self.commands.append("scan")
        return 1

    def stop_scan(self) -> None:
        self.scan = None

    def set_clutch(self, on: bool) -> None:
        self.commands.append(("clutch", on))


class DaemonLoop:
    """An event loop in a thread, as the expert daemon's: the console's server runs on it, and
    the scenario holds it up (``hold`` until ``release``, or ``periodic`` holds)."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self._gate = threading.Event()
        self.held_s = 0.0

    async def run(self, coro):
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def _hold(self, seconds: float) -> None:
        t0 = time.monotonic()
        self._gate.wait(seconds)
        self.held_s += time.monotonic() - t0

    def hold(self) -> None:
        """Hold the loop until :meth:`release` (at most 60 s)."""
        self._gate.clear()
        self.loop.call_soon_threadsafe(self._hold, 60.0)

    def release(self) -> None:
        self._gate.set()

    async def periodic(self, hold_s: float, every_s: float, for_s: float) -> None:
        """Hold the loop ``hold_s`` out of every ``every_s``, for ``for_s``."""

        async def holds():
            end = time.monotonic() + for_s
            while time.monotonic() < end:
                await asyncio.sleep(every_s - hold_s)
                self._gate.clear()
                self._hold(hold_s)

        self._periodic = asyncio.run_coroutine_threadsafe(holds(), self.loop)

    def stop(self) -> None:
        self.release()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


async def shot(ctx, page, name: str, data: dict) -> None:
    """A screenshot for people to look at, best effort: on a loaded machine Chromium may take
    longer than playwright waits (the page's behaviour is what the test checks)."""
    try:
        await ctx.shot(page, name)
    except Exception as exc:  # noqa: BLE001 - playwright's TimeoutError
        data.setdefault("shots_missed", []).append(f"{name}: {exc}"[:200])


async def sample(ctx, page, seconds: float, every_s: float = 0.1) -> list[dict]:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        out.append(await page.evaluate(SNAPSHOT_JS))
        await asyncio.sleep(every_s)
    return out


async def run(ctx) -> dict:
    from humantele.expert.console import ConsoleConfig, ConsoleServer

    frames, session, daemon = Frames(), Session(), DaemonLoop()
    cfg = ConsoleConfig(port=0, captures_dir=str(ctx.out / "captures"), stale_after_s=1.0)
    server = ConsoleServer(cfg, frames, session)
    await daemon.run(server.start())
    data: dict = {}
    snap = lambda: page.evaluate(SNAPSHOT_JS)  # noqa: E731
    try:
        page = await ctx.page(server.url, width=1280, height=800)

        # 1. The first screen: no frame yet, the link connecting; then the link up; then
        #    frames of a probe not on the patient (an empty picture); then contact.
        overlay = "document.getElementById('us-stale').textContent"
        data["first"] = await ctx.until(page, f"/connecting/.test({overlay}) && {overlay}", 30)
        await shot(ctx, page, "console_load_first", data)
        session.link = "connected"
        data["no_video"] = await ctx.until(
            page, f"/follower's ultrasound/.test({overlay}) && {overlay}", 30
        )
        frames.off = False
        empty = (
            "!document.getElementById('us-empty').hidden"
            " && document.getElementById('us-empty').textContent"
        )
        data["empty"] = await ctx.until(page, empty, 30)
        await shot(ctx, page, "console_load_empty", data)
        session.contact = True
        await ctx.until(page, "document.getElementById('us-empty').hidden", 30)
        await ctx.until(page, "document.getElementById('us-box').dataset.stale === 'false'", 30)
        data["live"] = await snap()
        ctx.mark("first screens, live")

        # 2. Frames that keep coming but were captured 1.6 s before: not live, and the page
        #    says how old the picture is.
        frames.capture_delay_s = 1.6
        n0 = await page.evaluate("consoleApp.frames.us")
        data["late"] = await ctx.until(
            page, f"consoleApp.frames.us > {n0 + 5} && document.getElementById('us-box')"
            ".dataset.stale === 'true' && document.getElementById('us-stale').textContent", 30,
        )  # fmt: skip
        data["late_frames"] = [n0, await page.evaluate("consoleApp.frames.us")]
        # The page's map of the daemon's clock (here, this process's monotonic clock) against
        # the truth, known to within half the time the page took to answer.
        t0 = time.monotonic()
        clock = await page.evaluate("({now: performance.now(), off: consoleApp.heartbeat.offset,"
                                    " rtt: consoleApp.heartbeat.rtt})")  # fmt: skip
        t1 = time.monotonic()
        clock["true_off_ms"] = (t0 + t1) / 2 * 1000 - clock["now"]
        clock["within_ms"] = (t1 - t0) / 2 * 1000
        data["clock"] = clock
        frames.capture_delay_s = 0.0
        await ctx.until(page, "document.getElementById('us-box').dataset.stale === 'false'", 30)

        ctx.mark("late frames")
        # 3. A loaded daemon: its loop held 0.7 s of every 1 s, for 8 s. Slow, never lost.
        await daemon.periodic(0.7, 1.0, 8.0)
        data["periodic"] = await sample(ctx, page, 8.0)
        await asyncio.sleep(1.0)

        ctx.mark("loaded daemon")
        # 4. A stalled daemon (its socket open): slow, its chips grey, the picture not live; a
        #    click not acknowledged says so, and its answer comes when the daemon does.
        daemon.hold()
        data["stall"] = await ctx.until(page, "(() => { const s = (" + SNAPSHOT_JS + ")();"
                                        " return s.chips_stale.length >= 6 && s.us_stale === 'true'"
                                        " && s.slow && s; })()", 30)  # fmt: skip
        await page.evaluate("document.getElementById('freeze').click()")
        await page.evaluate("document.getElementById('scan').click()")
        late = "/not acknowledged yet/.test(document.getElementById('tool-result').textContent)"
        await ctx.until(page, f"{late} && /not acknowledged yet/.test(document."
                        "getElementById('control-result').textContent)", 30)  # fmt: skip
        data["stall_click"] = await snap()
        await shot(ctx, page, "console_load_slow", data)
        daemon.release()
        data["answered"] = await ctx.until(
            page, "(() => { const s = (" + SNAPSHOT_JS + ")();"
            " return /answered after/.test(s.tool) && /answered after/.test(s.control) && s; })()",
            30,
        )  # fmt: skip
        # Recovered: the snapshot of the moment it was (a loaded machine may make the page
        # read late again a moment after, which it then says: not this check's subject).
        data["recovered"] = await ctx.until(
            page, "(() => { const s = (" + SNAPSHOT_JS + ")();"
            " return s.slow === null && s.expert_level === 'ok' && !s.chips_stale.length && s;"
            " })()",
            30,
        )  # fmt: skip
        data["commands"] = list(session.commands)
        ctx.mark("stalled daemon")

        # 5. A page that cannot keep up (its renderer given a hundredth of the time or less,
        #    with more to draw: Starved): it reads the daemon's messages late, says so ("page
        #    behind", not "slow", never "lost"), and the daemon holds its states and frames
        #    until it catches up (then it does). Starved harder until it falls behind.
        behind = ("(() => { const s = (" + SNAPSHOT_JS + ")();"
                  " return s.expert.startsWith('page behind') && s.slow && s; })()")  # fmt: skip
        data["behind"] = None
        frames.period_s, frames.scale = 1 / 30, 2  # more to draw meanwhile
        for share in (0.01, 0.005, 0.0025):
            async with Starved(share):
                with contextlib.suppress(AssertionError):
                    data["behind"] = await ctx.until(page, behind, 40)
                    data["starved"] = share
                    ctx.mark("page behind")
                    # The page judges itself behind before its next ping tells the daemon so:
                    # the daemon holds from that ping on (a page that caught up fast was let
                    # go before it had).
                    held = lambda: server.events["held_page_behind"] > 0  # noqa: E731
                    with contextlib.suppress(AssertionError):
                        await ctx.wait("the daemon holding the page's messages", held, 60)
                    data["held_page_behind"] = server.events["held_page_behind"]
            if data["behind"]:
                break
        frames.period_s, frames.scale = 0.1, 1
        assert data["behind"], "the page never fell behind, even given 1/400 of the time"
        await ctx.until(page, "document.getElementById('chip-expert').dataset.level === 'ok'"
                        " && document.getElementById('slow').hidden", 120)  # fmt: skip
        data["caught_up"] = await snap()
        ctx.mark("caught up")

        # 6. The daemon gone (its socket closed): lost contact; a click cannot be sent.
        await daemon.run(server.stop())
        data["gone"] = await ctx.until(
            page, "!document.getElementById('lost').hidden && document.getElementById('lost')"
            ".textContent", 30,
        )  # fmt: skip
        await page.evaluate("document.getElementById('capture').click()")
        data["gone_click"] = await ctx.until(
            page, "/not sent/.test(document.getElementById('tool-result').textContent) &&"
            " document.getElementById('tool-result').textContent", 10,
        )  # fmt: skip
        data["gone_snap"] = await snap()
        await shot(ctx, page, "console_load_gone", data)
        data["held_s"] = round(daemon.held_s, 2)
        data["refused"] = dict(server.refused)
        await ctx.close_page(page)
    finally:
        frames.stop()
        daemon.stop()
    return data
