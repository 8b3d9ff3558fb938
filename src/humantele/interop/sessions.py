"""What each daemon serves over OpenIGTLink (:mod:`.igtl`): small adapters the daemons call
once per tick, so the daemons hold one line per hook.

Follower: ``ProbeToWorld`` (measured, from the start), ``ProbeToPatient`` (measured, once
calibrated), ``VirtProbeToPatient`` (the expert's pose),
``PatientToWorld``, ``ProbeForce`` and, with ``image``, the ultrasound ``Image`` and
``ImageToProbe``. The image is the follower's own ultrasound track (the frames it sends the
expert, :mod:`humantele.media.sender`; pixel size from its sim ultrasound's geometry); with the
follower's video off, a sim ultrasound (:class:`humantele.video.sim_ultrasound.SimUltrasound`)
renders it at ``image_rate_hz`` in a separate low-priority process (a frame costs ~0.1 s of
CPU), only while a client is connected.
Expert: ``StylusToPatient`` (what it sends), ``ProbeToPatient`` and ``ProbeForce`` (as
received), and the ultrasound ``Image`` when it receives frames (``tick(..., us)``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from humantele.geometry import Pose
from humantele.interop.igtl import (
    FORCE,
    IMAGE_TO_PROBE,
    PATIENT,
    PROBE,
    PROBE_WORLD,
    STYLUS,
    VIRTUAL_PROBE,
    IgtlConfig,
    IgtlServer,
    force_text,
    image_to_probe,
    matrix_mm,
    ras_from_patient,
    world_from_ras,
)
from humantele.runtime.child import PRIORITY, ignore_group_signals, set_priority, watch_parent

log = logging.getLogger(__name__)


class _Served:
    """The server and the optional frame source common to both sides."""

    def __init__(self, config: IgtlConfig) -> None:
        self.config = config
        self.server: IgtlServer | None = IgtlServer(config) if config.enabled else None
        self.T_tip_image: np.ndarray | None = None

    @property
    def enabled(self) -> bool:
        return self.server is not None

    async def start(self) -> None:
        if self.server is not None and not await self.server.start():
            self.server = _Failed(self.server)  # type: ignore[assignment]

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.stop()

    def banner(self) -> str | None:
        s = self.server
        return s.banner() if isinstance(s, IgtlServer) and s.port else None

    def stats(self) -> dict[str, Any] | None:
        return None if self.server is None else self.server.stats()


class _Failed:
    """Stands in for a server that could not listen: publishes nothing, keeps the error."""

    def __init__(self, server: IgtlServer) -> None:
        self._server = server

    def __getattr__(self, name: str) -> Any:
        if name.startswith("publish_"):
            return lambda *a, **k: False
        return getattr(self._server, name)

    async def stop(self) -> None:
        await self._server.stop()


class FollowerIgtl(_Served):
    """The follower's OpenIGTLink output; ``tick`` is called once per follower tick."""

    def __init__(
        self,
        config: IgtlConfig,
        scene: Callable[[], Any] | None = None,
        us: tuple[Any, Any] | None = None,
    ) -> None:
        """``scene``: the sim clinic's scene (a SceneSnapshot callable) for an ultrasound of
        our own when the follower sends no video; ``us``: the follower's ultrasound track,
        (its latest-frame slot of CapturedFrame, its source config), used instead when it
        does. Neither: no Image."""
        super().__init__(config)
        self._scene = scene
        self._pool: ProcessPoolExecutor | None = None
        self._rendering = False
        self._last_render = -math.inf
        self.renders = 0
        self._us_slot = None
        self._us_seen = 0
        self._us_spacing_mm = 0.0
        self._us_row0 = 0.0
        if self.server is None or not config.image:
            return
        from humantele.video.sim_config import SimUltrasoundConfig

        if us is not None:
            slot, us_config = us
            if not isinstance(us_config, SimUltrasoundConfig):  # a scanner: its configured scale
                spacing = getattr(us_config, "pixel_spacing_mm", None)
                row0 = getattr(us_config, "depth_origin_row", None)
                if spacing is None or row0 is None:
                    log.warning("igtl: the ultrasound source does not say its scale: no Image")
                    return
                self._us_slot, self._us_spacing_mm = slot, float(spacing[0])
                self._us_row0 = float(row0)  # ImageToProbe once a frame gives the width
                return
            self._us_slot, c = slot, us_config
        elif scene is not None:
            c = SimUltrasoundConfig(counter=False)
            self._us_config = c.model_dump_json()
        else:
            return
        from humantele.video.scan import ScanGeometry

        g = ScanGeometry(c.probe, c.width, c.height, c.depth_m, c.fov_deg, c.radius_m,
                         c.aperture_m, c.beams, c.samples)  # fmt: skip
        self._us_spacing_mm = g.pixel_spacing_mm[0]
        self.T_tip_image = image_to_probe(g.origin_m, self._us_spacing_mm)

    async def start(self) -> None:
        await super().start()
        own = self._us_slot is None and self.T_tip_image is not None
        if isinstance(self.server, IgtlServer) and own:
            self._pool_start()  # spawned now, so the first client gets images at once

    def _pool_start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._pool = ProcessPoolExecutor(1, ctx, initializer=_us_init,
                                         initargs=(self._us_config,))  # fmt: skip
        self._pool.submit(_us_ping)

    async def stop(self) -> None:
        if self._pool is not None:
            pool, self._pool = self._pool, None
            await asyncio.to_thread(pool.shutdown, True, cancel_futures=True)
        await super().stop()

    def _forward_us(self, srv: IgtlServer) -> None:
        """The follower's newest ultrasound frame (I420; its luma is sent), once."""
        number, cf = self._us_slot.peek()  # type: ignore[union-attr]
        if cf is None or number == self._us_seen:
            return
        s = self._us_spacing_mm
        if self.T_tip_image is None:  # a scanner's picture: the face's centre at the top middle
            x0, z0 = -(cf.width - 1) / 2 * s / 1000.0, -self._us_row0 * s / 1000.0
            self.T_tip_image = image_to_probe((x0, z0), s)
        if srv.publish_image(cf.frame, (s, s), cf.t_capture):
            self._us_seen = number

    def _render_us(self, t: float) -> None:
        """Ask the sim ultrasound process for the image at ``t`` (one at a time, at most
        ``image_rate_hz``): rendering costs ~0.1 s of CPU per frame, so it never runs in the
        daemon's process; it runs at a lower priority in its own."""
        if self._rendering or t - self._last_render < 1.0 / self.config.image_rate_hz:
            return
        if self._pool is None:
            self._pool_start()
        s = self._scene()  # the sim clinic's world now, as its ultrasound probe sees it
        snap = type(s)(t, s.patient, s.T_world_tip, s.force_n, None)
        self._rendering, self._last_render = True, t
        fut = asyncio.get_running_loop().run_in_executor(self._pool, _us_render, snap, t)
        fut.add_done_callback(self._rendered)

    def _rendered(self, fut: asyncio.Future) -> None:
        self._rendering = False
        if fut.cancelled() or fut.exception() is not None:
            if not fut.cancelled():
                log.warning("igtl: sim ultrasound failed: %s", fut.exception())
            return
        image, spacing, t = fut.result()
        self.renders += 1
        if isinstance(self.server, IgtlServer) and spacing is not None:
            self.server.publish_image(image, spacing, t)

    def tick(
        self,
        t: float,
        calibration: Any | None,
        virtual_patient: Pose | None,
    ) -> None:
        """Once per follower tick: the virtual probe (``T_patient_tip`` of the expert's pose),
        the patient frame, ``ImageToProbe``, and the ultrasound image."""
        srv = self.server
        if srv is None:
            return
        if not isinstance(srv, IgtlServer) or not srv.clients:
            return  # nobody watching: no work
        if self._us_slot is not None:
            self._forward_us(srv)
        elif self.T_tip_image is not None:
            self._render_us(t)
        if calibration is not None:
            srv.publish_transform(PATIENT, world_from_ras(calibration.T_world_patient), t)
        if virtual_patient is not None:
            srv.publish_transform(VIRTUAL_PROBE, ras_from_patient(virtual_patient), t)
        if self.T_tip_image is not None:
            srv.publish_transform(IMAGE_TO_PROBE, self.T_tip_image, t)

    def on_measurement(self, t: float, calibration: Any | None, m: Any) -> None:
        """One tracker frame measured at ``t``: ``ProbeToWorld`` (when tracked, from the
        start), ``ProbeToPatient`` (when tracked, once calibrated) and ``ProbeForce``, stamped
        with the frame's time."""
        srv = self.server
        if not isinstance(srv, IgtlServer) or not srv.clients:
            return
        if m.T_world_tip is not None:
            srv.publish_transform(PROBE_WORLD, matrix_mm(m.T_world_tip), t)
            if calibration is not None:
                T = calibration.T_world_patient.inverse() @ m.T_world_tip
                srv.publish_transform(PROBE, ras_from_patient(T), t)
        srv.publish_string(FORCE, force_text(m.force_tip, m.contact), t)


