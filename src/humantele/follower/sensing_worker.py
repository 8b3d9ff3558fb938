"""Where the follower's tracker frames are measured while the daemon runs, off its loop.

:class:`SensingWorker` is the daemon's one handle: ``submit(frame)`` at the tracker's rate,
the measurement comes back on the loop through ``on_measured(frame, measurement)``. By
default a child process measures (:mod:`humantele.follower.sensing_process`: its own GIL, so
the pose path is never held up); ``sensing_worker = "thread"`` (or a child that failed for
good) measures on a worker thread; before :meth:`start`, frames are measured in line. Frames
are measured in order and never overlap: a frame due while the previous one is measured is
skipped (``skipped``), and so are those due while the child starts (``starting``). With real
devices (no simulated world to show them) a tick skipped while busy is not a frame lost: the
device keeps its frames, and the next measurement starts as soon as the last one is back
(``caught_up``), so the sensing reads the newest frame without waiting for the next tick
(frames the device replaced meanwhile are counted by the camera: hl2ss's ``stale``). A
sensing process that gives no answer for ``HUNG_S`` is killed and restarted.

A sensing process that dies is restarted, and its replacement takes 10-15 s on a loaded
machine to import and build its sensing: no measurement meanwhile (no state to the expert,
the tracker's pose stale). :class:`MeasurementGaps` counts such gaps (issue 20 §2), shown in
the stats and the demo's ``--json``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from humantele.follower.sensing import Measurement, Sensing, SensingConfig, TrackerImage
from humantele.follower.sensing_process import SensingProcess
from humantele.runtime.stats import SortedWindow, percentile_ms

log = logging.getLogger(__name__)

OnMeasured = Callable[[TrackerImage, Measurement], None]

GAP_S = 0.5  # s without a measurement that counts as a gap (22 frames at 45 Hz)
UNMEASURED_WINDOW_S = 5.0  # the reasons frames went unmeasured are judged over this (s)


def unmeasured_frames(devices: dict | None, skipped: int) -> dict[str, int]:
    """Tracker frames not measured, by reason, from the sensing devices' counters
    (:meth:`~humantele.follower.sensing.ProbeSensing.device_stats`): ``no_pose`` (a frame
    without the camera's pose: hl2ss's rig pose missing, by reason in the camera's
    ``no_pose``), ``no_frame`` (a read gave none: timeouts, a stalled or lost stream),
    ``stale`` (frames the camera replaced by a newer one before they were read: the reader
    was behind), ``skipped`` (the daemon's ticks skipped while the sensing was busy) and
    ``stalls`` (stalled streams dropped and reconnected); ``measured``: frames the tracker
    measured."""
    d = devices or {}
    cam = d.get("camera") or {}
    return {
        "measured": int(d.get("frames", 0)),
        "no_pose": int(d.get("no_camera_pose", 0)),
        "no_frame": int(d.get("no_frame", 0)),
        "stale": int((cam.get("dropped") or {}).get("stale", 0)),
        "skipped": int(skipped),
        "stalls": int(cam.get("stalls", 0)),
    }


class UnmeasuredWindow:
    """The reason most tracker frames went unmeasured over the last ``UNMEASURED_WINDOW_S``
    (None: most were measured, or too few frames to say): ``update(now, counts)`` with the
    running totals of :func:`unmeasured_frames`."""

    REASONS = ("no_pose", "no_frame", "stale", "skipped")

    def __init__(self) -> None:
        self.history: list[tuple[float, dict[str, int]]] = []
        self.dominant: str | None = None
        self.share = 0.0

    def update(self, now: float, counts: dict[str, int]) -> str | None:
        self.history.append((now, dict(counts)))
        while len(self.history) > 2 and now - self.history[1][0] >= UNMEASURED_WINDOW_S:
            self.history.pop(0)
        old = self.history[0][1]
        delta = {k: max(0, counts.get(k, 0) - old.get(k, 0)) for k in (*self.REASONS, "measured")}
        total = sum(delta.values())
        reason = max(self.REASONS, key=lambda k: delta[k])
        if total >= 10 and delta[reason] > delta["measured"]:
            self.dominant, self.share = reason, delta[reason] / total
        else:
            self.dominant, self.share = None, 0.0
        return self.dominant


UNMEASURED_WORDS = {"no_pose": "no camera pose (the headset not located)",
                    "no_frame": "no frame from the camera", "stale": "frames replaced before "
                    "read (the sensing behind)", "skipped": "skipped under load"}  # fmt: skip


class MeasurementGaps:
    """Time without measurements after the first one (s, the daemon's clock): gaps longer
    than ``GAP_S`` counted and summed, the one going on included."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.last_t: float | None = None
        self.count = 0
        self.total_s = 0.0
        self.max_s = 0.0

    def measured(self, t: float) -> None:
        if self.last_t is not None and t - self.last_t > GAP_S:
            gap = t - self.last_t
            self.count += 1
            self.total_s += gap
            self.max_s = max(self.max_s, gap)
        self.last_t = t if self.last_t is None else max(t, self.last_t)

    def stats(self) -> dict[str, Any]:
        now = self.clock()
        ongoing = 0.0 if self.last_t is None else max(0.0, now - self.last_t)
        ongoing = ongoing if ongoing > GAP_S else 0.0
        return {
            "measurement_age_s": None if self.last_t is None else round(now - self.last_t, 3),
            "measurement_gaps": self.count + (ongoing > 0.0),
            "measurement_gap_s": round(self.total_s + ongoing, 3),
            "measurement_gap_max_s": round(max(self.max_s, ongoing), 3),
        }


class SensingWorker:
    """The follower's sensing off its loop. ``config``: the follower's; ``on_failed(reason)``
    once if the child cannot build its sensing (a bad config: the daemon stops)."""

    def __init__(
        self,
        config: Any,
        sensing_config: SensingConfig | None,
        on_measured: OnMeasured,
        on_failed: Callable[[str], None],
        target: Callable[..., None] | None = None,
    ) -> None:
        """``target``: the sensing child's main (default the follower's; a bench gives its
        own, on its own devices)."""
        self.target = target
        self.config = config
        self.on_measured = on_measured
        self.on_failed = on_failed
        # with a sensing process, the in-process copy is built only if ever used
        self.sensing = Sensing(config, sensing_config, build=config.sensing_worker == "thread")
        self.proc: SensingProcess | None = None
        self.executor: ThreadPoolExecutor | None = None
        self._pending: Future | None = None  # the thread's frame in flight
        self._proc_frame: tuple[int, TrackerImage] | None = None  # (job, frame) in the child
        self._jobs = 0
        self.skipped = 0
        self.errors = 0  # the worker thread's own failures (the sensing's are in sensing.errors)
        self.starting = 0  # frames due before the sensing process was ready
        self.caught_up = 0  # measurements started at once after the last (real devices)
        self.skipped_frames = 0  # the sim world's frames skipped (its devices never saw them)
        self._due: TrackerImage | None = None  # a real device's tick skipped while busy
        self.failure: str | None = None
        self.times = SortedWindow(2000)  # s per measurement (thread or child)
        self.gaps = MeasurementGaps()
        self.unmeasured = UnmeasuredWindow()
        self.closed = False

    def start(self) -> None:
        """Start the worker thread and, by default, the sensing process (it starts while the
        link connects)."""
        self.executor = ThreadPoolExecutor(1, thread_name_prefix="humantele-sensing")
        if self.config.sensing_worker == "process" and self.sensing.unbuilt:
            self.proc = SensingProcess(self.config, self.sensing.sensing_config,
                                       self._measured_in_process, self._cannot_start,
                                       priority=self.config.sensing_priority,
                                       target=self.target)  # fmt: skip
            self.proc.start()

    def measuring(self) -> bool:
        """False while the sensing process starts (its frames are skipped)."""
        proc = self.proc
        return proc is None or not proc.running or proc.ready

    def submit(self, frame: TrackerImage) -> None:
        """Measure one tracker frame (the result comes through ``on_measured``)."""
        proc = self.proc
        if proc is not None and proc.running:
            if not proc.ready:  # still starting (importing, calibrating the sim force board)
                self.starting += 1
            elif proc.busy and not proc.check_hung():
                self.skipped += 1
                if frame.world is None:  # real devices: measure again as soon as it is back
                    self._due = frame
                else:  # the sim's world at this frame is never shown to its devices
                    self.skipped_frames += 1
            elif proc.busy:  # hung: killed, restarting
                self.skipped += 1
            else:
                self._jobs += 1
                if proc.submit(self._jobs, (frame.t, frame.world)):
                    self._proc_frame = (self._jobs, frame)
                else:
                    self.skipped += 1
            return
        if self.executor is None:
            self.gaps.measured(frame.t)
            self.on_measured(frame, self.sensing.measure(frame.t, frame.world))
            return
        if self._pending is not None:
            self.skipped += 1
            self.skipped_frames += frame.world is not None
            return
        fut = asyncio.get_running_loop().run_in_executor(self.executor, self._measure, frame)
        self._pending = fut
        fut.add_done_callback(lambda f: self._measured(frame, f))

    def _measured_in_process(self, job: int, m: Measurement, seconds: float) -> None:
        pending, self._proc_frame = self._proc_frame, None
        self.times.append(seconds)
        if pending is not None and pending[0] == job:  # else: a child since replaced
            self.gaps.measured(pending[1].t)
            self.on_measured(pending[1], m)
        due, self._due = self._due, None
        proc = self.proc
        if due is not None and proc is not None and proc.ready and not proc.busy:
            self.caught_up += 1
            self._jobs += 1
            frame = TrackerImage(time.monotonic(), None, due.virtual, due.target)
            if proc.submit(self._jobs, (frame.t, None)):
                self._proc_frame = (self._jobs, frame)

    def _cannot_start(self, reason: str) -> None:
        self.failure = reason
        self.on_failed(reason)

    def _measure(self, frame: TrackerImage) -> Measurement:
        """On the worker thread: measure, and time it."""
        t0 = time.perf_counter()
        m = self.sensing.measure(frame.t, frame.world)
        self.times.append(time.perf_counter() - t0)
        return m

    def _measured(self, frame: TrackerImage, fut: Future) -> None:
        self._pending = None
        if fut.cancelled():
            return
        exc = fut.exception()
        if exc is not None:  # Sensing.measure catches the pipeline's; this is the worker's
            self.errors += 1
            if self.errors in (1, 10, 100, 1000):
                log.error("follower: sensing worker failed (%d so far): %r", self.errors, exc)
            return
        self.gaps.measured(frame.t)
        self.on_measured(frame, fut.result())

    def device_stats(self) -> dict | None:
        """The sensing devices' counters: the child's latest, or the in-process sensing's."""
        proc = self.proc
        if proc is not None and proc.running:
            return proc.device_stats
        return None if self.sensing.unbuilt else self.sensing.device_stats()

    def device_summary(self) -> dict[str, Any]:
        """Whether the headset's stream is stalled and the force stale now, and the tracker
        frames not measured, by reason (:func:`unmeasured_frames`) and the one that
        dominates lately (``unmeasured_dominant``, its share ``unmeasured_share``)."""
        dev = self.device_stats()
        counts = unmeasured_frames(dev, self.skipped_frames)
        previous = self.unmeasured.dominant
        dominant = self.unmeasured.update(time.monotonic(), counts)
        if dominant is not None and dominant != previous:
            log.warning("follower: most tracker frames are not measured lately: %s (%.0f %%)",
                        UNMEASURED_WORDS[dominant], 100 * self.unmeasured.share)  # fmt: skip
        force = (dev or {}).get("force") or {}
        return {
            "headset_stream_stalled": bool(((dev or {}).get("camera") or {}).get("stalled")),
            "force_stale": bool(force.get("stale")) if force else None,
            "unmeasured": counts,
            "unmeasured_dominant": dominant,
            "unmeasured_share": round(self.unmeasured.share, 3),
            "sensing_devices": dev,
        }

    def stats(self) -> dict[str, Any]:
        proc = self.proc
        running = proc is not None and proc.running
        return {
            **self.device_summary(),
            "sensing_errors": self.sensing.errors
            + self.errors
            + (0 if proc is None else proc.child_errors),
            "sensing_skipped": self.skipped,
            "sensing_starting": self.starting,
            "sensing_worker": "process" if running else "thread",
            "sensing_ready": self.measuring(),  # False while the sensing process starts
            "sensing_restarts": 0 if proc is None else proc.restarts,
            "sensing_hangs": 0 if proc is None else proc.hangs,
            "sensing_caught_up": self.caught_up,
            "sensing_p50_ms": percentile_ms(self.times, 50),
            "sensing_p99_ms": percentile_ms(self.times, 99),
            "cpu_percent_sensing": None if proc is None else proc.cpu_percent(),
            "sensing_state": self.state(),
            **self.gaps.stats(),
        }

    def state(self) -> str:
        """``thread``, ``starting``, ``restarting (N)``, ``running``, ``failed: <why>`` or
        ``stopped`` (closed)."""
        proc = self.proc
        if self.closed:
            return "stopped"
        if proc is None:
            return "thread"
        if proc.failed:
            return f"failed: {proc.error or 'exited too often; measuring in a thread'}"
        if not proc.ready:  # the replacement under way counts from the death (its back-off)
            n = proc.restarts + (1 if proc.restarter.down else 0)
            return f"restarting ({n})" if n else "starting"
        return "running"

    def close(self) -> None:
        """Stop the thread (the frame being measured ends first) and the child."""
        self.closed = True
        if self.executor is not None:
            self.executor.shutdown(wait=True)
            self.executor = None
        if self.proc is not None:
            self.proc.close()
        self.sensing.close()
