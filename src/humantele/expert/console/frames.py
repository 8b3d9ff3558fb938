"""Where the console gets its pictures: the latest frame of each track, on the expert's clock.

The console asks a :class:`FrameProvider` for ``latest("us")`` and ``latest("pov")``: the
newest decoded :class:`~humantele.video.base.VideoFrame` of that track (``seq`` increasing,
``t_capture`` the capture time mapped onto this process's ``time.monotonic()``), or None when
there is none yet. It never blocks: the receiver (or a reader thread) keeps the latest frame.

The console does no work per frame unless a page is open: it then ``subscribe`` s to each
track (``fn(frame, encoded)`` for each new frame, from the provider's thread or the loop;
``encoded`` the encoded frame the picture was decoded from, or None) and ``unsubscribe`` s
when the last page closes. Providers count the frames they handed on (``notified``).

:class:`SourceFrames` is a provider over local :class:`~humantele.video.base.VideoSource` s,
one reader thread each (the sim sources in tests); :class:`ProcessFrames` renders sim sources in
a child process (the daemon's stand-in for the follower's tracks: in-process, their numpy work
held the GIL enough to halve the daemon's pose rate on 2 cores); the expert daemon's WebRTC
receiver is the real provider.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import queue
import threading
from collections.abc import Mapping
from typing import Any, Protocol

from humantele.runtime.child import PRIORITY, set_priority, spawn, stop_process
from humantele.video.base import VideoFrame, VideoSource, VideoSourceError

log = logging.getLogger(__name__)

TRACKS = ("us", "pov")


class FrameProvider(Protocol):
    """The latest frame of a track (``"us"`` or ``"pov"``), or None; never blocks; and the
    new frames as they come to a subscriber (see the module doc)."""

    def latest(self, track: str) -> VideoFrame | None: ...

    def subscribe(self, track: str, fn: Any) -> None: ...

    def unsubscribe(self, track: str, fn: Any) -> None: ...


class _Subscribers:
    """Who gets each new frame of a track: ``fn(frame, None)`` (local sources have no
    encoded frame), called from the source's thread."""

    def __init__(self) -> None:
        self.subscribers: dict[str, list[Any]] = {t: [] for t in TRACKS}
        self.notified = 0

    def subscribe(self, track: str, fn: Any) -> None:
        if fn not in self.subscribers[track]:
            self.subscribers[track] = [*self.subscribers[track], fn]

    def unsubscribe(self, track: str, fn: Any) -> None:
        self.subscribers[track] = [f for f in self.subscribers[track] if f is not fn]

    def _notify(self, track: str, frame: Any) -> None:
        for fn in self.subscribers.get(track, ()):
            self.notified += 1
            try:
                fn(frame, None)
            except Exception:
                log.exception("console: a %s frame subscriber failed", track)


class _OnDemand:
    """``start``/``stop`` from any thread, in any order and overlap (the console starts its
    sources when a page opens, on the event loop, and stops them in a worker thread when the
    last one closes; pages may open and close faster than a stop takes): one switch at a time,
    and whoever holds the switch applies the last request when it is done. :meth:`start`
    never blocks (it is called on the event loop); :meth:`stop` waits for its switch."""

    def __init__(self) -> None:
        self._switch = threading.Lock()
        self._want = False

    def start(self) -> None:
        """Run (nothing if running; done by a stop in progress when that stop ends)."""
        self._want = True
        self._apply(block=False)

    def stop(self, timeout: float = 3.0) -> None:
        """Stop (nothing if stopped), waiting up to ``timeout`` s for each thread or child."""
        self._want = False
        self._apply(block=True, timeout=timeout)

    def _apply(self, block: bool, timeout: float = 3.0) -> None:
        while True:
            if not self._switch.acquire(blocking=block):
                return  # the holder applies self._want once it is done
            try:
                want = self._want
                if want and not self._running():
                    self._start_locked()
                elif not want and self._running():
                    self._stop_locked(timeout)
            finally:
                self._switch.release()
            if self._want == want:  # read after the release: a request that found the
                return  # switch taken set _want before trying it, so one of us sees it
            block = False

    def _running(self) -> bool:
        raise NotImplementedError

    def _start_locked(self) -> None:
        raise NotImplementedError

    def _stop_locked(self, timeout: float) -> None:
        raise NotImplementedError