_US_SOURCE = None  # the sim ultrasound of the render process


def _us_init(config_json: str) -> None:
    """The render process's start (a pool worker, so not :func:`~humantele.runtime.child.
    spawn`; the same rules): group signals ignored, the follower watched, below everything
    else that runs (:data:`~humantele.runtime.child.PRIORITY`)."""
    global _US_SOURCE
    ignore_group_signals()
    watch_parent(os.getppid())
    set_priority(PRIORITY["igtl_render"])
    from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

    _US_SOURCE = SimUltrasound(SimUltrasoundConfig.model_validate_json(config_json))


def _us_ping() -> bool:
    return _US_SOURCE is not None


def _us_render(snapshot: Any, t: float) -> tuple[np.ndarray, tuple[float, float] | None, float]:
    frame = _US_SOURCE.render(snapshot, t_capture=t)  # type: ignore[union-attr]
    return frame.image[:, :, 1].copy(), frame.pixel_spacing_mm, t


class ExpertIgtl(_Served):
    """The expert's OpenIGTLink output; ``tick`` is called once per expert tick.

    The received ultrasound carries no pixel size: it is taken from the sim ultrasound's
    default geometry (the follower's default source), scaled by the received width, and so is
    ``ImageToProbe``. A real scanner's figures belong in the follower's frames (not yet sent).
    """

    def __init__(self, config: IgtlConfig) -> None:
        super().__init__(config)
        self._last_us: Any = None
        self._us_width = 0
        self._us_spacing_mm = 0.0
        if self.server is not None and config.image:
            from humantele.video.scan import ScanGeometry
            from humantele.video.sim_config import SimUltrasoundConfig

            c = SimUltrasoundConfig(counter=False)
            g = ScanGeometry(c.probe, c.width, c.height, c.depth_m, c.fov_deg, c.radius_m,
                             c.aperture_m, c.beams, c.samples)  # fmt: skip
            self._us_width, self._us_spacing_mm = c.width, g.pixel_spacing_mm[0]
            self._us_origin_m = g.origin_m

    def tick(
        self,
        t: float,
        stylus_patient: Pose | None,
        state: Any | None,
        state_t: float | None,
        us: Any | None = None,
    ) -> None:
        """``stylus_patient``: the pose the expert sends (``T_patient_tip``); ``state``: the
        follower's last StateMessage (probe in the patient frame, force in the tip frame),
        sampled at ``state_t`` on this daemon's clock (its arrival, less its age if known)."""
        srv = self.server
        if not isinstance(srv, IgtlServer) or not srv.clients:
            return
        if stylus_patient is not None:
            srv.publish_transform(STYLUS, ras_from_patient(stylus_patient), t)
        if state is not None:
            if str(getattr(state.tracking, "name", state.tracking)).lower() == "tracked":
                srv.publish_transform(PROBE, ras_from_patient(state.pose), state_t or t)
            srv.publish_string(FORCE, force_text(np.asarray(state.force), state.contact), t)
        if us is not None and us is not self._last_us and self._us_width:
            self._publish_us(srv, us)
        if self.T_tip_image is not None:
            srv.publish_transform(IMAGE_TO_PROBE, self.T_tip_image, t)

    def _publish_us(self, srv: IgtlServer, us: Any) -> None:
        """A newly received ultrasound frame (:class:`humantele.media.receiver.ReceivedFrame`)."""
        width = int(us.width)
        if width <= 0:
            return
        s = self._us_spacing_mm * self._us_width / width  # the follower may send it scaled
        t = us.t_capture if us.t_capture is not None else us.t_received
        if srv.publish_image(us.frame, (s, s), t):
            self._last_us = us
            self.T_tip_image = image_to_probe(self._us_origin_m, s)
