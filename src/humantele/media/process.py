"""The follower's video sources in their own process: render (sim) or capture, scale, stamp the
counter and convert to YUV there; the follower's process only wraps the frames for aiortc.

Why: the sim ultrasound and POV cost tens of ms of CPU per frame on these cores (docs/
benchmarks.md). In the follower's process they compete for the GIL with the asyncio loop,
the sensing worker and aiortc, and the pose stream and sensing ran seconds late on a loaded
machine. In a separate process they only compete for CPU, and the process runs at a lower
priority (``[follower.video] process_nice``, its POV thread lower still:
:data:`humantele.runtime.child.PRIORITY`), so when CPU is short the video gives way first
(the POV before the US, also by the degradation policy) while the pose and state streams and
the tracker keep their budget.

The process is a :func:`humantele.runtime.child.spawn` child. One that dies (killed, a
crash) is restarted by the follower (:class:`humantele.media.sender.VideoSender` with a
:class:`~humantele.runtime.child.Restarter`): :meth:`ProcessVideo.restart` starts a new one on
the same shared memory, pipes and latest-frame slots, so the tracks carry on with its frames.

Plumbing (``multiprocessing`` spawn):

- scene, follower -> video process: a :class:`~humantele.haptics.shm.SeqlockArray` of the sim
  world's latest snapshot (the follower writes it each tick; the patient is fixed at start);
- control, follower -> video process: per source, a shared (scale, max_fps) pair;
- frames, video process -> follower: per source, a ring of ``RING`` shared-memory buffers of
  YUV 4:2:0, each with a sequence word written odd before and even after the pixels; a pipe
  message per frame names the buffer, and the follower checks the word after copying (a
  buffer rewritten meanwhile is dropped, counted as ``torn``);
- records (every frame's timestamps, the JPEGs) and errors travel on the same pipe, so the
  follower's recorder writes them.

:class:`ProcessCapture` has the interface of :class:`humantele.media.capture.VideoCapture`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing as mp
import os
import threading
import time
from multiprocessing import shared_memory
from typing import TYPE_CHECKING, Any

import numpy as np

from humantele.geometry import Pose
from humantele.haptics.shm import SeqlockArray
from humantele.media.capture import CapturedFrame, VideoCapture, i420_frame
from humantele.media.slot import LatestSlot
from humantele.runtime.child import (
    POV_EXTRA_NICE,
    Priority,
    set_priority,
    set_thread_nice,
    spawn,
    stop_process,
    watch_parent,
)
from humantele.video.base import SourceCounters, VideoSourceUnavailable

if TYPE_CHECKING:
    from humantele.video.scene import SceneSnapshot

log = logging.getLogger(__name__)

RING = 4
OPEN_TIMEOUT_S = 30.0
# scene layout: t, force_n, then (valid, x, y, z, qx, qy, qz, qw) for tip, head, virtual
SCENE_N = 2 + 3 * 8


def pack_scene(s: SceneSnapshot) -> np.ndarray:
    a = np.zeros(SCENE_N)
    a[0], a[1] = s.t, s.force_n
    for i, pose in enumerate((s.T_world_tip, s.T_world_head, s.T_world_virtual_tip)):
        if pose is not None:
            o = 2 + 8 * i
            a[o] = 1.0
            a[o + 1 : o + 4] = pose.position
            a[o + 4 : o + 8] = pose.quaternion
    return a


def unpack_scene(a: np.ndarray, patient: Any) -> SceneSnapshot | None:
    from humantele.video.scene import SceneSnapshot  # the sim sources' input: sim only

    poses = []
    for i in range(3):
        o = 2 + 8 * i
        if a[o] != 1.0:
            poses.append(None)
            continue
        try:
            poses.append(Pose(a[o + 1 : o + 4].copy(), a[o + 4 : o + 8].copy()))
        except ValueError:
            return None  # a bad pose: the source renders a dark frame and counts it
    return SceneSnapshot(float(a[0]), patient, poses[0], float(a[1]), poses[1], poses[2])


def _frame_bytes(width: int, height: int) -> int:
    return width * height * 3 // 2


# --- the video process ------------------------------------------------------------------------


class VideoProcessDied(VideoSourceUnavailable):
    """The video process ended (killed, crashed) before its sources opened: a restart may
    help, unlike a source that refused to open."""


class StopFlag:
    """The video process's stop signal: one byte of shared memory, set by the follower and
    polled. Not a ``multiprocessing.Event``: its ``set()`` waits for every sleeper to take
    the wake-up, and waits for good when a sleeper was killed (SIGKILL, a signal to the
    process group), which hung the follower at its stop."""

    POLL_S = 0.02

    def __init__(self, ctx: Any) -> None:
        self._flag = ctx.Value("b", 0, lock=False)

    def set(self) -> None:
        self._flag.value = 1

    def clear(self) -> None:
        self._flag.value = 0

    def is_set(self) -> bool:
        return bool(self._flag.value)

    def wait(self, timeout: float | None = None) -> bool:
        """True once set; False when ``timeout`` (s) passed first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._flag.value:
            left = self.POLL_S if deadline is None else deadline - time.monotonic()
            if left <= 0:
                return False
            time.sleep(min(self.POLL_S, left))
        return True