class SourceFrames(_OnDemand, _Subscribers):
    """A :class:`FrameProvider` reading local video sources, one daemon thread per track.

    ``sources``: track name -> source (not yet opened). :meth:`start` opens them in their
    threads; :meth:`stop` ends the threads and closes the sources (see :class:`_OnDemand`). A
    source that fails is logged once and its track gives no new frames (``errors`` says
    why)."""

    def __init__(self, sources: Mapping[str, VideoSource]) -> None:
        _OnDemand.__init__(self)
        _Subscribers.__init__(self)
        self.sources = dict(sources)
        self.errors: dict[str, str] = {}
        self._latest: dict[str, VideoFrame] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def latest(self, track: str) -> VideoFrame | None:
        with self._lock:
            return self._latest.get(track)

    def _running(self) -> bool:
        return bool(self._threads)

    def _start_locked(self) -> None:
        """Open the sources and read them."""
        self._stop = threading.Event()  # a thread still ending keeps the event it was given
        for track, source in self.sources.items():
            t = threading.Thread(
                target=self._read,
                args=(track, source, self._stop),
                name=f"console-{track}",
                daemon=True,
            )
            t.start()
            self._threads.append(t)

    def _stop_locked(self, timeout: float) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout)
        self._threads = []

    def _read(self, track: str, source: VideoSource, stop: threading.Event) -> None:
        try:
            source.open()
            while not stop.is_set():
                frame = source.read()
                if frame is not None:
                    with self._lock:
                        self._latest[track] = frame
                    self._notify(track, frame)
        except VideoSourceError as exc:
            self.errors[track] = str(exc)
            log.error("console: %s source stopped: %s", track, exc)
        finally:
            source.close()


class ProcessFrames(_OnDemand, _Subscribers):
    """A :class:`FrameProvider` rendering sim sources in a child process (``spawn``), so their
    Python work never competes with the daemon's event loop for the GIL.

    ``configs``: track -> sim source configuration; ``scene``: the daemon-side callable whose
    snapshots the child renders (sent ``scene_hz`` times a second, latest wins). Frames come
    back whole (BGR arrays) with their number and capture time: ``time.monotonic()`` is one
    clock for every process of a Linux machine. :meth:`start`/:meth:`stop` as
    :class:`SourceFrames` (:class:`_OnDemand`)."""

    def __init__(self, configs: Mapping[str, Any], scene: Any, scene_hz: float = 30.0) -> None:
        _OnDemand.__init__(self)
        _Subscribers.__init__(self)
        self.configs = dict(configs)
        self.scene = scene
        self.scene_hz = scene_hz
        self.errors: dict[str, str] = {}
        self._latest: dict[str, VideoFrame] = {}
        self._lock = threading.Lock()
        self._proc: Any = None
        self._stop: Any = None
        self._threads: list[threading.Thread] = []

    def latest(self, track: str) -> VideoFrame | None:
        with self._lock:
            return self._latest.get(track)

    def _running(self) -> bool:
        return self._proc is not None

    def _start_locked(self) -> None:
        ctx = mp.get_context("spawn")
        stop, scene_q, out_q = ctx.Event(), ctx.Queue(maxsize=2), ctx.Queue(maxsize=4)
        proc = spawn(_render_child, (self.configs, scene_q, out_q, stop), name="humantele-csim")
        self._stop, self._scene_q, self._out_q, self._proc = stop, scene_q, out_q, proc
        self._threads = [
            threading.Thread(target=self._feed, args=(stop, scene_q), name="console-scene",
                             daemon=True),
            threading.Thread(target=self._collect, args=(stop, out_q), name="console-frames",
                             daemon=True),
        ]  # fmt: skip
        for t in self._threads:
            t.start()

    def _stop_locked(self, timeout: float) -> None:
        proc, threads = self._proc, self._threads
        self._stop.set()
        for t in threads:
            t.join(timeout)
        stop_process(proc, timeout_s=timeout, term=False)  # (it ignores SIGTERM)
        for q in (self._scene_q, self._out_q):
            q.cancel_join_thread()
            q.close()
        self._proc = None
        self._threads = []

    def _feed(self, stop: Any, scene_q: Any) -> None:
        period = 1.0 / self.scene_hz
        while not stop.wait(period):
            try:
                snap = self.scene()
            except Exception:  # noqa: BLE001 - counted by the child as a dark frame
                snap = None
            with contextlib.suppress(queue.Full, ValueError, OSError):  # (closed at a stop)
                scene_q.put_nowait(snap)

    def _collect(self, stop: Any, out_q: Any) -> None:
        while not stop.is_set():
            try:
                item = out_q.get(timeout=0.2)
            except queue.Empty:
                continue
            except (EOFError, OSError, ValueError):  # (closed at a stop)
                return
            track, image, seq, t, spacing, depth0, error = item
            if error:
                self.errors[track] = error
                log.error("console: %s sim source stopped: %s", track, error)
                continue
            frame = VideoFrame(image, seq, t, spacing, {}, depth0)
            with self._lock:
                self._latest[track] = frame
            self._notify(track, frame)


