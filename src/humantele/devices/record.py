"""``humantele devices record``: record what a clinic's devices deliver, to replay it as a test.

Opens the devices the follower's configuration names (``[sensing.camera]``: ``hl2ss``;
``[sensing.force.sensor]``: ``hid``; ``[follower.video.us|pov]``: any real video source) and
writes what they deliver into one MCAP (:mod:`humantele.recording.device_file`): the AHAT frames
as hl2ss sent them (raw depth and AB images, hl2ss timestamp, sensor ticks, the rig pose
matrix) and the AHAT calibration once; every HID report as read, before parsing, with its
receive time; the video frames as JPEG at the source's rate, with their capture time. One
thread per device; a progress line on stderr (seconds, frames per device, MB written). Ctrl-C
(or SIGTERM, or ``--duration``) ends it with a complete file::

    humantele devices record --follower-config configs/follower.toml --out clinic.mcap

The ``replay`` backends read the file (``[sensing.camera] backend = "replay"``, ``[sensing.
force.sensor] backend = "replay"``, ``[follower.video.us|pov] backend = "replay"``), and so
does ``python -m humantele.tracking.hl2ss_replay clinic.mcap``: docs/device_recording.md.

The simulated clinic is refused (nothing real to record); so is a ``sim`` device backend. A
tracker camera other than ``hl2ss`` is not recorded (said once). A device that cannot open
ends the command with its own one-line message (exit 1); one that stops while recording
ends its track, said once, and the others go on.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import cv2

from humantele.recording.device_file import (
    AHAT_CALIBRATION,
    AHAT_FRAME,
    HID_REPORT,
    VIDEO,
    DeviceRecordingWriter,
)

FLUSH_INTERVAL_S = 1.0
PROGRESS_INTERVAL_S = 0.5


def add_parser(sub: argparse._SubParsersAction) -> None:
    what = "record what the follower's devices deliver into one MCAP, to replay it as a test"
    p = sub.add_parser("record", help=what, description=what)
    p.add_argument(
        "--follower-config",
        required=True,
        help="the follower's TOML ([sensing], [follower.clinic], [follower.video])",
    )
    p.add_argument("--out", required=True, help="the MCAP file to write (must not exist)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: until Ctrl-C)")
    p.add_argument("--jpeg-quality", type=int, default=90, help="video frames' JPEG quality")


class RecordRefused(ValueError):
    """Nothing real to record with this configuration: one line saying why."""


@dataclass
class DevicePlan:
    """What will be recorded: (name, opened device, kind) and what is left out, with why."""

    devices: list[tuple[str, Any, str]] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    force_calibration: str = ""  # the board's calibration file (JSON), kept in the recording


def _raw_hl2ss_source(config: Any) -> Any:
    """An hl2ss source that keeps every frame (``newest = false``: none skipped when the
    recorder falls behind) and keeps them raw (not undistorted): the file keeps what the
    headset sent; the replay undistorts with the recorded calibration."""
    from humantele.tracking.hl2ss_source import Hl2ssFrameSource

    class RawHl2ssSource(Hl2ssFrameSource):
        unbias_h26x = False  # H.26x: the images as hl2ss's own client decodes them

        def _set_calibration(self, cal: Any) -> None:
            super()._set_calibration(cal)
            self._undistort = False

    return RawHl2ssSource(config.model_copy(update={"newest": False}))


def plan_devices(config_path: str | Path) -> DevicePlan:
    """The follower's configured devices, not yet opened; :class:`RecordRefused` for the
    simulated clinic or a ``sim`` tracker/force backend."""
    from humantele.config import load_config
    from humantele.follower.config import FollowerConfig
    from humantele.follower.sensing import SensingConfig
    from humantele.forcesense.hid import HidForceSensor
    from humantele.forcesense.sensors import make_force_sensor

    follower = load_config(FollowerConfig, config_path, "follower")
    sensing = load_config(SensingConfig, config_path, "sensing")
    if follower.clinic.backend != "devices":
        raise RecordRefused(
            f"{config_path}: the clinic is the simulator ([follower.clinic] backend = "
            f'"{follower.clinic.backend}"); recording needs real devices (backend = "devices")'
        )
    if sensing.camera.backend == "sim" or sensing.force.sensor.backend == "sim":
        raise RecordRefused(
            f"{config_path}: [sensing.camera] and [sensing.force.sensor] are "
            "simulated; set them to the real backends to record them"
        )
    plan = DevicePlan()
    if sensing.camera.backend == "hl2ss":
        plan.devices.append(("ahat", _raw_hl2ss_source(sensing.camera), "ahat"))
    else:
        plan.skipped.append(
            f"tracker camera ({sensing.camera.backend}): only hl2ss AHAT frames are recorded"
        )
    if sensing.force.calibration_file:  # the replay needs it as much as the board does
        plan.force_calibration = Path(sensing.force.calibration_file).read_text(encoding="utf-8")
    sensor = make_force_sensor(sensing.force.sensor)
    if isinstance(sensor, HidForceSensor):
        plan.devices.append(("force", sensor, "hid"))
    else:  # pragma: no cover - every real force backend is an HID reader today
        plan.skipped.append(f"force sensor ({sensing.force.sensor.backend}): not HID")
    from humantele.video.sources import make_video_source

    for track in ("us", "pov"):
        vc = getattr(follower.video, track)
        if vc.backend == "sim":
            plan.skipped.append(f"{track} video: sim source, not recorded")
            continue
        plan.devices.append((track, make_video_source(vc), "video"))
    return plan


class DeviceRecorder:
    """Records the opened devices of a :class:`DevicePlan` into ``writer`` from one thread
    each, until ``stop`` is set. ``counts[name]``: samples written; ``notes``: what ended a
    track early."""

    def __init__(self, plan: DevicePlan, writer: DeviceRecordingWriter, jpeg_quality: int = 90):
        self.plan, self.writer = plan, writer
        self.jpeg_quality = jpeg_quality
        self.stop = threading.Event()
        self.counts: dict[str, int] = {name: 0 for name, _, _ in plan.devices}
        self.notes: list[str] = []
        self._threads: list[threading.Thread] = []

    def open(self) -> None:
        """Open every device (all or none: a failure closes those opened and re-raises)."""
        opened = []
        try:
            for _name, dev, kind in self.plan.devices:
                dev.open()
                opened.append(dev)
                if kind == "ahat" and dev.calibration is not None:
                    self.writer.write(
                        AHAT_CALIBRATION,
                        time.monotonic(),
                        {
                            "t_receive": time.monotonic(),
                            "source": f"hl2ss mode 2 or {dev.config.calibration_file}",
                        },
                        {"calibration": dev.calibration.to_bytes()},
                    )
        except Exception:
            for dev in opened:
                dev.close()
            raise

    def start(self) -> None:
        for name, dev, kind in self.plan.devices:
            target = {"ahat": self._ahat, "hid": self._hid, "video": self._video}[kind]
            th = threading.Thread(
                target=self._guard, args=(name, target, dev), name=f"record-{name}", daemon=True
            )
            th.start()
            self._threads.append(th)

    def _guard(self, name: str, target: Any, dev: Any) -> None:
        try:
            target(name, dev)
        except Exception as exc:  # noqa: BLE001 - one device's end must not stop the others
            self.notes.append(f"{name}: stopped ({exc})")

    def _ahat(self, name: str, src: Any) -> None:
        import numpy as np

        while not self.stop.is_set():
            frame = src.read()
            if frame is None:  # a timeout, or the stream is reconnecting: do not spin
                self.stop.wait(0.005)
                continue
            t = time.monotonic()
            blobs: dict[str, Any] = {"depth": frame.depth_mm, "ab": frame.ir}
            if src.last_pose is not None and src.config.mode == 1:
                blobs["pose"] = np.asarray(src.last_pose, "<f4")
            self.writer.write(
                AHAT_FRAME,
                t,
                {
                    "t_receive": t,
                    "timestamp": src.last_timestamp,
                    "sensor_ticks": src.last_sensor_ticks,
                    "seq": frame.seq,
                },
                blobs,
            )
            self.counts[name] += 1

    def _hid(self, name: str, sensor: Any) -> None:
        def on_report(data: bytes, t: float) -> None:
            self.writer.write(HID_REPORT, t, {"t_receive": t}, {"report": data})
            self.counts[name] += 1

        sensor.on_report = on_report
        while not self.stop.is_set():
            sensor.read()
            if not self.stop.is_set() and sensor.config.read_timeout_ms == 0:
                time.sleep(0.001)

    def _video(self, name: str, src: Any) -> None:
        params = [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)]
        while not self.stop.is_set():
            frame = src.read()
            if frame is None:
                continue
            ok, jpeg = cv2.imencode(".jpg", frame.image, params)
            if not ok:
                continue
            spacing = None if frame.pixel_spacing_mm is None else list(frame.pixel_spacing_mm)
            self.writer.write(
                VIDEO[name],
                frame.t_capture,
                {
                    "t_capture": frame.t_capture,
                    "seq": frame.seq,
                    "width": frame.width,
                    "height": frame.height,
                    "pixel_spacing_mm": spacing,
                    "depth_origin_row": frame.depth_origin_row,
                },
                {"jpeg": jpeg.tobytes()},
            )
            self.counts[name] += 1

    def alive(self) -> bool:
        return any(th.is_alive() for th in self._threads)

    def finish(self) -> None:
        """Stop the threads, close the devices (a thread blocked in a read gets up to a few
        seconds: the devices' read timeouts)."""
        self.stop.set()
        for th in self._threads:
            th.join(timeout=5.0)
        for _name, dev, _kind in self.plan.devices:
            try:
                dev.close()
            except Exception:  # noqa: BLE001 - closing a vanished device must not raise
                pass


def progress_line(elapsed: float, counts: dict[str, int], nbytes: int) -> str:
    """``12.5 s  ahat 560  force 1250  us 375  pov 375  41.2 MB``."""
    parts = "  ".join(f"{k} {v}" for k, v in counts.items())
    return f"{elapsed:6.1f} s  {parts}  {nbytes / 1e6:.1f} MB"


def record(
    config_path: str | Path,
    out: str | Path,
    duration: float | None = None,
    stop: threading.Event | None = None,
    progress: TextIO | None = None,
    jpeg_quality: int = 90,
    until: Callable[[dict[str, int]], bool] | None = None,
) -> tuple[dict[str, int], list[str]]:
    """Record until ``duration`` (s), ``stop``, or ``until(samples per device)`` is true;
    returns (samples per device, notes). Raises RecordRefused, a device's unavailability
    error, or OSError (the output)."""
    plan = plan_devices(config_path)
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; give a new file")
    names = ",".join(n for n, _, _ in plan.devices)
    info = {"follower_config": str(config_path), "devices": names}
    if plan.force_calibration:
        info["force_calibration"] = plan.force_calibration
    writer = DeviceRecordingWriter(out, info)
    rec = DeviceRecorder(plan, writer, jpeg_quality)
    stop = stop or threading.Event()
    try:
        rec.open()
    except Exception:
        writer.close()
        out.unlink(missing_ok=True)
        raise
    notes = list(plan.skipped)
    t0 = time.monotonic()
    last_flush = last_progress = t0
    try:
        rec.start()
        while not stop.is_set():
            now = time.monotonic()
            if duration is not None and now - t0 >= duration:
                break
            if not rec.alive() or (until is not None and until(dict(rec.counts))):
                break
            if now - last_flush >= FLUSH_INTERVAL_S:
                writer.flush()
                last_flush = now
            if progress is not None and now - last_progress >= PROGRESS_INTERVAL_S:
                progress.write("\r" + progress_line(now - t0, rec.counts, writer.bytes_written()))
                progress.flush()
                last_progress = now
            stop.wait(0.05)
    finally:
        rec.finish()
        writer.close()
    if progress is not None:
        progress.write(
            "\r" + progress_line(time.monotonic() - t0, rec.counts, writer.bytes_written()) + "\n"
        )
        progress.flush()
    return dict(rec.counts), notes + rec.notes


def run(args: argparse.Namespace) -> int:
    from humantele.forcesense.base import ForceSensorUnavailable
    from humantele.tracking.frames import FrameSourceUnavailable
    from humantele.video.base import VideoSourceError

    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        counts, notes = record(
            args.follower_config, args.out, args.duration, stop, sys.stderr, args.jpeg_quality
        )
    except RecordRefused as exc:
        print(f"devices record: {exc}", file=sys.stderr)
        return 2
    except (FrameSourceUnavailable, ForceSensorUnavailable, VideoSourceError, OSError) as exc:
        print(f"devices record: {exc}", file=sys.stderr)
        return 1
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    for note in notes:
        print(f"devices record: {note}", file=sys.stderr)
    summary = ", ".join(f"{k} {v}" for k, v in counts.items())
    print(f"recorded {args.out}: {summary}")
    return 0
