"""The ``replay`` tracker backend: AHAT frames from a device recording, as the headset sent them.

Reads ``/ahat/frame`` (and the calibration, ``/ahat/calibration``) of a file written by
``humantele devices record`` (:mod:`humantele.recording.device_file`) and gives the frames the
``hl2ss`` backend would have given: the raw images undistorted with the recorded calibration,
``T_world_rig`` from the recorded rig pose (hl2ss's row-vector matrix, converted by
:func:`~humantele.tracking.hl2ss_protocol.pose_from_hl2ss`), ``T_world_camera = T_world_rig @
T_rig_camera`` (the AHAT extrinsics). A frame without a usable pose is returned without one and
counted in ``no_pose``, as the hl2ss backend does.

Pacing (``pace = true``): ``read`` blocks until the frame's recorded time (its hl2ss
timestamp, 100 ns ticks) on the recording's timeline
(:mod:`humantele.recording.replay_timeline`), shared with the force board's replay of the same
file: from ``open``, counted from the recording's first message, each loop the recording's
span; so a press comes with the frames of its tip, however late the first ``read`` comes. A
reader that fell behind skips to the newest frame already due, the older ones counted in
``dropped["stale"]``, as the hl2ss backend does (``newest = false``: every frame in order).
One ``read`` waits at most ``MAX_WAIT_S`` (a recording with a pause, e.g. a stalled stream,
must not hold a read longer than the headset's would be held: the follower takes a sensing
process that gives no answer for seconds as hung); the frame is then given by a later read.
``device_time_s`` is the frame's hl2ss timestamp in s. ``loop``: start again at the end; else
``read`` returns None (counted in ``dropped["end"]``).

``open`` raises :class:`FrameSourceUnavailable` (one line) for a file that is not a device
recording or holds no AHAT frame; a truncated file is replayed up to its torn tail, logged.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Literal

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.geometry import Pose
from humantele.recording.device_file import (
    AHAT_CALIBRATION,
    AHAT_FRAME,
    DeviceRecording,
    DeviceRecordingError,
    Sample,
    open_recording,
)
from humantele.recording.replay_timeline import DeviceClock, ReplayTimeline, shared_timeline
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.frames import FrameSource, FrameSourceUnavailable, TrackingFrame
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_protocol import AHAT_HEIGHT, AHAT_WIDTH, frame_poses

TICKS_PER_S = 1e7  # hl2ss timestamps: 100 ns


MAX_WAIT_S = 1.0  # one read waits at most this long for a frame's recorded time (s)


class ReplayFrameConfig(ConfigModel):
    """The ``replay`` tracker backend: a device recording's AHAT frames."""

    backend: Literal["replay"] = "replay"
    file: str = Field(..., min_length=1, description="MCAP from `humantele devices record`")
    loop: bool = Field(False, description="start again at the end")
    pace: bool = Field(True, description="at the recorded times (False: as fast as read)")
    newest: bool = Field(
        True,
        description="a paced reader that fell behind skips to the newest frame due (counted "
        "as stale), as the hl2ss backend; false: every frame in order",
    )