def _render_child(configs: Mapping[str, Any], scene_q: Any, out_q: Any, stop: Any) -> None:
    """The child process (ended with its daemon: ``spawn`` watches the parent): one thread
    per track renders the latest scene and sends frames, at the US video's priority."""
    from humantele.video.sources import make_video_source

    set_priority(PRIORITY["video_us"])
    latest: list[Any] = [None]
    lock = threading.Lock()

    def scene() -> Any:
        with lock:
            while True:
                try:
                    latest[0] = scene_q.get_nowait()
                except queue.Empty:
                    return latest[0]

    def run(track: str, config: Any) -> None:
        source = make_video_source(config, scene)
        try:
            source.open()
            while not stop.is_set():
                f = source.read()
                if f is None:
                    continue
                item = (track, f.image, f.seq, f.t_capture, f.pixel_spacing_mm,
                        f.depth_origin_row, "")  # fmt: skip
                with contextlib.suppress(queue.Full):
                    out_q.put(item, True, 0.5)
        except VideoSourceError as exc:
            out_q.put((track, None, 0, 0.0, None, None, str(exc)))
        finally:
            source.close()

    threads = [threading.Thread(target=run, args=kv, daemon=True) for kv in configs.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


class _Received:
    """A received frame as the console reads it (``image`` converted when first read, in the
    console's encoding thread)."""

    __slots__ = ("_frame", "seq", "t_capture", "t_received", "pixel_spacing_mm", "depth_origin_row")

    def __init__(
        self, frame: Any, seq: int, spacing: tuple[float, float] | None, depth0: float | None
    ) -> None:
        self._frame = frame
        self.seq = seq
        # Capture time mapped onto the expert's clock; the decode time when it is unknown.
        self.t_capture = frame.t_capture if frame.t_capture is not None else frame.t_received
        self.t_received = frame.t_received  # decoded by the expert's receiver (its clock)
        self.pixel_spacing_mm = spacing
        self.depth_origin_row = depth0

    @property
    def image(self) -> Any:
        return self._frame.image()

    @property
    def av_frame(self) -> Any:
        """The decoded frame (``av.VideoFrame``, yuv420p): its planes, for a JPEG."""
        return self._frame.frame

    @property
    def width(self) -> int:
        return self._frame.width

    @property
    def height(self) -> int:
        return self._frame.height


class ReceivedFrames:
    """A :class:`FrameProvider` over the expert's WebRTC receiver
    (:class:`humantele.media.receiver.VideoReceiver`): its latest decoded frame of each track,
    numbered by the frame counter the follower stamped (a frame whose counter did not read
    gets the next number), with ``us_spacing_mm`` (row, col; mm per pixel of the frames as
    received, from ``[expert.console] us_pixel_spacing_mm``) and ``us_depth_origin_row``
    (``[expert.console] us_depth_origin_row``) on the ultrasound frames."""

    def __init__(
        self,
        receiver: Any,
        us_spacing_mm: tuple[float, float] | None,
        us_depth_origin_row: float | None = None,
    ) -> None:
        self.receiver = receiver
        self.us_spacing_mm = us_spacing_mm
        self.us_depth_origin_row = us_depth_origin_row
        self._last: dict[str, tuple[Any, _Received]] = {}
        self._listeners: dict[tuple[str, Any], Any] = {}
        self.notified = 0

    def subscribe(self, track: str, fn: Any) -> None:
        """``fn(frame, encoded)`` on the loop for each decoded frame of ``track`` (those the
        receiver skipped for a newer one too: a page decoding the encoded frames shows them)."""
        if (track, fn) in self._listeners:
            return

        def listener(f: Any, encoded: Any) -> None:
            self.notified += 1
            fn(self._wrap(track, f), encoded)

        self._listeners[(track, fn)] = listener
        self.receiver.listen(track, listener)

    def unsubscribe(self, track: str, fn: Any) -> None:
        listener = self._listeners.pop((track, fn), None)
        if listener is not None:
            self.receiver.unlisten(track, listener)

    def request_keyframe(self, track: str) -> bool:
        """Ask the follower for a keyframe of ``track`` (a page's decoder starts on one)."""
        return bool(self.receiver.request_keyframe(track))

    def latest(self, track: str) -> _Received | None:
        f = self.receiver.latest(track)
        if f is None:
            return None
        return self._wrap(track, f)

    def _wrap(self, track: str, f: Any) -> _Received:
        last = self._last.get(track)
        if last is not None and last[0] is f:
            return last[1]
        seq = f.seq if f.seq is not None else (0 if last is None else last[1].seq + 1)
        us = track == "us"
        out = _Received(
            f, seq, self.us_spacing_mm if us else None, self.us_depth_origin_row if us else None
        )
        self._last[track] = (f, out)
        return out
