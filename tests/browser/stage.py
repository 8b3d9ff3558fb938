"""What a browser scenario gets, inside its network namespace: :class:`Ctx`.

``ctx.page(url)`` opens a page in headless Chromium (self-signed certificates accepted, the
page's console errors collected, optionally Meta's IWER WebXR emulator installed first);
``ctx.shot(page, name)`` saves a screenshot in the scenario's directory; ``ctx.daemons()``
starts a signaling server here and the daemons as processes (tests/session's
:class:`Session`: ``start``, ``kill``, ``stats``, ``wait``); ``ctx.demo()`` runs
``humantele demo``; ``ctx.feed()`` serves the headset page from a feed in this process, which
the scenario publishes to; ``ctx.console()`` the sonographer's console, over the scenario's
frames and session. Everything is stopped at the end, pages first (an aiohttp runner
waits for open pages otherwise).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import secrets
import signal
import sys
import time
from pathlib import Path
from typing import Any

from playwright.async_api import Browser, BrowserContext, Page, async_playwright

from humantele.runtime.signal_child import signal_child

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent / "session"), str(HERE.parent)]  # its helpers, and tests/'s

from netns import GROUPS_FILE, chromium_path  # noqa: E402
from session_helpers import CONSOLE_KEY, PAIRING_CODE, Session, read_json  # noqa: E402

from session_slot import scaled  # noqa: E402
from waits import until  # noqa: E402

IWER = HERE / "vendor" / "iwer" / "iwer.min.js"
CHROMIUM_ARGS = [
    "--allow-loopback-in-peer-connection",  # WebRTC ICE on loopback, in the namespace
    "--disable-features=WebRtcHideLocalIpsWithMdns",
    "--autoplay-policy=no-user-gesture-required",
    "--enable-unsafe-swiftshader",  # WebGL in software, headless (the headset page)
    "--use-angle=swiftshader",
]
# The sonographer's pages composite in software, as Chromium does by itself on a machine
# without a GPU (chrome://gpu: "Compositing: Software only"): composited through
# SwiftShader's emulated GPU instead, the console's two videos cost the GPU process 76 % of a
# core. A headset has a GPU: its pages (``headset=True``) open in a second Chromium that
# composites on the emulated one, so WebGL frames are not read back to a software compositor
# (that added ~90 ms from a pose's receipt to the page's draw).
SOFTWARE_COMPOSITING = ["--disable-gpu-compositing"]
# The pages' windows (CSS px): the sonographer's screen; a headset browser's window, smaller:
# its WebGL scene is rendered (antialiased) and composited in SwiftShader on the CPU, which at
# 1280 x 800 took 1.4 cores (30 CPU-s in a 21 s scenario), 19 CPU-s at this size, starving
# the daemons of the tests running beside it. (scenarios/pages_bench.py keeps 1280 x 800.)
CONSOLE_WINDOW = (1280, 800)
HEADSET_WINDOW = (960, 600)
# A headset page draws at most every 200 ms in the tests, in WebXR under IWER too. Its WebGL
# scene is rendered in SwiftShader on the CPU, about 0.14 CPU-s a frame in Chromium's GPU
# process: the page drew as fast as that process could (6 frames a second at load 7), which
# took 59 % of headset_feed's CPU (41-46 of 71-77 CPU-s). No check needs a rate: they wait for
# frames drawn (``headset.frames``) and states shown, and the draw latency is a figure, not a
# bound. headset_feed at load 7-9: 60-77 CPU-s at Chromium's rate, 49 at this one (3 frames a
# second). scenarios/pages_bench.py measures the page at Chromium's own rate
# (``ctx.headset_frame_ms = 0``). IWER runs the XR session's frames on the window's
# requestAnimationFrame, so the cap, installed before it, holds them too: the four headset
# modules (registration, replayed clinic, session, feed) took 140 CPU-s with it and 169
# without, Chromium's GPU processes 30 and 58, in the same wall time, all 25 tests passing
# (2026-11-29, one run each, quiet host).
HEADSET_FRAME_MS = 200
# The page's requestAnimationFrame, answered on every animation frame at least ``every`` ms
# after the last one answered (all callbacks of one frame together); its ids kept so that
# cancelAnimationFrame (three.js's loop stopping) still cancels.
FRAME_EVERY = """(() => {
  const every = %d, raf = window.requestAnimationFrame.bind(window);
  const caf = window.cancelAnimationFrame.bind(window), pending = new Map();
  let next = 1, open = -Infinity;
  window.requestAnimationFrame = (cb) => {
    const id = next++;
    const tick = (t) => {
      if (t !== open && t - open < every - 1) { pending.set(id, raf(tick)); return; }
      open = t;
      pending.delete(id);
      cb(t);
    };
    pending.set(id, raf(tick));
    return id;
  };
  window.cancelAnimationFrame = (id) => {
    if (pending.has(id)) caf(pending.get(id));
    pending.delete(id);
  };
})();"""
# A headset page's WebGL drawn without multisampling in the tests (with the frame cap, so not
# in pages_bench; nor in tools/page_screenshots.py's pictures): 4x MSAA in SwiftShader cost
# the GPU process 0.064 CPU-s a frame against 0.048 (960 x 600, the feed's scene,
# 2026-11-29), and no check reads an edge's smoothing: they read where objects are drawn and
# in which colour. A headset's GPU resolves it for free.
NO_MSAA = """(() => {
  const get = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, attrs) {
    if (kind === 'webgl2' || kind === 'webgl') attrs = { ...(attrs || {}), antialias: false };
    return get.call(this, kind, attrs);
  };
})();"""
# Meta's emulator as a Quest 3, installed before any page script runs.
IWER_INSTALL = (  # the device kept as window.xrDevice: a scenario may move the headset
    "globalThis.xrDevice = new IWER.XRDevice(IWER.metaQuest3);"
    " xrDevice.installRuntime({forceInstall: true});"
)


class Ctx:
    """A scenario's browser and the processes it started; use as ``async with``."""

    def __init__(self, out_dir: Path, args: dict[str, Any]) -> None:
        self.out = out_dir
        self.args = args
        self.browser: Browser | None = None  # the sonographer's (software compositing)
        self._headset_browser: Browser | None = None  # a headset's, on first use
        self.console_errors: list[str] = []
        self.t0 = time.monotonic()
        self.marks: list[tuple[str, float]] = []  # (step, s since the scenario started)
        self._contexts: list[BrowserContext] = []
        self._services = contextlib.AsyncExitStack()
        self._pw = None
        self.headset_frame_ms = HEADSET_FRAME_MS  # 0: Chromium's own rate (the bench)

    async def __aenter__(self) -> Ctx:
        self._pw = await async_playwright().start()
        self.browser = await self._launch(SOFTWARE_COMPOSITING)
        return self

    async def _launch(self, more: list[str]) -> Browser:
        extra = ["--no-sandbox"] if os.geteuid() == 0 else []
        return await self._pw.chromium.launch(
            executable_path=chromium_path(), args=[*CHROMIUM_ARGS, *more, *extra]
        )

    async def __aexit__(self, *exc: object) -> None:
        for c in self._contexts:  # pages first
            with contextlib.suppress(Exception):
                await c.close()
        await self._services.aclose()
        for browser in (self.browser, self._headset_browser):
            if browser is not None:
                await browser.close()
        if self._pw is not None:
            await self._pw.stop()

    def mark(self, step: str) -> None:
        """Note that ``step`` is done, and when (the result's ``marks``: where time goes)."""
        self.marks.append((step, round(time.monotonic() - self.t0, 2)))

    # --- the browser ----------------------------------------------------------------------

    async def page(
        self,
        url: str,
        iwer: bool = False,
        width: int | None = None,
        height: int | None = None,
        init_script: str = "",
        headset: bool = False,
    ) -> Page:
        """A new page (its own context) at ``url``; with ``iwer``, the WebXR emulator;
        ``init_script``: JavaScript run before the page's own (e.g. its storage);
        ``headset`` (implied by ``iwer``): in the headset's browser (GPU compositing);
        ``width`` x ``height`` (CSS px): by default the window of the browser it opens in."""
        assert self.browser is not None
        browser = self.browser
        default_w, default_h = HEADSET_WINDOW if headset or iwer else CONSOLE_WINDOW
        width, height = width or default_w, height or default_h
        if headset or iwer:
            if self._headset_browser is None:
                self._headset_browser = await self._launch([])
            browser = self._headset_browser
        context = await browser.new_context(
            ignore_https_errors=True, viewport={"width": width, "height": height}
        )
        self._contexts.append(context)
        if (headset or iwer) and self.headset_frame_ms:
            await context.add_init_script(FRAME_EVERY % self.headset_frame_ms)
            if not self.args.get("pictures"):  # the docs' pictures: as a headset draws them
                await context.add_init_script(NO_MSAA)
        if iwer:
            await context.add_init_script(IWER.read_text() + "\n" + IWER_INSTALL)
        if init_script:
            await context.add_init_script(init_script)
        # Playwright's own waits (a navigation, a click's target) 30 s by default: scaled, as
        # every deadline here (session_slot.time_scale), so a loaded machine gets more time
        context.set_default_timeout(scaled(30.0) * 1000)
        context.set_default_navigation_timeout(scaled(60.0) * 1000)
        page = await context.new_page()
        page.on(
            "console",
            lambda m: self.console_errors.append(f"{url}: {m.text}") if m.type == "error" else None,
        )
        page.on("pageerror", lambda e: self.console_errors.append(f"{url}: {e}"))
        await page.goto(url)
        return page

    async def until(self, page: Page, expression: str, timeout: float = 30.0) -> Any:
        """Poll ``expression`` (JavaScript) in the page until it is truthy; its value.
        (Playwright's ``wait_for_function`` evaluates strings, which the pages' CSP forbids;
        ``page.evaluate`` is not subject to it.) ``timeout`` (s) is scaled to the machine's
        load (session_slot.time_scale)."""
        timeout = scaled(timeout)
        end = time.monotonic() + timeout
        value = None
        while time.monotonic() < end:
            value = await page.evaluate(expression)
            if value:
                return value
            await asyncio.sleep(0.05)
        raise AssertionError(f"page: {expression!r} still {value!r} after {timeout:.0f} s")

    async def until_progress(
        self, page: Page, expression: str, progress: str, stall_s: float = 90.0,
        cap_s: float = 900.0,
    ) -> Any:  # fmt: skip
        """Poll ``expression`` (JavaScript) until it is truthy, for as long as ``progress``
        (JavaScript, a JSON-able value such as frame counters) keeps changing: it fails when
        ``progress`` has not changed for ``stall_s`` (from the start: nothing yet) or after
        ``cap_s`` in all. A page that draws slowly on a loaded machine gets there; one that
        stopped drawing fails within ``stall_s``. Both scaled (session_slot.time_scale)."""
        stall_s, cap_s = scaled(stall_s), scaled(cap_s)
        t0 = time.monotonic()
        last, changed = None, t0
        value = None
        while True:
            value = await page.evaluate(expression)
            if value:
                return value
            now = time.monotonic()
            seen = await page.evaluate(progress)
            if seen != last:
                last, changed = seen, now
            if now - changed > stall_s or now - t0 > cap_s:
                raise AssertionError(
                    f"page: {expression!r} still {value!r} after {now - t0:.0f} s; "
                    f"{progress!r} = {last!r}, unchanged for {now - changed:.0f} s"
                )
            await asyncio.sleep(0.1)

    async def wait(self, what: str, pred, timeout: float = 30.0) -> None:
        """Poll ``pred()`` (here, in the scenario) until it is true; ``timeout`` scaled."""
        await until(pred, scaled(timeout), what=what, poll=0.02)

    async def close_page(self, page: Page) -> None:
        """Close a page as a user closing the tab would."""
        await page.context.close()
        self._contexts.remove(page.context)

    async def shot(self, page: Page, name: str) -> str:
        """Save a screenshot as ``<name>.png`` in the scenario's directory; its file name."""
        await page.screenshot(path=str(self.out / f"{name}.png"))
        return f"{name}.png"

    async def still_shot(self, page: Page, name: str, tries: int = 20) -> str:
        """:meth:`shot` of a page that holds still (a frozen 3D view): screenshots a frame
        apart until two in a row are the same picture. A loaded headless Chromium can hand
        back a WebGL canvas older than the page's last draw (puppeteer#5352), which is what
        CI's one failure of the headset's probe test looked like (the probe, hidden three
        frames before, still in the picture)."""
        previous = None
        for _ in range(tries):
            png = await page.screenshot()
            if png == previous:
                (self.out / f"{name}.png").write_bytes(png)
                return f"{name}.png"
            previous = png
            await page.evaluate(
                "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))"
            )
        raise AssertionError(f"{name}: the page's picture still changing after {tries} shots")

    async def other_site(self) -> Page:
        """A page from another origin (a blank page served here on another port)."""
        url, stop = await _serve_blank()
        self._services.push_async_callback(stop)
        return await self.page(url)

    # --- what the pages talk to -----------------------------------------------------------

    async def daemons(self) -> Session:
        """A signaling server here and a :class:`Session` to start the daemons with."""
        from humantele.signaling.server import SignalConfig, SignalingServer

        token = secrets.token_urlsafe(16)
        server = SignalingServer(SignalConfig(port=0), token=token)
        await server.start()
        (self.out / "daemons").mkdir(exist_ok=True)
        session = Session(self.out / "daemons", server, token)
        self._services.push_async_callback(session.close)
        return session

    async def demo(self, *args: str, own_group: bool = False) -> DemoRun:
        """``humantele demo --keep ARGS`` running (its run directory is found under ours);
        ``own_group``: in a process group of its own, as a terminal starts it (its Ctrl-C:
        :meth:`DemoRun.ctrl_c`), its status lines (stderr) kept in ``lines`` and its
        stdout in ``demo.out``."""
        run = DemoRun(self.out / "demo")
        await run.start(*args, own_group=own_group)
        self._services.push_async_callback(run.stop)
        return run

    async def feed(self, **config: Any):
        """A headset page and feed served from this process (TLS, certificate in ours)."""
        from humantele.follower.feed import FeedConfig, RendererFeed

        feed = RendererFeed(FeedConfig(port=0, **config), self.out / "feed-state")
        await feed.start()
        self._services.push_async_callback(feed.stop)
        return feed

    async def console(self, frames, session, **config: Any):
        """The sonographer's console served from this process, over ``frames`` (a frame
        provider) and ``session`` (a ConsoleSession); captures in ours."""
        from humantele.expert.console import ConsoleConfig, ConsoleServer

        cfg = ConsoleConfig(port=0, captures_dir=str(self.out / "captures"), **config)
        server = ConsoleServer(cfg, frames, session, on_demand=getattr(frames, "demand", None))
        await server.start()
        self._services.push_async_callback(server.stop)
        return server