def _child(
    specs: dict[str, dict], patient: Any, scene_name: str, controls: dict, conn: Any, stop: Any,
    nice: int, parent_pid: int,
) -> None:  # fmt: skip
    """The video process (:func:`~humantele.runtime.child.spawn` ignores SIGINT and SIGTERM
    for it: the follower stops it): one capture thread per source until ``stop`` is set or
    the follower ``parent_pid`` is gone (watched from the start: it may die while we open;
    the watch only sets the flag, which never waits on anyone)."""
    watch_parent(parent_pid, stop.set)
    import cv2

    from humantele.video.sources import make_video_source

    set_priority(Priority(nice=nice))
    cv2.setNumThreads(1)
    scene_shm = SeqlockArray(SCENE_N, name=scene_name)
    send_lock = threading.Lock()

    def send(msg: tuple) -> None:
        with send_lock, contextlib.suppress(Exception):
            conn.send(msg)

    def scene() -> SceneSnapshot | None:
        try:
            return unpack_scene(scene_shm.read(), patient)
        except TimeoutError:
            return None

    def record(topic: str, t: float, payload: dict) -> None:
        send(("rec", topic, t, payload))

    caps = []
    for name, spec in specs.items():
        cap = RingCapture(
            name, make_video_source(spec["config"], scene), spec, controls[name], send
        )
        try:
            cap.open()
        except VideoSourceUnavailable as exc:
            send(("open_failed", name, str(exc)))
            return
        send(("opened", name, None))
        caps.append(cap)
    from humantele.runtime.simulator import simulator_modules

    send(("simulator", simulator_modules()))
    for cap in caps:
        cap._stop = stop  # the process's stop event ends the capture loops
        cap.start_thread()
    stop.wait()
    for cap in caps:
        if cap._thread is not None:
            cap._thread.join(timeout=2.0)


class RingCapture(VideoCapture):
    """A capture that publishes into a shared-memory ring and tells the follower (the video
    process's side)."""

    def __init__(self, name: str, source: Any, spec: dict, control: Any, send: Any) -> None:
        super().__init__(
            name, source, stamp_counter=spec["stamp_counter"],
            record=lambda topic, t, p: send(("rec", topic, t, p)),
            record_hz=spec["record_hz"], jpeg_quality=spec["jpeg_quality"],
        )  # fmt: skip
        self.shm = shared_memory.SharedMemory(name=spec["shm"])
        self.slot_bytes = spec["slot_bytes"]
        self.header = np.ndarray((RING,), dtype=np.int64, buffer=self.shm.buf, offset=0)
        self.control = control
        self.send = send
        self.k = 0
        self._last_error = ""

    def start_thread(self) -> None:
        self._thread = threading.Thread(target=self._run_at_priority, name=f"video-{self.name}")
        self._thread.start()

    def _run_at_priority(self) -> None:
        """The POV's thread runs below the US's (it gives way first)."""
        if self.name == "pov":
            set_thread_nice(POV_EXTRA_NICE)
        self._run()

    def _take(self, f: Any) -> None:
        self.scale = float(self.control[0])
        m = float(self.control[1])
        self.max_fps = None if m <= 0 else m
        super()._take(f)
        if self.error and self.error != self._last_error:
            self.send(("error", self.name, self.error))
        self._last_error = self.error

    def emit(self, seq: int, t: float, yuv: np.ndarray, width: int, height: int) -> None:
        if yuv.nbytes > self.slot_bytes:
            self.error = f"frame {width}x{height} larger than its shared buffer"
            self.errors += 1
            return
        k = self.k
        off = 8 * RING + k * self.slot_bytes
        self.header[k] += 1  # odd: writing
        self.shm.buf[off : off + yuv.nbytes] = yuv.reshape(-1).data
        self.header[k] += 1  # even: consistent
        prep = self.prepare_times[-1] if self.prepare_times else 0.0
        invalid = self.source.counters.invalid
        self.send(("frame", self.name, k, int(self.header[k]), seq, t, width, height, prep,
                   invalid, self.captured))  # fmt: skip
        self.k = (k + 1) % RING


