"""``GET /web/...`` on both daemons' web servers (the console's and the headset page's): the
page's own files, and a plain 404 for any other name, never a 500 with a traceback (issue 20
item 5: a 5000-character name gave ENAMETOOLONG)."""

from __future__ import annotations

import logging

import aiohttp
from aiohttp import web

from humantele.expert.console import ConsoleConfig, ConsoleServer
from humantele.expert.console.server import WEB_DIR as CONSOLE_WEB
from humantele.follower.feed import WEB_DIR as HEADSET_WEB
from humantele.follower.feed import FeedConfig, RendererFeed
from humantele.web.static import add_page_files, page_files

BAD_NAMES = [
    "a" * 5000,  # ENAMETOOLONG for the file system
    "a/" * 3000 + "x",
    "vendor/" + "b" * 300,
    "..%2f..%2fserver.py",
    "%2e%2e/server.py",
    "a%00b",
    "vendor",  # a directory
    "vendor/three",
    "nothing.js",
    "",
]


class _Session:
    recorder = None
    scan = None

    def snapshot(self) -> dict:
        return {"link": {"state": "connected"}, "scan": None, "force": {}, "alignment": {}}

    def pose_at(self, t: float):
        return None


async def _check(base: str, own: list[str], web_dir, caplog) -> None:
    caplog.set_level(logging.ERROR)
    async with aiohttp.ClientSession() as s:
        for name in own:
            async with s.get(f"{base}/web/{name}") as r:
                assert r.status == 200, name
                assert await r.read() == (web_dir / name).read_bytes()
        for name in BAD_NAMES:
            async with s.get(f"{base}/web/{name}") as r:
                assert r.status == 404, (name[:40], r.status)
            async with s.head(f"{base}/web/{name}") as r:
                assert r.status == 404, (name[:40], r.status)
    assert "Traceback" not in caplog.text and "Error handling request" not in caplog.text


async def test_console_serves_its_files_and_404_for_any_other_name(tmp_path, caplog):
    config = ConsoleConfig(port=0, captures_dir=str(tmp_path / "captures"))
    server = ConsoleServer(config, None, _Session())
    await server.start()
    try:
        base = server.address.rstrip("/")  # (url carries the page's key after a #)
        await _check(base, ["console.js", "style.css", "index.html"], CONSOLE_WEB, caplog)
    finally:
        await server.stop()


async def test_headset_page_serves_its_files_and_404_for_any_other_name(caplog):
    feed = RendererFeed(FeedConfig(port=0, host="127.0.0.1", tls=False))
    await feed.start()
    try:
        base = f"http://127.0.0.1:{feed.port}"
        own = ["headset.js", "vendor/three/three.module.js", "vendor/three/LICENSE"]
        await _check(base, own, HEADSET_WEB, caplog)
    finally:
        await feed.stop()


def test_only_regular_files_inside_are_listed(tmp_path):
    (tmp_path / "a.js").write_text("x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.css").write_text("y")
    (tmp_path / ".hidden").write_text("z")
    (tmp_path / "__pycache__").mkdir()
    (tmp_path / "__pycache__" / "c.pyc").write_text("z")
    outside = tmp_path.parent / "outside.txt"
    outside.write_text("secret")
    (tmp_path / "link.txt").symlink_to(outside)
    assert sorted(page_files(tmp_path)) == ["a.js", "sub/b.css"]


async def test_served_files_have_their_types():
    app = web.Application()
    add_page_files(app, HEADSET_WEB)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # noqa: SLF001
    try:
        async with aiohttp.ClientSession() as s:
            async with s.get(f"http://127.0.0.1:{port}/web/headset.js") as r:
                assert "javascript" in r.headers["Content-Type"]  # module scripts need it
            async with s.get(f"http://127.0.0.1:{port}/web/index.html") as r:
                assert r.headers["Content-Type"].startswith("text/html")
    finally:
        await runner.cleanup()
