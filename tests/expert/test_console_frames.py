"""The console's frame providers started and stopped as pages open and close, fast and from
several threads (issue 20 item 5: ``AttributeError ... is_alive`` in ``frames.stop``): no
exception, and the last request wins."""

from __future__ import annotations

import os
import random
import threading
import time

import numpy as np
import pytest

from humantele.expert.console.frames import ProcessFrames, SourceFrames
from humantele.runtime.child import PRIORITY, child_priority
from humantele.video.base import VideoFrame, VideoSource
from humantele.video.scene import DemoScene
from humantele.video.sim_ultrasound import SimUltrasoundConfig


class CountingSource(VideoSource):
    def __init__(self) -> None:
        super().__init__()
        self.opens = self.closes = self.seq = 0
        self.lock = threading.Lock()

    def open(self) -> None:
        with self.lock:
            self.opens += 1

    def read(self) -> VideoFrame | None:
        time.sleep(0.002)
        self.seq += 1
        return VideoFrame(np.zeros((4, 4, 3), np.uint8), self.seq, time.monotonic())

    def close(self) -> None:
        with self.lock:
            self.closes += 1

    @property
    def size(self) -> tuple[int, int]:
        return (4, 4)

    @property
    def fps(self) -> float:
        return 500.0


def hammer(frames, rounds: int, seed: int) -> list[BaseException]:
    """Pages opening (start, on 'the loop': this thread) and closing (stop, in a worker
    thread each, as the server does) in random order; the exceptions the threads raised."""
    rng = random.Random(seed)
    errors: list[BaseException] = []

    def stop() -> None:
        try:
            frames.stop()
        except BaseException as exc:  # noqa: BLE001 - what the test is looking for
            errors.append(exc)

    workers = []
    for _ in range(rounds):
        if rng.random() < 0.5:
            frames.start()
        else:
            workers.append(threading.Thread(target=stop))
            workers[-1].start()
        time.sleep(rng.random() * 0.01)
    for w in workers:
        w.join(60)
    return errors


def test_source_frames_survive_pages_opening_and_closing_fast():
    sources = {"us": CountingSource(), "pov": CountingSource()}
    frames = SourceFrames(sources)
    for seed in range(5):
        assert hammer(frames, 60, seed) == []
        frames.start()  # a page is open: frames come
        n = sources["us"].seq
        t_end = time.monotonic() + 30
        while sources["us"].seq <= n + 3:
            assert time.monotonic() < t_end, "no frames after the last start"
            time.sleep(0.01)
        frames.stop()  # the last page closed: the threads end and every open is closed
        assert not frames._threads  # noqa: SLF001
        for s in sources.values():
            assert s.opens == s.closes
    assert all(s.opens > 5 for s in sources.values())


@pytest.mark.slow
def test_process_frames_stop_from_two_threads_and_a_start_between():
    frames = ProcessFrames({"us": SimUltrasoundConfig(width=160, height=120, fps=10)}, DemoScene())
    try:
        frames.start()  # the shared child helper's: named, at the US video's nice, rendering
        pid, base = frames._proc.pid, os.getpriority(os.PRIO_PROCESS, 0)  # noqa: SLF001
        want = ("other", base + PRIORITY["video_us"].nice)
        deadline = time.monotonic() + 120
        while (frames.latest("us") is None or child_priority(pid) != want) and (
            time.monotonic() < deadline
        ):
            time.sleep(0.05)
        assert child_priority(pid) == want and frames.latest("us") is not None
        assert open(f"/proc/{pid}/comm").read().strip() == "humantele-csim"
        for _ in range(3):
            frames.start()
            proc = frames._proc  # noqa: SLF001
            errors: list[BaseException] = []

            def stop(errors: list = errors) -> None:
                try:
                    frames.stop()
                except BaseException as exc:  # noqa: BLE001
                    errors.append(exc)

            two = [threading.Thread(target=stop) for _ in range(2)]
            for t in two:
                t.start()
            for t in two:
                t.join(60)
            assert errors == [], errors
            assert frames._proc is None and not proc.is_alive()  # noqa: SLF001
        # A start while a stop is under way (the stop holds the switch) is done after it.
        frames.start()
        stopping = threading.Thread(target=frames.stop)
        stopping.start()
        while not frames._switch.locked() and stopping.is_alive():  # noqa: SLF001
            time.sleep(0.001)
        frames.start()  # a page opened: never blocks the loop
        stopping.join(60)
        assert frames._proc is not None and frames._proc.is_alive()  # noqa: SLF001
    finally:
        frames.stop()
    assert frames._proc is None  # noqa: SLF001