async def _serve_blank(host: str = "127.0.0.1"):
    """A page of another origin (another site, as far as a browser knows): its URL and a
    stop function."""
    from aiohttp import web

    app = web.Application()
    app.router.add_get("/", lambda r: web.Response(text="<!doctype html><title>other</title>",
                                                   content_type="text/html"))  # fmt: skip
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    return f"http://{host}:{port}/", runner.cleanup


def page_url(follower_stats: dict) -> str | None:
    """The headset page of a follower from its stats, on loopback (the namespace has no other
    address the page could be reached at), with the pairing code the harness gave the
    follower (``#code=``: the page keeps it, as if typed)."""
    feed = follower_stats.get("feed") or {}
    url = feed.get("page_url")
    if not url:
        return None
    scheme, rest = url.split("://", 1)
    port = rest.split("/", 1)[0].rsplit(":", 1)[1]
    return f"{scheme}://127.0.0.1:{port}/#code={PAIRING_CODE}"


def console_url(expert_stats: dict) -> str | None:
    """The console of an expert from its stats, with the key the harness gave the expert (the
    stats never carry it)."""
    url = (expert_stats.get("console") or {}).get("url")
    return f"{url}#key={CONSOLE_KEY}" if url else None


class DemoRun:
    """``humantele demo`` as a process; ``stats(role)`` reads a daemon's stats."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.proc: asyncio.subprocess.Process | None = None
        self.own_group = False
        self.lines: list[str] = []  # its stderr's lines, with ``own_group``
        self._reader: asyncio.Task | None = None

    async def start(self, *args: str, own_group: bool = False) -> None:
        self.tmp.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, TMPDIR=str(self.tmp))
        env.pop("HUMANTELE_TOKEN", None)
        env.update(HUMANTELE_CONSOLE_KEY=CONSOLE_KEY, HUMANTELE_PAIRING_CODE=PAIRING_CODE)
        self.own_group = own_group
        log = open(self.tmp / "demo.log", "wb")  # noqa: SIM115 - the child has it
        out = open(self.tmp / "demo.out", "wb") if own_group else log  # noqa: SIM115
        self.proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "humantele", "demo", "--keep", "--log-level", "INFO", *args,
            stdin=asyncio.subprocess.DEVNULL, stdout=out,
            stderr=asyncio.subprocess.PIPE if own_group else log, env=env,
            start_new_session=own_group,
        )  # fmt: skip
        out.close()
        if own_group:  # noted, so that a runner killed on its deadline takes it along
            with open(self.tmp.parent / GROUPS_FILE, "a") as f:
                f.write(f"{self.proc.pid}\n")
            self._reader = asyncio.create_task(self._read_lines(log))
        else:
            log.close()

    async def _read_lines(self, log) -> None:
        """Its stderr, line by line, into ``lines`` and ``demo.log``."""
        assert self.proc is not None and self.proc.stderr is not None
        with log:
            while line := await self.proc.stderr.readline():
                self.lines.append(line.decode(errors="replace"))
                log.write(line)
                log.flush()

    async def ctrl_c(self, timeout: float = 60.0) -> int:
        """A terminal's Ctrl-C (``own_group``): SIGINT to its process group, the demo, both
        daemons and their children at once; its exit code, once its stderr is read."""
        assert self.proc is not None and self.own_group
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGINT)
        await asyncio.wait_for(self.proc.wait(), timeout)
        if self._reader is not None:
            await asyncio.wait_for(self._reader, 10)
        return self.proc.returncode

    def stdout(self) -> str:
        """What it printed (``own_group``: ``--json``'s summary is the last line)."""
        return (self.tmp / "demo.out").read_text(errors="replace")

    def run_dir(self) -> Path | None:
        dirs = sorted(self.tmp.glob("humantele-demo-*"))
        return dirs[0] if dirs else None

    def stats(self, role: str) -> dict:
        d = self.run_dir()
        return {} if d is None else read_json(d / f"{role}.json")

    async def wait(self, what: str, pred, timeout: float = 60.0) -> None:
        """Poll ``pred(expert stats, follower stats)`` until true; ``timeout`` (s) scaled."""
        timeout = scaled(timeout)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred(self.stats("expert"), self.stats("follower")):
                return
            if self.proc is not None and self.proc.returncode is not None:
                break
            await asyncio.sleep(0.2)
        raise AssertionError(
            f"demo: failed waiting for {what} ({timeout:.0f} s); "
            f"follower {json.dumps(self.stats('follower'))}"
        )

    async def stop(self) -> None:
        if self.proc is None:
            return
        if self.proc.returncode is None:
            signal_child(self.proc, signal.SIGTERM)
            try:
                await asyncio.wait_for(self.proc.wait(), 30)
            except TimeoutError:
                signal_child(self.proc, signal.SIGKILL)
                await self.proc.wait()
        if self.own_group:  # whatever of its group is left (the runner's group is not it)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        if self._reader is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._reader, 10)