class ReplayFrameSource(FrameSource):
    """AHAT frames from a device recording (see the module docstring). ``last_timestamp`` is
    the last frame's hl2ss timestamp; ``problem`` says why the file ended early, if it did."""

    name = "replay AHAT"

    def __init__(self, config: ReplayFrameConfig, clock=time.monotonic, sleep=time.sleep):
        self.config = config
        self.intrinsics = CameraIntrinsics(width=AHAT_WIDTH, height=AHAT_HEIGHT)
        self.calibration: Hl2ssAhatCalibration | None = None
        self.T_rig_camera: Pose | None = None
        self.dropped: dict[str, int] = {}
        self.no_pose: dict[str, int] = {}
        self.received = 0
        self.last_timestamp: int | None = None
        self.last_sensor_ticks: int | None = None
        self.problem: str | None = None
        self._clock, self._sleep = clock, sleep
        self._held: tuple[Sample, float] | None = None  # a frame a read stopped waiting for
        self._rec: DeviceRecording | None = None
        self._it: Iterator[Sample] | None = None
        self._next: Sample | None = None
        self._next_due = 0.0  # when it is due (s, the clock)
        self._timeline: ReplayTimeline | None = None
        self._loop = 0
        self._device = DeviceClock(TICKS_PER_S)
        self._seq = 0
        self._undistort = False

    def open(self) -> None:
        if self._rec is not None:
            return
        try:
            rec = open_recording(self.config.file)
        except DeviceRecordingError as exc:
            raise FrameSourceUnavailable(f"replay tracker: {exc}") from None
        self._rec = rec
        self._timeline, self._loop = shared_timeline(rec.path, rec.span(), self._clock), 0
        self._restart()
        if self._next is None:
            self._rec = None
            raise FrameSourceUnavailable(
                f"replay tracker: {self.config.file} holds no AHAT "
                f"frame{'' if rec.problem is None else f' ({rec.problem})'}"
            )

    def _restart(self) -> None:
        assert self._rec is not None
        self._it = self._rec.samples({AHAT_CALIBRATION, AHAT_FRAME})
        self._device = DeviceClock(TICKS_PER_S)  # hl2ss's 100 ns ticks
        self._next = self._advance()

    def _advance(self) -> Sample | None:
        """The next frame sample (taking the calibration on the way)."""
        assert self._it is not None and self._rec is not None
        for s in self._it:
            if s.topic == AHAT_CALIBRATION:
                if self.calibration is None:
                    self._set_calibration(s)
                continue
            assert self._timeline is not None
            ts = s.fields.get("timestamp")
            t = self._device.time(s.t, int(ts) if isinstance(ts, int | float) else None)
            self._next_due = self._timeline.due(t, self._loop)
            return s
        self.problem = self._rec.problem
        return None

    def _set_calibration(self, s: Sample) -> None:
        try:
            cal = Hl2ssAhatCalibration.from_bytes(bytes(s.blobs["calibration"]))
            cal.check_axes()
        except (KeyError, ValueError):
            self.dropped["calibration"] = self.dropped.get("calibration", 0) + 1
            return
        self.calibration = cal
        self.T_rig_camera = cal.T_rig_camera()
        self.intrinsics = cal.intrinsics()
        self._undistort = not cal.is_identity_map()

    def read(self, t: float | None = None) -> TrackingFrame | None:
        """The next recorded frame (stamped ``t``, default the clock), once it is due; None at
        the end (without ``loop``) or before ``open``."""
        if self._rec is None:
            self.dropped["not_open"] = self.dropped.get("not_open", 0) + 1
            return None
        if self._held is None and self._next is None and self.config.loop:
            assert self._timeline is not None
            if self._timeline.period is None:  # no span known: from where it ends, on its own
                self._timeline, self._loop = ReplayTimeline(None, self._clock), 0
            else:
                self._loop += 1
            self._restart()
        held, self._held = self._held, None
        if held is not None:
            s, due = held
        elif self._next is None:
            self.dropped["end"] = self.dropped.get("end", 0) + 1
            return None
        else:
            s, due = self._next, self._next_due
            self._next = self._advance()
        if self.config.pace:
            now = self._clock()
            while self.config.newest and self._next is not None and self._next_due <= now:
                s, due = self._next, self._next_due  # behind: the newer one is due
                self._next = self._advance()
                self.dropped["stale"] = self.dropped.get("stale", 0) + 1
            wait = due - now
            if wait > MAX_WAIT_S:  # a pause in the recording: this read ends, the frame waits
                self._sleep(MAX_WAIT_S)
                self._held = (s, due)
                self.dropped["timeout"] = self.dropped.get("timeout", 0) + 1
                return None
            if wait > 0:
                self._sleep(wait)
        return self._frame(s, int(s.fields.get("timestamp", 0)), t)

    def _frame(self, s: Sample, ts: int, t: float | None) -> TrackingFrame | None:
        try:
            depth = np.asarray(s.blobs["depth"], np.uint16).reshape(AHAT_HEIGHT, AHAT_WIDTH)
            ab = np.asarray(s.blobs["ab"], np.uint16).reshape(AHAT_HEIGHT, AHAT_WIDTH)
        except (KeyError, ValueError):
            self.dropped["bad_frame"] = self.dropped.get("bad_frame", 0) + 1
            return None
        self.last_timestamp, self.last_sensor_ticks = ts, int(s.fields.get("sensor_ticks", 0))
        pose = s.blobs.get("pose")
        matrix = None if pose is None else np.asarray(pose, np.float32).reshape(4, 4)
        T_world_rig, T_world_camera = frame_poses(matrix, self.T_rig_camera, self.no_pose)
        if self._undistort and self.calibration is not None:
            depth, ab = self.calibration.undistort(depth, ab)
        self.received += 1
        self._seq += 1
        return TrackingFrame(
            t=self._clock() if t is None else t,
            ir=ab,
            depth_mm=depth,
            intrinsics=self.intrinsics,
            seq=self._seq,
            T_world_camera=T_world_camera,
            T_world_rig=T_world_rig,
            device_time_s=ts / TICKS_PER_S,
        )

    def close(self) -> None:
        if self._it is not None:
            close = getattr(self._it, "close", None)
            if close is not None:
                close()
        self._it, self._next, self._rec = None, None, None
