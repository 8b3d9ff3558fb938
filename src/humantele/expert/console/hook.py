"""The console in the expert daemon: the session it shows, and where its video comes from.

:class:`DaemonSession` is the :class:`~humantele.expert.console.session.ConsoleSession` of the
expert daemon, which the console sees only as an :class:`~.expert_view.ExpertView` (a protocol:
the console never imports the daemon). :func:`make_console` builds the server with the video
``[expert.console] video`` asks for:

- ``received``: the follower's tracks as the daemon's WebRTC receiver decodes them
  (:mod:`humantele.media.receiver`, given when ``[expert.video]`` is enabled);
- ``sim``: sim sources here, rendering what the session knows (the patient model, the
  follower's tracked probe and force), labelled as simulated on the page: a stand-in for
  development and the demo while the tracks do not come over the link;
- ``auto`` (default): ``received`` when ``[expert.video]`` is enabled, else ``sim``;
- ``none``: no video.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from humantele.expert.console.config import ConsoleConfig
from humantele.expert.console.expert_view import ExpertView
from humantele.expert.console.frames import FrameProvider, ProcessFrames, ReceivedFrames
from humantele.expert.console.server import ConsoleServer
from humantele.geometry import Pose
from humantele.recording import Recorder
from humantele.video.scene import SceneSnapshot, look_at
from humantele.video.sim_pov import SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasoundConfig
from humantele.web.credential import CONSOLE_KEY_ENV, key_from_env
from humantele.wire import UsScale

log = logging.getLogger(__name__)


def alignment(a: Pose, b: Pose) -> dict[str, float]:
    """Tip distance (mm) and rotation angle (deg) between two probe poses (same frame)."""
    m, rad = a.distance_to(b)
    return {"mm": m * 1000.0, "deg": math.degrees(rad)}


def pressing_n(force_tip: Any) -> float:
    """The contact force along the beam (N, > 0 pressing into the patient) of a force on the
    probe in its tip frame (+z along the beam, into the patient): the patient pushes the probe
    back along -z."""
    return -float(force_tip[2])


class DaemonSession:
    """The expert daemon as the console sees it."""

    def __init__(self, expert: ExpertView) -> None:
        self.d = expert

    @property
    def recorder(self) -> Recorder | None:
        return self.d.rec

    def snapshot(self) -> dict[str, Any]:
        d = self.d
        now = d.clock()
        st = d.last_state
        pose_age = None
        if st is not None and d.last_state_t is not None:
            pose_age = (now - d.last_state_t) * 1000.0  # last_state_t: when it was sent
        latest = d.servo.latest() if d.servo.alive else None
        try:
            servo_stats = d.servo.stats() if d.servo.alive else None
        except Exception:  # noqa: BLE001 - a servo that just died: shown as stopped
            servo_stats = None
        al = None
        if st is not None and d.last_pose is not None:
            al = alignment(d.last_pose, st.pose)
        rec = d.rec
        return {
            "t": now,
            "link": {"state": d.link.state, "pose_age_ms": pose_age},
            "calibration": {
                "state": d.calibration_state,
                "landmark": d.calibration_landmark,
                "last": d.calibration_events[-1] if d.calibration_events else None,
            },
            "alignment": al,
            "servo": {
                "alive": latest is not None,
                "rate_hz": None if servo_stats is None else servo_stats.rate_hz,
                "fault": "" if latest is None else latest.fault,
            },
            "recording": {
                "on": rec is not None and not rec.failed,
                "error": None if rec is None else rec.stats.error,
                "written": None if rec is None else rec.stats.written,
            },
            "scan": d.scan,
            "clutch": {"on": d.console_clutch, "engaged": d.mapping.clutched},
            "force": {
                "measured_n": None if st is None else pressing_n(st.force),
                "rendered_n": None
                if latest is None
                else pressing_n(latest.T_patient_stylus.inverse().rotate(latest.force)),
                "contact": None if st is None else bool(st.contact),
            },
        }

    def pose_at(self, t: float) -> dict[str, Any] | None:
        real = self.d.probe_history.at(t)
        if real is None:
            return None
        out: dict[str, Any] = {"position": real.position, "quaternion": real.quaternion}
        virtual = self.d.virtual_history.at(t)
        if virtual is not None:
            out.update(virtual_position=virtual.position, virtual_quaternion=virtual.quaternion)
        return out

    def start_scan(self) -> int:
        return self.d.start_scan(self.d.clock())

    def stop_scan(self) -> None:
        self.d.stop_scan(self.d.clock())

    def set_clutch(self, on: bool) -> None:
        self.d.console_clutch = bool(on)


class SessionScene:
    """The sim sources' scene from what the expert knows: the patient model (its patient
    frame as the world), the follower's tracked probe and force, the virtual probe; a head
    0.5 m above and beside the probe, looking at it. Called from the sources' threads: it only
    reads references the daemon replaces whole."""

    def __init__(self, expert: ExpertView) -> None:
        self.d = expert

    def __call__(self) -> SceneSnapshot:
        d = self.d
        model, st = d.model, d.last_state
        tip = None if st is None else st.pose
        force = 0.0 if st is None else float(np.linalg.norm(st.force))
        head = None
        if model is not None:
            target = tip.position if tip is not None else np.asarray(model.center, dtype=float)
            head = look_at(model.T_world_patient.apply((0.02, 0.45, 0.42)), target)
        return SceneSnapshot(d.clock(), model, tip, force, head, d.last_pose)


def sim_frames(expert: ExpertView) -> ProcessFrames:
    """Sim ultrasound and POV of the session, rendered in a child process (lighter than the
    follower's: 15 fps, POV 640 x 360), for ``video = "sim"``."""
    return ProcessFrames(
        {
            "us": SimUltrasoundConfig(fps=15.0),
            "pov": SimPovConfig(fps=15.0, width=640, height=360),
        },
        SessionScene(expert),
    )


def make_console(
    expert: ExpertView, cfg: ConsoleConfig, receiver: Any | None
) -> tuple[ConsoleServer, ProcessFrames | None]:
    """The console server for ``expert`` (``cfg``: ``[expert.console]``; ``receiver``: the
    daemon's :class:`~humantele.media.receiver.VideoReceiver`, None when ``[expert.video]`` is
    off) and, for sim video, its sources (they run while a console page is open; the daemon
    stops them at the end)."""
    received: FrameProvider | None = None
    if receiver is not None:
        received = ReceivedFrames(receiver, cfg.us_pixel_spacing_mm, cfg.us_depth_origin_row)
    mode = cfg.video
    if mode == "auto":
        mode = "received" if received is not None else "sim"
    local = sim_frames(expert) if mode == "sim" else None
    frames = received if mode == "received" else local
    server = ConsoleServer(
        cfg, frames, DaemonSession(expert), clock=expert.clock, video=mode, on_demand=local
    )
    return server, local


class DaemonConsole:
    """The console of the expert daemon (``cfg``: ``[expert.console]``; ``receiver``: the
    daemon's video receiver, None when ``[expert.video]`` is off): served from the daemon's
    start (a port that cannot be had is logged and the daemon runs without it: the haptics come
    first), the follower's US scale on its received frames, stopped at the daemon's end."""

    def __init__(self, cfg: ConsoleConfig, receiver: Any | None, archive: Any = None) -> None:
        self.cfg = cfg
        self.archive_cfg = archive  # [expert.archive] (None or disabled: no archive)
        self.receiver = receiver
        self.server: Any = None  # the ConsoleServer while served (tests may put a stand-in)
        self.local: ProcessFrames | None = None  # sim video sources, stopped at the end
        self.us_scale: tuple[tuple[float, float], float] | None = None  # the follower's
        if cfg.enabled:  # a bad $HUMANTELE_CONSOLE_KEY refused now, before the servo starts
            key_from_env()

    def on_us_scale(self, msg: UsScale) -> None:
        """The follower's scanner scale: the console's calipers and depth scale take it,
        unless ``[expert.console]`` sets them (the configuration wins, and says so)."""
        if self.cfg.us_pixel_spacing_mm is not None or self.cfg.us_depth_origin_row is not None:
            log.info("expert: the follower's US scale %s ignored: [expert.console] sets it",
                     msg.pixel_spacing_mm)  # fmt: skip
            return
        self.us_scale = (msg.pixel_spacing_mm, msg.depth_origin_row)
        self.apply_us_scale(getattr(self.server, "frames", None))

    def apply_us_scale(self, frames: object) -> None:
        """The follower's scale on the console's received frames (not the sim stand-in)."""
        if self.us_scale is not None and hasattr(frames, "us_spacing_mm"):
            frames.us_spacing_mm, frames.us_depth_origin_row = self.us_scale

    async def start(self, expert: ExpertView) -> None:
        """Serve the console page of ``expert`` (nothing if disabled or already served)."""
        if not self.cfg.enabled or self.server is not None:
            return
        self.server, self.local = make_console(expert, self.cfg, self.receiver)
        if self.archive_cfg is not None and self.archive_cfg.enabled:
            from humantele.expert.console.archive_routes import ConsoleArchive

            try:
                self.server.archive = ConsoleArchive(
                    self.archive_cfg, self.server.key, scan=lambda: expert.scan
                )
            except OSError as exc:  # its queue folder: the haptics and the session go on
                log.error("expert: [expert.archive] queue_dir unusable, no archive: %s", exc)
        self.apply_us_scale(self.server.frames)  # one that came before the console
        try:
            await self.server.start()
        except OSError as exc:
            log.error("expert: console not served: %s", exc)
            print(f"humantele expert: console not served: {exc}", flush=True)
            self.server = None
            return
        print(f"humantele expert: {console_line(self.server, sys.stdout.isatty())}", flush=True)

    async def stop(self) -> None:
        if self.local is not None:
            await asyncio.to_thread(self.local.stop)
            self.local = None
        if self.server is not None:
            await self.server.stop()


def console_url_file() -> Path:
    """Where the expert keeps its console's whole address (with the key) when its output is
    not a terminal: ``$XDG_STATE_HOME/humantele/console_url`` (``~/.local/state``)."""
    state = os.environ.get("XDG_STATE_HOME") or "~/.local/state"
    return Path(state).expanduser() / "humantele" / "console_url"


def console_line(server: ConsoleServer, tty: bool) -> str:
    """The expert's line about its console. On a terminal (a person runs it) the whole
    address, with the key; otherwise (a log file, systemd's journal, which others may read)
    the address without the key, and where the key is: ``$HUMANTELE_CONSOLE_KEY`` when set,
    else the whole address written to a file only this user can read."""
    if tty:
        return server.banner()
    if os.environ.get(CONSOLE_KEY_ENV):
        return f"console {server.address} (its key: ${CONSOLE_KEY_ENV}; not logged)"
    path = console_url_file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # made again below with this run's address, owner-only
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(server.url + "\n")
    except OSError as exc:
        return (
            f"console {server.address} (its key is not logged, and could not be kept in "
            f"{path}: {exc.strerror or exc}; set ${CONSOLE_KEY_ENV} to choose it)"
        )
    return f"console {server.address} (the address with its key, not logged: in {path})"
