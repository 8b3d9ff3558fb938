"""An OpenIGTLink server so 3D Slicer (OpenIGTLinkIF) or PLUS can watch a session live.

Messages are encoded by ``pyigtl`` (the Slicer community's Python OpenIGTLink); the server is
ours, on the daemon's asyncio loop, because pyigtl's own server serves one client, installs
signal handlers and busy-waits in ``send_message(wait=True)``. Any number of clients up to
``max_clients`` connect and reconnect; each gets every message while its socket keeps up. A
client that comes when all places are taken gets the place of the longest idle one (the one
that connected or last sent anything longest ago; ``stats()["evicted"]``), so idle or
forgotten connections never keep Slicer out.
A slow or stalled client never blocks the daemon: once more than ``max_queued_bytes`` wait for
it, new messages to it are dropped and counted (``stats()["dropped"]``), never queued without
bound (one message always fits an empty queue). Images are packed on a worker thread; an
image due while the last is still being packed is dropped and counted.

Frames and units (docs/slicer.md): every pose is a 4x4 in millimetres. The reference is the
patient in Slicer's RAS convention (Right, Anterior, Superior) built from the patient frame of
:mod:`humantele.follower.calibration` (x head to feet, y up = anterior for a supine patient,
z to the patient's right): R = z, A = y, S = -x. Device names (at most 20 characters):

=====================  =======================================================================
``ProbeToWorld``       follower: tracked real probe tip frame -> the tracker's world, with
                       each tracker frame the probe is tracked in, from the start
``ProbeToPatient``     tracked real probe tip frame -> patient RAS (follower: measured, once
                       calibrated; expert: as received)
``VirtProbeToPatient`` virtual probe tip frame -> patient RAS (follower: the expert's pose)
``StylusToPatient``    expert: the stylus mapped onto the patient (what it sends)
``PatientToWorld``     patient RAS -> the headset's world frame (follower, once calibrated)
``ImageToProbe``       the image's pixel frame (x along columns, y down the rows, mm) -> tip
``Image``              the ultrasound image (IMAGE, uint8, spacing in its matrix, RAS)
``ProbeForce``         STRING, JSON: force on the probe (N, tip frame), magnitude, contact
=====================  =======================================================================

Message timestamps are the sample's time on the wall clock (s since 1970), so a client on the
same machine can measure the latency from sample to screen.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from humantele.config import ConfigModel, Port
from humantele.geometry import Pose

log = logging.getLogger(__name__)

PROBE = "ProbeToPatient"
PROBE_WORLD = "ProbeToWorld"
VIRTUAL_PROBE = "VirtProbeToPatient"
STYLUS = "StylusToPatient"
PATIENT = "PatientToWorld"
IMAGE_TO_PROBE = "ImageToProbe"
IMAGE = "Image"
FORCE = "ProbeForce"

# Patient frame (x head->feet, y anterior, z to the patient's right) -> RAS: rows R, A, S.
R_RAS_PATIENT = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


class IgtlConfig(ConfigModel):
    """The OpenIGTLink server (``[follower.igtl]`` / ``[expert.igtl]``); off by default.

    ``host``: 127.0.0.1 keeps it on this machine (set 0.0.0.0 or an address to let Slicer on
    another machine connect: the stream is not encrypted or authenticated, use a trusted
    network). ``port``: 18944 is Slicer's default (0 picks a free one, printed and in the
    stats). Rates cap what is sent per device name (Hz).
    """

    enabled: bool = False
    host: str = "127.0.0.1"
    port: Port = 18944
    max_clients: int = Field(4, ge=1, le=64)
    pose_rate_hz: float = Field(60.0, gt=0.0, le=1000.0)
    image_rate_hz: float = Field(10.0, gt=0.0, le=60.0)
    image: bool = Field(True, description="send the ultrasound image (IMAGE)")
    max_queued_bytes: int = Field(2_000_000, ge=10_000, le=100_000_000)


def matrix_mm(T: Pose) -> NDArray[np.float64]:
    """4x4 of ``T`` with its translation in mm."""
    m = np.eye(4)
    m[:3, :3] = T.rotation_matrix
    m[:3, 3] = np.asarray(T.position, dtype=float) * 1e3
    return m


def ras_from_patient(T_patient_x: Pose) -> NDArray[np.float64]:
    """``T_RAS_x`` (4x4, mm) of a pose given in the patient frame (m)."""
    m = matrix_mm(T_patient_x)
    out = np.eye(4)
    out[:3, :] = R_RAS_PATIENT @ m[:3, :]
    return out


def world_from_ras(T_world_patient: Pose) -> NDArray[np.float64]:
    """``T_world_RAS`` (4x4, mm): patient RAS coordinates -> the headset world."""
    m = matrix_mm(T_world_patient)
    m[:3, :3] = m[:3, :3] @ R_RAS_PATIENT.T
    return m


def image_to_probe(origin_m: tuple[float, float], spacing_mm: float) -> NDArray[np.float64]:
    """``T_tip_image`` (4x4, mm): image frame (x along columns, y down the rows, z = x cross y,
    origin at pixel (0, 0)'s centre, mm) -> the probe tip frame, for an image in the tip's x-z
    plane whose pixel (row, col) is at tip (x0 + col s, 0, z0 + row s); see
    :class:`humantele.video.scan.ScanGeometry`. ``spacing_mm`` is carried by the IMAGE."""
    m = np.eye(4)
    m[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    m[:3, 3] = [origin_m[0] * 1e3, 0.0, origin_m[1] * 1e3]
    return m


def _wall_offset() -> float:
    return time.time() - time.monotonic()


@dataclass(eq=False)
class _Client:
    writer: asyncio.StreamWriter
    peer: str
    active_t: float = field(default_factory=time.monotonic)  # connected or last sent us bytes
    sent: int = 0
    dropped: int = 0
    bytes_in: int = 0


@dataclass
class IgtlStats:
    connections: int = 0
    refused: int = 0  # none since a newcomer evicts the idlest (key kept for stats readers)
    evicted: int = 0
    sent: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    bytes_sent: int = 0
    pack_s: float = 0.0  # time spent encoding (s, loop + worker)


class IgtlServer:
    """OpenIGTLink server on the running asyncio loop; see the module docstring.

    ``publish_*`` are called from the loop (cheap when no client is connected); ``start`` and
    ``stop`` open and close the listening socket.
    """

    def __init__(self, config: IgtlConfig | None = None) -> None:
        self.config = config or IgtlConfig()
        self.stats_ = IgtlStats()
        self.port: int | None = None
        self.error: str | None = None
        self._server: asyncio.base_events.Server | None = None
        self._clients: set[_Client] = set()
        self._last: dict[str, float] = {}
        self._image_busy = False
        self._pool: ThreadPoolExecutor | None = None
        self._wall = _wall_offset()
        self._tasks: set[asyncio.Task] = set()

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def start(self) -> bool:
        """Listen; False (logged, ``error`` set) when the port cannot be opened: the daemon
        carries on without OpenIGTLink."""
        c = self.config
        try:
            self._server = await asyncio.start_server(self._on_client, c.host, c.port)
        except OSError as exc:
            self.error = f"cannot listen on {c.host}:{c.port}: {exc.strerror or exc}"
            log.error("igtl: %s (is another program, e.g. PLUS, using the port?)", self.error)
            return False
        self.port = self._server.sockets[0].getsockname()[1]
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="humantele-igtl")
        log.info("igtl: OpenIGTLink server on %s:%d", c.host, self.port)
        return True

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            for cl in list(self._clients):
                cl.writer.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            self._clients.clear()
            self._server = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def banner(self) -> str:
        return f"OpenIGTLink on {self.config.host}:{self.port} (Slicer: OpenIGTLinkIF, client)"

    # ------------------------------------------------------------------ clients
    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = str(writer.get_extra_info("peername"))
        if len(self._clients) >= self.config.max_clients:
            self._evict_idlest()
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        client = _Client(writer, peer)
        self._clients.add(client)
        self.stats_.connections += 1
        log.info("igtl: client %s connected", peer)
        try:
            while True:  # Slicer's own messages (STATUS, GET_*) are read and not used
                data = await reader.read(65536)
                if not data:
                    break
                client.bytes_in += len(data)
                client.active_t = time.monotonic()
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            self._clients.discard(client)
            writer.close()
            if task is not None:
                self._tasks.discard(task)
            log.info("igtl: client %s left (%d sent, %d dropped)", peer, client.sent,
                     client.dropped)  # fmt: skip

    def _evict_idlest(self) -> None:
        """Close the client idle longest (connected or last sent bytes longest ago) to make
        room; its reader then ends and removes it."""
        idlest = min(self._clients, key=lambda c: c.active_t)
        self._clients.discard(idlest)
        idlest.writer.close()
        self.stats_.evicted += 1
        log.info("igtl: client %s closed: idle longest, its place taken by a new one", idlest.peer)

    def _send(self, kind: str, data: bytes) -> None:
        st = self.stats_
        limit = self.config.max_queued_bytes
        for cl in list(self._clients):
            tr = cl.writer.transport
            if tr.is_closing():
                continue
            queued = tr.get_write_buffer_size()
            if queued and queued + len(data) > limit:  # (a lone big image still goes)
                cl.dropped += 1
                st.dropped[kind] = st.dropped.get(kind, 0) + 1
                continue
            cl.writer.write(data)
            cl.sent += 1
            st.sent[kind] = st.sent.get(kind, 0) + 1
            st.bytes_sent += len(data)

    def _due(self, name: str, rate_hz: float, t: float) -> bool:
        """A client is there and ``name``'s last message is at least ``1/rate_hz`` older
        than sample time ``t`` (the samples' own clock, so a burst of late samples is not cut
        short; a time going back restarts the cap)."""
        if not self._clients:
            return False
        last = self._last.get(name)
        if last is not None and 0.0 <= t - last < 1.0 / rate_hz * 0.9:
            return False
        self._last[name] = t
        return True

    # ------------------------------------------------------------------ publishing
    def wall(self, t_monotonic: float) -> float:
        """The wall-clock time (s since 1970) of a ``time.monotonic()`` time."""
        return t_monotonic + self._wall

    def publish_transform(self, name: str, matrix: NDArray, t: float) -> bool:
        """Send TRANSFORM ``name`` (4x4, mm) sampled at monotonic ``t``; False if not sent
        (no client, rate cap, or not finite)."""
        if not self._due(name, self.config.pose_rate_hz, t):
            return False
        m = np.asarray(matrix, dtype=float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            self.stats_.dropped["bad_pose"] = self.stats_.dropped.get("bad_pose", 0) + 1
            return False
        import pyigtl

        t0 = time.perf_counter()
        data = pyigtl.TransformMessage(m, timestamp=self.wall(t), device_name=name).pack()
        self.stats_.pack_s += time.perf_counter() - t0
        self._send("transform", data)
        return True

    def publish_string(self, name: str, text: str, t: float, rate_hz: float | None = None) -> bool:
        """Send STRING ``name`` (rate-capped like the poses unless ``rate_hz``)."""
        if not self._due(name, rate_hz or self.config.pose_rate_hz, t):
            return False
        import pyigtl

        data = pyigtl.StringMessage(text, timestamp=self.wall(t), device_name=name).pack()
        self._send("string", data)
        return True

    def publish_image(
        self, image: NDArray, spacing_mm: tuple[float, float], t: float, name: str = IMAGE
    ) -> bool:
        """Send IMAGE ``name``: a (H, W) or (H, W, 3) uint8 frame (BGR: its green channel is
        sent; the sim and most scanners are grey) or a decoded ``av.VideoFrame`` (its luma),
        pixel size (row, col) mm, captured at monotonic ``t``. Packed on the worker thread;
        dropped (counted) while one is packing."""
        rate = self.config.image_rate_hz
        if not self.config.image or not self._due(name, rate, t):
            return False
        if self._image_busy or self._pool is None:
            self.stats_.dropped["image_busy"] = self.stats_.dropped.get("image_busy", 0) + 1
            return False
        if not all(np.isfinite(spacing_mm)):
            self.stats_.dropped["bad_image"] = self.stats_.dropped.get("bad_image", 0) + 1
            return False
        if isinstance(image, np.ndarray):
            img = image[:, :, 1] if image.ndim == 3 else image
            if img.ndim != 2 or img.dtype != np.uint8:
                self.stats_.dropped["bad_image"] = self.stats_.dropped.get("bad_image", 0) + 1
                return False
            image = np.ascontiguousarray(img)
        self._image_busy = True
        loop = asyncio.get_running_loop()
        fut = loop.run_in_executor(self._pool, _pack_image, image, spacing_mm, self.wall(t), name)
        fut.add_done_callback(self._image_packed)
        return True

    def _image_packed(self, fut: asyncio.Future) -> None:
        self._image_busy = False
        if fut.cancelled():
            return
        try:
            data, dt = fut.result()
        except Exception:  # noqa: BLE001 - a bad frame must not stop the stream
            self.stats_.dropped["image_error"] = self.stats_.dropped.get("image_error", 0) + 1
            log.exception("igtl: packing an image failed (counted)")
            return
        self.stats_.pack_s += dt
        self._send("image", data)

    def stats(self) -> dict[str, Any]:
        s = self.stats_
        return {
            "host": self.config.host,
            "port": self.port,
            "error": self.error,
            "clients": len(self._clients),
            "connections": s.connections,
            "refused": s.refused,
            "evicted": s.evicted,
            "sent": dict(s.sent),
            "dropped": dict(s.dropped),
            "bytes_sent": s.bytes_sent,
            "pack_s": round(s.pack_s, 4),
        }


def _pack_image(img: Any, spacing_mm: tuple[float, float], t_wall: float, name: str):
    import pyigtl

    t0 = time.perf_counter()
    if not isinstance(img, np.ndarray):  # a decoded av.VideoFrame: its luma, here off the loop
        img = np.ascontiguousarray(img.to_ndarray(format="gray"), dtype=np.uint8)
    ijk = np.diag([float(spacing_mm[1]), float(spacing_mm[0]), 1.0, 1.0])  # i: columns, j: rows
    msg = pyigtl.ImageMessage(
        img[np.newaxis], ijk_to_world_matrix=ijk, world_coordinate_system="ras",
        timestamp=t_wall, device_name=name,
    )  # fmt: skip
    return msg.pack(), time.perf_counter() - t0


def force_text(force_tip: NDArray | None, contact: bool) -> str:
    """The ``ProbeForce`` STRING: JSON with the force (N, tip frame), magnitude and contact."""
    f = [0.0, 0.0, 0.0] if force_tip is None else [round(float(v), 4) for v in force_tip]
    mag = float(np.linalg.norm(f))
    return json.dumps({"force_tip_n": f, "magnitude_n": round(mag, 4), "contact": bool(contact)})
