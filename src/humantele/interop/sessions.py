"""What each daemon serves over OpenIGTLink (:mod:`.igtl`): small adapters the daemons call
once per tick, so the daemons hold one line per hook.

Follower: ``ProbeToPatient`` (measured), ``VirtProbeToPatient`` (the expert's pose),
``PatientToWorld``, ``ProbeForce`` and, with ``image``, the ultrasound ``Image`` and
``ImageToProbe``. Until the follower streams its own ultrasound track the image comes from a
sim ultrasound source (:class:`humantele.video.sim_ultrasound.SimUltrasound`) run on a thread
at ``image_rate_hz`` on the follower's simulated scene; ``on_us_frame`` is the entry for a
daemon that has frames of its own.
Expert: ``StylusToPatient`` (what it sends), ``ProbeToPatient`` and ``ProbeForce`` (as
received), and the ultrasound ``Image`` when it receives frames (``on_us_frame``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

import numpy as np

from humantele.geometry import Pose
from humantele.interop.igtl import (
    FORCE,
    IMAGE_TO_PROBE,
    PATIENT,
    PROBE,
    STYLUS,
    VIRTUAL_PROBE,
    IgtlConfig,
    IgtlServer,
    force_text,
    image_to_probe,
    ras_from_patient,
    world_from_ras,
)

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

    def on_us_frame(self, frame: Any, T_tip_image: np.ndarray | None = None) -> None:
        """An ultrasound frame (:class:`humantele.video.base.VideoFrame`), on the loop."""
        if not isinstance(self.server, IgtlServer) or frame.pixel_spacing_mm is None:
            return
        if T_tip_image is not None:
            self.T_tip_image = T_tip_image
        self.server.publish_image(frame.image, frame.pixel_spacing_mm, frame.t_capture)

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

    def __init__(self, config: IgtlConfig, patient: Any | None = None) -> None:
        super().__init__(config)
        self._scene = None  # the latest SceneSnapshot for the sim ultrasound
        self._patient = patient  # an Ellipsoid: the true patient the sim ultrasound images
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._source = None

    async def start(self) -> None:
        await super().start()
        if isinstance(self.server, IgtlServer) and self.config.image:
            self._start_sim_ultrasound(asyncio.get_running_loop())

    async def stop(self) -> None:
        self._stop.set()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 5.0)
        await super().stop()

    def _start_sim_ultrasound(self, loop: asyncio.AbstractEventLoop) -> None:
        from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

        src = SimUltrasound(
            SimUltrasoundConfig(fps=self.config.image_rate_hz, counter=False),
            scene=lambda: self._scene,
        )
        g = src.geometry
        self.T_tip_image = image_to_probe(g.origin_m, g.pixel_spacing_mm[0])
        self._source = src

        def run() -> None:
            src.open()
            try:
                while not self._stop.is_set():
                    frame = src.read()
                    if self._scene is None:
                        continue
                    loop.call_soon_threadsafe(self.on_us_frame, frame)
            except RuntimeError:  # the loop closed under us: the daemon is stopping
                pass
            finally:
                src.close()

        self._reader = threading.Thread(target=run, name="humantele-igtl-us", daemon=True)
        self._reader.start()

    def tick(
        self,
        t: float,
        calibration: Any | None,
        virtual_patient: Pose | None,
        true_tip: Pose | None = None,
        force_n: float = 0.0,
    ) -> None:
        """Once per follower tick: the virtual probe (``T_patient_tip`` of the expert's pose),
        the patient frame, ``ImageToProbe``; ``true_tip``/``force_n`` (the sim world) feed the
        sim ultrasound."""
        srv = self.server
        if srv is None:
            return
        if self._source is not None and self._patient is not None:
            from humantele.video.scene import SceneSnapshot

            self._scene = SceneSnapshot(t, self._patient, true_tip, float(force_n), None)
        if not isinstance(srv, IgtlServer) or not srv.clients:
            return
        if calibration is not None:
            srv.publish_transform(PATIENT, world_from_ras(calibration.T_world_patient), t)
        if virtual_patient is not None:
            srv.publish_transform(VIRTUAL_PROBE, ras_from_patient(virtual_patient), t)
        if self.T_tip_image is not None:
            srv.publish_transform(IMAGE_TO_PROBE, self.T_tip_image, t)

    def on_measurement(self, t: float, calibration: Any | None, m: Any) -> None:
        """One tracker frame measured at ``t``: ``ProbeToPatient`` (once calibrated, when
        tracked) and ``ProbeForce``, stamped with the frame's time."""
        srv = self.server
        if not isinstance(srv, IgtlServer) or not srv.clients:
            return
        if calibration is not None and m.T_world_tip is not None:
            T = calibration.T_world_patient.inverse() @ m.T_world_tip
            srv.publish_transform(PROBE, ras_from_patient(T), t)
        srv.publish_string(FORCE, force_text(m.force_tip, m.contact), t)


class ExpertIgtl(_Served):
    """The expert's OpenIGTLink output; ``tick`` is called once per expert tick."""

    def tick(
        self, t: float, stylus_patient: Pose | None, state: Any | None, state_t: float | None
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
        if self.T_tip_image is not None:
            srv.publish_transform(IMAGE_TO_PROBE, self.T_tip_image, t)