# --- the follower's side ----------------------------------------------------------------------


class _Shared:
    """What the captures of one video process share: the process, the pipe, the scene."""

    def __init__(self, ctx: Any) -> None:
        self.ctx = ctx
        self.scene = SeqlockArray(SCENE_N)
        self.stop = StopFlag(ctx)
        self.recv_conn: Any = None  # the current process's pipe (ProcessVideo._launch)
        self.process: Any = None
        self.captures: dict[str, ProcessCapture] = {}
        self.opened: dict[str, str | None] = {}
        self.opened_event = threading.Event()
        self.reader: threading.Thread | None = None
        self.record: Any = None


class ProcessCapture:
    """One source captured in the video process; the interface of ``VideoCapture``."""

    def __init__(self, name: str, shared: _Shared, spec: dict, fps: float) -> None:
        self.name = name
        self.shared = shared
        self.spec = spec
        self.fps = fps
        w, h = spec["size"]
        self.slot_bytes = _frame_bytes(w, h)
        self.shm = shared_memory.SharedMemory(create=True, size=8 * RING + RING * self.slot_bytes)
        spec["shm"], spec["slot_bytes"] = self.shm.name, self.slot_bytes
        self.control = shared.ctx.Array("d", [1.0, 0.0], lock=False)
        self.slot: LatestSlot = LatestSlot()
        self.captured = 0
        self.published = 0
        self.sent = 0
        self.errors = 0
        self.error = ""
        self.torn = 0
        self.rate_skipped = 0
        self.prepare_times: list[float] = []
        self.source = _SourceView(fps)
        self._header = np.ndarray((RING,), dtype=np.int64, buffer=self.shm.buf, offset=0)

    @property
    def scale(self) -> float:
        return float(self.control[0])

    @scale.setter
    def scale(self, value: float) -> None:
        self.control[0] = float(value)

    @property
    def max_fps(self) -> float | None:
        v = float(self.control[1])
        return None if v <= 0 else v

    @max_fps.setter
    def max_fps(self, value: float | None) -> None:
        self.control[1] = 0.0 if value is None else float(value)

    def on_frame(self, msg: tuple) -> None:
        """A frame message from the video process (reader thread): copy it out, check it."""
        _, _, k, hseq, seq, t, w, h, prep, invalid, captured = msg
        n = _frame_bytes(w, h)
        off = 8 * RING + k * self.slot_bytes
        yuv = np.frombuffer(self.shm.buf, np.uint8, count=n, offset=off).copy()
        if int(self._header[k]) != hseq:
            self.torn += 1
            return
        self.captured = captured
        self.source.counters.invalid = invalid
        self.prepare_times.append(prep)
        if len(self.prepare_times) > 500:
            del self.prepare_times[:250]
        self.published += 1
        self.slot.put(CapturedFrame(i420_frame(yuv.reshape(h * 3 // 2, w), t), seq, t, w, h))

    def open(self) -> None:  # the process opens all sources: see ProcessVideo.open
        pass

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.slot.bind(loop)

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            self.shm.close()
            self.shm.unlink()


class _SourceView:
    """What the sender reads of a source it does not hold: nominal fps, counters."""

    def __init__(self, fps: float) -> None:
        self.fps = fps
        self.counters = SourceCounters()


class ProcessVideo:
    """Both sources in one video process; ``captures`` maps 'us'/'pov' to ProcessCapture."""

    def __init__(self, specs: dict[str, dict], patient: Any, record: Any, nice: int) -> None:
        self.shared = _Shared(mp.get_context("spawn"))
        self.shared.record = record
        self.patient = patient
        self.nice = nice
        self.specs = specs
        self.closed = False
        self._lock = threading.Lock()  # a (re)start and the close, one at a time
        self.simulator_modules: list[str] | None = None  # loaded in the video process (opened)
        self._cpu_s: float | None = None
        self.captures = {
            name: ProcessCapture(name, self.shared, spec, spec["fps"])
            for name, spec in specs.items()
        }

    def publish_scene(self, snapshot: SceneSnapshot) -> None:
        if not self.closed:
            self.shared.scene.write(pack_scene(snapshot))

    def open(self) -> None:
        """Start the process and wait until it opened every source (VideoSourceUnavailable
        with the source's message if one could not)."""
        with self._lock:
            if self.closed:
                return
            self._launch()
        try:
            self._wait_opened()
        except VideoProcessDied:
            raise  # not the sources' fault: the follower restarts it (VideoSender)
        except VideoSourceUnavailable:
            self.close()
            raise

    def restart(self) -> None:
        """After the process died: a new one on the same shared memory and slots (blocks
        until it opened its sources; VideoSourceUnavailable if it could not, and then it is
        stopped). Nothing when closed meanwhile."""
        with self._lock:
            if self.closed:
                return
            self._reap()
            self._launch()
        try:
            self._wait_opened()
        except VideoSourceUnavailable:
            with self._lock:
                self._reap()
            raise

    def _launch(self) -> None:
        """Spawn the process and its pipe's reader (with the lock held)."""
        sh = self.shared
        sh.stop.clear()
        sh.opened.clear()
        sh.opened_event.clear()
        recv_conn, send_conn = sh.ctx.Pipe(duplex=False)
        controls = {n: c.control for n, c in self.captures.items()}
        try:
            sh.process = spawn(
                _child,
                (self.specs, self.patient, sh.scene.name, controls, send_conn, sh.stop,
                 self.nice, os.getpid()),
                name="humantele-video", watch=False,
            )  # fmt: skip
        finally:
            send_conn.close()  # the child has its own: its death ends the reader (EOF)
        sh.recv_conn = recv_conn
        sh.reader = threading.Thread(
            target=self._read, args=(recv_conn,), name="humantele-video-rx", daemon=True
        )
        sh.reader.start()

    def _wait_opened(self) -> None:
        sh = self.shared
        if not sh.opened_event.wait(OPEN_TIMEOUT_S):
            raise VideoSourceUnavailable("video process: the sources did not open in time")
        if self.closed:  # closed while opening (the daemon is stopping)
            return
        failed = [m for m in sh.opened.values() if m]
        if failed:
            raise VideoSourceUnavailable(failed[0])
        if len(sh.opened) < len(self.captures):
            code = None if sh.process is None else sh.process.exitcode
            raise VideoProcessDied(f"video process exited with code {code} while opening")

    def _reap(self) -> None:
        """Stop and reap the current process and its reader (with the lock held)."""
        sh = self.shared
        sh.stop.set()
        stop_process(sh.process, timeout_s=2.0, term=False)
        if sh.recv_conn is not None:
            with contextlib.suppress(Exception):
                sh.recv_conn.close()
        if sh.reader is not None and sh.reader is not threading.current_thread():
            sh.reader.join(timeout=2.0)

    def _read(self, conn: Any) -> None:
        sh = self.shared
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            try:
                if kind == "frame":
                    self.captures[msg[1]].on_frame(msg)
                elif kind == "rec":
                    if sh.record is not None:
                        sh.record(msg[1], msg[2], msg[3])
                elif kind == "simulator":
                    self.simulator_modules = msg[1]
                elif kind in ("opened", "open_failed"):
                    sh.opened[msg[1]] = msg[2]
                    if kind == "open_failed" or len(sh.opened) == len(self.captures):
                        sh.opened_event.set()
                elif kind == "error":
                    cap = self.captures[msg[1]]
                    cap.errors += 1
                    if cap.error != msg[2]:
                        log.error("video %s: %s", msg[1], msg[2])
                    cap.error = msg[2]
            except Exception:
                log.exception("video: bad message from the video process")
        if conn is sh.recv_conn:  # the current process ended: an open() waiting returns
            sh.opened_event.set()

    def close(self) -> None:
        if self.closed:
            return
        self.cpu_seconds()  # the last figure, while it runs
        self.closed = True
        sh = self.shared
        sh.opened_event.set()  # an open() or restart() still waiting returns now (sees closed)
        with self._lock:  # a (re)start in progress has spawned its process: it is stopped too
            self._reap()
        for cap in self.captures.values():
            cap.stop()
        with contextlib.suppress(Exception):
            sh.scene.close()
            sh.scene.unlink()

    @property
    def alive(self) -> bool:
        p = self.shared.process
        return p is not None and p.is_alive()

    @property
    def exitcode(self) -> int | None:
        p = self.shared.process
        return None if p is None else p.exitcode

    @property
    def pid(self) -> int | None:
        p = self.shared.process
        return None if p is None else p.pid

    def cpu_seconds(self) -> float | None:
        from humantele.runtime.stats import process_cpu_seconds

        p = self.shared.process
        if p is not None and p.is_alive():
            self._cpu_s = process_cpu_seconds(p.pid) or self._cpu_s
        return self._cpu_s
