"""The follower daemon (the clinic side); its command line is :mod:`humantele.follower.cli`.

Every tick (``rate_hz``, asyncio) it:

1. shows the clinic the guide (:mod:`humantele.follower.clinic`: the virtual probe and
   whether it is live, the landmark asked for while calibrating); the real novice sees it on
   the headset page, the simulated clinic's novice moves the probe;
2. at the tracker's rate (``sensing_rate_hz``) has a tracker frame and a force reading
   measured off the loop (:mod:`humantele.follower.sensing_worker`; the devices are the
   clinic's, :mod:`humantele.follower.sensing`);
3. with each measurement: feeds the calibration while calibrating, streams the probe pose
   and force to the expert (``state``, patient frame; :mod:`humantele.follower.to_expert`)
   and records them (:mod:`humantele.follower.records`);
4. publishes the measured probe and the virtual probe to renderers (world frame,
   :mod:`humantele.follower.virtual_probe`): a fresh virtual probe as its pose arrives, a
   stale one (no fresh pose, link down) at each tick;
5. once a second lets the video's degradation policy lower the POV (never the US).

Frames: the tracker's world (y up) here; the patient frame of the calibration on the wire
(``T_world_patient`` from the saved calibration). Poses are of the transducer's tip frame
(origin at the centre of the face, +z along the beam). The calibration is saved under
``state_dir`` and reused after a restart; every Hello from the expert gets the model.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from humantele.cliargs import EXIT_FAILED
from humantele.daemons.common import Daemon
from humantele.follower.calibration import Calibration
from humantele.follower.calibration_session import CalibrationSession
from humantele.follower.clinic import Guide, simulator_modules
from humantele.follower.clinics import make_clinic
from humantele.follower.config import FollowerConfig
from humantele.follower.device_watch import DeviceWatch
from humantele.follower.feed import RendererFeed, model_fields
from humantele.follower.figures import AlignmentFigures, TickFigures
from humantele.follower.records import measurement_samples
from humantele.follower.registration import HeadsetRegistration
from humantele.follower.sensing import LOST, Measurement, SensingConfig, TrackerImage
from humantele.follower.sensing_worker import SensingWorker
from humantele.follower.to_expert import ExpertStream
from humantele.follower.virtual_probe import VirtualProbe
from humantele.interop.sessions import FollowerIgtl
from humantele.media.sender import VideoSender
from humantele.transport import PeerLink
from humantele.video.base import VideoSourceUnavailable
from humantele.wire import CalibrationProgress, ControlMessage, Hello, PoseMessage, Scan

log = logging.getLogger(__name__)


class FollowerDaemon(Daemon):
    """The follower's state and its message handlers; :meth:`run` is the daemon."""

    role = "follower"

    def __init__(
        self,
        config: FollowerConfig,
        stats_file: str | None = None,
        sensing_config: SensingConfig | None = None,
    ) -> None:
        super().__init__(config, stats_file)
        self.state_dir = Path(config.state_dir).expanduser()
        self.feed = RendererFeed(config.feed, self.state_dir)
        self.cal = CalibrationSession(config.calibration, self.state_dir, self.send_control,
                                      self.feed.publish, self.record, self.on_fitted)  # fmt: skip
        self.worker = SensingWorker(config, sensing_config, self._measured, self._sensing_failed)
        self.sensing = self.worker.sensing
        self.measurement = LOST
        self.last_measure_t = -math.inf
        self.measurements = 0
        self.registration = HeadsetRegistration.attach(config, self.feed)
        # The clinic (its devices; the sim's world and the scene its video sources render),
        # then the us and pov tracks (humantele.media.sender).
        self.clinic = make_clinic(config.clinic)
        self.video = (
            VideoSender(
                config.video,
                self.clinic.scene,
                self.record_any,
                getattr(self.clinic, "patient", None),
            )  # fmt: skip
            if config.video.enabled
            else None
        )
        if self.video is not None and hasattr(self.clinic, "on_scene"):
            self.clinic.on_scene = self.video.publish_scene
        self.video_error = ""
        us = (self.video.captures["us"].slot, config.video.us) if self.video else None
        sim_us = None if config.video.enabled else getattr(self.clinic, "scene", None)
        self.igtl = FollowerIgtl(config.igtl, sim_us, us)
        self.virtual = VirtualProbe(
            config.stale_after_s, self.feed, lambda: self.link, lambda: self.calibration
        )
        self.to_expert = ExpertStream(lambda: self.link, lambda: self.calibration, config.video)
        self.link = PeerLink(
            "follower",
            config.link,
            on_pose=self.on_pose,
            on_control=self.on_control,
            on_link_state=self.on_link_state,
            media=None if self.video is None else (lambda pc, role: self.video.attach(pc)),
        )
        self.following_since: float | None = None
        self.last_force_n = 0.0
        self.poses = self.virtual.figures  # the expert's pose stream
        self.alignment = AlignmentFigures()
        self.ticks = TickFigures(config.rate_hz)  # the main loop's ticks, how late
        self.tick_errors = 0
        self.tracking_lost = 0
        # the headset's stream and the force board, told to the headset page as they change
        self.devices = DeviceWatch(lambda state: self.feed.publish("devices", state))
        # Scans (from the expert).
        self.scan: int | None = None
        self.scans_seen = 0

    # --- incoming messages, one handler per kind ------------------------------------------

    def on_pose(self, msg: PoseMessage) -> None:
        """A virtual probe pose from the expert (``T_patient_probe``)."""
        self.virtual.on_pose(msg)

    @property
    def last_pose(self) -> PoseMessage | None:
        return self.virtual.last

    @property
    def last_pose_rx(self) -> float:
        """When the last pose came (s, monotonic)."""
        return self.virtual.rx

    @last_pose_rx.setter
    def last_pose_rx(self, t: float) -> None:
        self.virtual.rx = t

    def on_control(self, msg: ControlMessage) -> None:
        if isinstance(msg, Hello):
            self.to_expert.model()  # the expert (re)joined: give it the model we have
            self.to_expert.us_scale()
        elif isinstance(msg, CalibrationProgress) and msg.event == "start":
            self.start_calibration()
        elif isinstance(msg, Scan):
            self.on_scan(msg)

    def on_scan(self, msg: Scan) -> None:
        """The expert started or stopped a scan (its number is ``scan_id``)."""
        number = int(msg.scan_id) if msg.scan_id.isdigit() else None
        if msg.action == "start":
            self.scan = number
            self.scans_seen += 1
        elif self.scan == number or number is None:
            self.scan = None
        log.info("follower: scan %s %s", msg.scan_id, msg.action)
        if number is not None:  # the analysis takes scans from /expert/scan; this is the echo
            self.record("/follower/scan", None, {"event": msg.action, "scan": number})
        self.feed.publish("scan", {"scan": self.scan, "action": msg.action})

    def on_link_state(self, state: str) -> None:
        self.feed.publish("link", {"state": state})

    # --- outgoing -------------------------------------------------------------------------

    def send_control(self, msg: ControlMessage) -> bool:
        """Control messages only while connected (the expert learns the rest on Hello)."""
        return self.to_expert.control(msg)

    def publish_model(self) -> None:
        """The fitted ellipsoid (world frame) for the page's outline, if calibrated."""
        if self.calibration is not None:
            self.feed.publish("model", model_fields(self.calibration.ellipsoid))

    @property
    def calibration(self) -> Calibration | None:
        return self.cal.calibration

    @property
    def calibrating(self) -> bool:
        return self.cal.calibrating

    def start_calibration(self) -> None:
        self.cal.start()

    def on_fitted(self, t: float | None) -> None:
        """A new calibration: its model to the expert, the recording and the page."""
        self.to_expert.model()
        self.cal.record_model(t)
        self.publish_model()

    # --- the tick -------------------------------------------------------------------------

    def virtual_stale(self, t: float) -> bool:
        return self.virtual.stale(t)

    def tick(self, t: float) -> None:
        """The clinic sees the guide; at the tracker's rate, a frame is measured."""
        self.poses.tick(t, None if self.calibration is None else self.virtual_stale(t))
        virtual = self.virtual.world()
        live = virtual is not None and not self.virtual_stale(t) and not self.last_pose.clutch
        target = virtual if live else None  # the guide the novice follows (clutch: hold still)
        landmark = self.cal.landmark
        self.clinic.step(Guide(t, virtual, live, landmark, self.worker.measuring()))
        if self.calibrating or target is None:
            self.following_since = None
        elif self.following_since is None:
            self.following_since = t
        frame_period = 1.0 / self.config.sensing_rate_hz
        if t - self.last_measure_t >= frame_period:  # a tracker frame and a force reading
            # On the frame clock, so the rate is sensing_rate_hz even when it is not a whole
            # fraction of the tick rate (45 Hz from 100 Hz ticks, not 33); no catching up.
            late = t - self.last_measure_t >= 2.0 * frame_period
            self.last_measure_t = t if late else self.last_measure_t + frame_period
            world = self.clinic.world_at_frame(t)  # for the sim's devices; opaque here
            self.worker.submit(TrackerImage(t, world, virtual, target))
        self.virtual.publish_tick(t, self.measurement)
        v_patient = None if self.last_pose is None else self.last_pose.pose
        self.igtl.tick(t, self.calibration, v_patient)

    # --- measurements (sensing worker thread -> loop) -------------------------------------

    def _measured(self, frame: TrackerImage, m: Measurement) -> None:
        try:
            self.take_measurement(frame, m)
        except Exception:
            self.tick_errors += 1
            if self.tick_errors in (1, 10, 100, 1000):
                log.exception("follower: measurement failed (%d so far)", self.tick_errors)

    def _sensing_failed(self, reason: str) -> None:
        """The sensing process refused its config: the daemon stops (exit code 2)."""
        self.stop()

    def take_measurement(self, frame: TrackerImage, m: Measurement) -> None:
        """One tracker frame measured: calibration, alignment, the state stream, recording."""
        self.measurement = m
        self.measurements += 1
        self.devices.update(m)
        self.tracking_lost += m.T_world_tip is None
        self.last_force_n = float(np.linalg.norm(m.force_world))
        if self.calibrating and not m.force_stale:  # a stale force is never taken as fresh
            tip = None if m.T_world_tip is None else m.T_world_tip.position
            self.cal.update(frame.t, tip, self.last_force_n)
        elif frame.target is not None and self.following_since is not None:
            settled = frame.t - self.following_since >= self.config.alignment_settle_s
            if settled and m.T_world_tip is not None:
                self.alignment.add(m.T_world_tip, frame.virtual)
        self.to_expert.state(frame.t, m)
        self.record_measurement(frame.t, m)
        self.igtl.on_measurement(frame.t, self.calibration, m)
        self.registration.on_measurement(frame.t, m.T_world_tip, m.T_world_rig)

    # --- recording ------------------------------------------------------------------------

    def record(self, topic: str, t: float | None, payload: dict) -> None:
        """One sample (``t``: this daemon's monotonic clock, s; None: now), if recording."""
        if self.rec is not None:
            self.rec.write(topic, time.monotonic() if t is None else t, payload)

    def record_measurement(self, t: float, m: Measurement) -> None:
        for topic, payload in measurement_samples(m, self.calibration):
            self.record(topic, t, payload)

    def record_reports(self, t: float) -> None:
        """The clock-sync estimate when it changes; the pose stream's one-way latency (median
        since the last report) and how long the virtual probe was stale since then
        (``pose_stale_s``, once calibrated) about once a second."""
        if self.rec is None:
            return
        self.clock_log.update(self.rec, self.link.clock)
        self.poses.report(self.rec, t)

    def stats(self) -> dict:
        now = time.monotonic()
        return {
            **self.common_stats(self.link),
            **self.poses.stats(now),
            "states_sent": self.link.counters.sent.get("state", 0),
            **self.cal.stats(),
            "force_n": round(self.last_force_n, 3),
            **self.alignment.stats(),
            "feed_clients": len(self.feed.clients),
            "feed_url": self.feed.address if self.feed.port else None,
            "feed": self.feed.stats(),
            "registration": self.registration.stats(),
            "measurements": self.measurements,
            "tracking_lost": self.tracking_lost,
            **self.worker.stats(),
            "scan": self.scan,
            "scans_seen": self.scans_seen,
            "tick_errors": self.tick_errors,
            **self.ticks.stats(),
            "igtl": self.igtl.stats(),
            "video": None if self.video is None else self.video.stats(),
            "simulator_modules": self.simulator_loaded(),
        }

    def simulator_loaded(self) -> dict[str, list[str] | None]:
        """The simulator's modules loaded in each of the follower's processes (None: that
        process not running or not ready): all empty in a real clinic."""
        video = getattr(self.video, "process", None)
        return {"daemon": simulator_modules(),
                "sensing": getattr(self.worker.proc, "simulator_modules", None),
                "video": getattr(video, "simulator_modules", None)}  # fmt: skip

    async def run(self, duration_s: float | None = None) -> int:
        if not self.start_run():
            await self.stop_children(None)  # (the video's shared memory, made at __init__)
            return 2
        self.cal.record_model()  # a saved calibration's model
        # The video sources open beside the session (the video process takes a few seconds
        # to start); one that cannot open stops the daemon with a clear message, exit code 2.
        video_task = None if self.video is None else asyncio.create_task(self.start_video())
        self.worker.start()
        if self.config.feed.enabled:
            try:
                await self.feed.start()
            except OSError as exc:  # port taken, unknown host, unwritable state dir
                await self.stop_children(video_task)
                self.close_recording()
                print(self.feed.start_error(exc, self.state_dir), file=sys.stderr)
                return EXIT_FAILED
            except BaseException:  # the recording is still closed
                await self.stop_children(video_task)
                self.close_recording()
                raise
            print(f"humantele follower: {self.feed.banner()}", flush=True)
        await self.igtl.start()
        if self.igtl.banner():
            print(f"humantele follower: {self.igtl.banner()}", flush=True)
        link_task = asyncio.create_task(self.link.run())
        if self.calibration is None:
            self.start_calibration()
        else:
            log.info("follower: reusing the saved calibration %s", self.cal.path)
        self.cal.publish()
        self.publish_model()
        try:
            async for t in self.loop_ticks(
                self.config.rate_hz, duration_s, link_task, on_late=self.ticks.count_late
            ):
                self.ticks.tick(t)
                try:
                    self.tick(t)
                    self.record_reports(t)
                    if self.video is not None:
                        self.video.tick(t, self.ticks.late_ticks, self.measurements,
                                        self.config.sensing_rate_hz)  # fmt: skip
                except Exception:  # never let one bad tick end the daemon
                    self.tick_errors += 1
                    if self.tick_errors in (1, 10, 100, 1000):
                        log.exception("follower: tick failed (%d so far)", self.tick_errors)
        finally:
            await self.close_link(self.link, link_task)
            await self.feed.stop()
            await self.stop_children(video_task)
            await self.igtl.stop()
            self.finish_run()
        if self.worker.failure is not None:
            print(f"humantele follower: sensing cannot start: {self.worker.failure}", flush=True)
            return 2
        if self.video_error:
            return 2
        return self.run_result(link_task)

    async def stop_children(self, video_task: asyncio.Task | None) -> None:
        """Stop the video process (its open, if still waiting, then returns) and the sensing
        process."""
        if self.video is not None:  # (also never started: its shared memory goes)
            await asyncio.to_thread(self.video.close)
        if video_task is not None:
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(video_task, 5.0)
            await self.video.settle()  # a restart of the video process in flight
        self.worker.close()

    async def start_video(self) -> None:
        """Open the video sources (in a thread: it blocks) and start them; a source that
        cannot open is reported on stderr and stops the daemon (exit code 2)."""
        assert self.video is not None
        try:
            await asyncio.to_thread(self.video.open)
        except VideoSourceUnavailable as exc:
            self.video_error = str(exc)
            print(f"humantele follower: {exc}", file=sys.stderr, flush=True)
            self._stop.set()
            return
        self.video.start(asyncio.get_running_loop())
