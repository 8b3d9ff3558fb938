"""A killed video process comes back (issue 20 §2): the follower's VideoSender notices it on
its tick, says so (log line, state), starts a new one on the same shared memory and slots
after a back-off, and frames flow again; a stop while the new one starts neither hangs nor
leaks shared memory."""

import asyncio
import logging
import os
import signal
import time
from pathlib import Path

import pytest
from media_helpers import small_video_config

from humantele.media.sender import VideoSender
from humantele.video.scene import DEFAULT_PATIENT

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


async def _ticking_until(sender: VideoSender, cond, timeout_s: float = 180.0) -> None:
    """Tick the sender (as the follower's loop does) until ``cond()``; generous bound."""
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, "condition not met in time"
        sender.tick(time.monotonic(), 0)
        await asyncio.sleep(0.05)


def _shm_names(sender: VideoSender) -> list[str]:
    names = [c.shm.name for c in sender.process.captures.values()]
    return [*names, sender.process.shared.scene.name]


def _leaked(names: list[str]) -> list[str]:
    return [n for n in names if Path(f"/dev/shm/{n.lstrip('/')}").exists()]


async def test_a_killed_video_process_is_restarted_and_frames_flow_again(caplog):
    caplog.set_level(logging.WARNING)
    sender = VideoSender(small_video_config(process=True), None, None, DEFAULT_PATIENT)
    await asyncio.to_thread(sender.open)
    sender.start(asyncio.get_running_loop())
    names = _shm_names(sender)
    us = sender.captures["us"]
    try:
        await _ticking_until(sender, lambda: us.slot.number >= 3)
        old = sender.process.pid
        assert sender.stats()["process"]["state"] == "running"
        os.kill(old, signal.SIGKILL)
        await _ticking_until(sender, lambda: not sender.process.alive)
        sender.tick(time.monotonic(), 0)  # the death noticed
        st = sender.stats()["process"]
        assert st["state"].startswith("down: video process exited with code -9"), st
        assert "video process exited with code -9; restarting it in 1 s" in caplog.text
        await _ticking_until(sender, lambda: sender.restarter.restarts == 1)
        assert sender.process.pid != old and sender.process.alive
        n = us.slot.number
        await _ticking_until(sender, lambda: us.slot.number >= n + 3)  # frames again
        st = sender.stats()["process"]
        assert st["state"] == "running" and st["restarts"] == 1
        assert "video process restarted (1)" in caplog.text
    finally:
        sender.close()
        await sender.settle()
    assert _leaked(names) == []


async def test_a_stop_while_the_new_video_process_starts_neither_hangs_nor_leaks():
    sender = VideoSender(small_video_config(process=True), None, None, DEFAULT_PATIENT)
    await asyncio.to_thread(sender.open)
    sender.start(asyncio.get_running_loop())
    names = _shm_names(sender)
    try:
        old = sender.process.pid
        os.kill(old, signal.SIGKILL)
        # the new process is spawned; stopped before it opened its sources (or just after)
        await _ticking_until(sender, lambda: sender.process.pid not in (None, old))
        assert sender.restarter.restarting
        spawned = sender.process.shared.process
    finally:
        await asyncio.wait_for(asyncio.to_thread(sender.close), 60.0)
        await asyncio.wait_for(sender.settle(), 60.0)
    assert not spawned.is_alive()
    assert not sender.process.alive and sender.stats()["process"]["state"] == "stopped"
    assert _leaked(names) == []


async def test_a_video_process_killed_while_it_first_opens_is_restarted_not_a_config_error():
    """Killed before its sources opened (the follower starting): not the sources' fault, so
    not the follower's exit code 2; the follower starts the video and the restart brings it."""
    sender = VideoSender(small_video_config(process=True), None, None, DEFAULT_PATIENT)
    opening = asyncio.ensure_future(asyncio.to_thread(sender.open))
    try:
        end = time.monotonic() + 120
        while sender.process.pid is None:
            assert time.monotonic() < end
            await asyncio.sleep(0.01)
        os.kill(sender.process.pid, signal.SIGKILL)
        await asyncio.wait_for(opening, 120)  # returns: no VideoSourceUnavailable
        sender.start(asyncio.get_running_loop())
        await _ticking_until(sender, lambda: sender.restarter.restarts == 1)
        n = sender.captures["us"].slot.number
        await _ticking_until(sender, lambda: sender.captures["us"].slot.number >= n + 3)
    finally:
        sender.close()
        await sender.settle()
