"""HoloLens 2 research-mode AHAT frames and rig poses over the network, from the hl2ss app.

hl2ss (github.com/jdibenes/hl2ss) runs a TCP server on the headset; the AHAT (short-throw
depth + active brightness) stream is port 3804. The wire format and the matrix conventions
are in :mod:`humantele.tracking.hl2ss_protocol` (checked against hl2ss's own sources).

This backend asks for depth SAME with AB RAW (1 MiB a frame, ~377 Mbit/s at 45 Hz) or AB
H.264/H.265 at a chosen bitrate (``ab_profile``, ``bitrate``; decoded as hl2ss's own client
does, :mod:`humantele.tracking.hl2ss_codec`), always with a bitrate > 0 (the app refuses 0
even for RAW) and, by default, mode 1: every frame carries the rig's pose in the app's world.
Depth ZDEPTH is refused (its decoder, hl2ss's pyzdepth, is not on PyPI). A link slower than
the stream makes the app queue frames without bound (docs/hololens.md): 3 frames in a row
each later than ``max_backlog_s`` behind the connection's quickest drop the connection, which
empties that queue (counted as "backlog"; :mod:`humantele.tracking.hl2ss_backlog`). H.26x
frames are un-biased for the tracker (:func:`~humantele.tracking.hl2ss_codec.unbias_h26x`)
and marked ``ab_paired``.

Per frame (:class:`TrackingFrame`): ``T_world_rig`` = the rig pose (converted from hl2ss's
row-vector matrix), ``T_world_camera = T_world_rig @ T_rig_camera`` with the AHAT extrinsics
from hl2ss's calibration (downloaded at ``open`` over mode 2, or read from the file
``humantele devices hl2ss-calibration`` saved). "world" is hl2ss's world (the headset's
spatial coordinate system at app start, y up, m), not WebXR's ``local-floor``. The camera
frame is OpenCV's (x right, y down, z forward), as the tracker's ``T_camera_probe``. With a
calibration the raw (wide-angle) images are undistorted with its maps to the pinhole image
of its K, which become the frames' intrinsics.

A frame without a usable pose (mode 0; a pose of zeros: the headset was not located; not
finite; not rigid) is still returned, with ``T_world_camera``/``T_world_rig`` None, and
counted in ``no_pose`` by reason. A packet that is not a RAW AHAT frame is dropped and counted
in ``dropped`` ("size": its size fields disagree; "encoding": not RAW); bytes out of step
(an impossible payload size) drop the connection ("out_of_step"). ``open`` failing is
:class:`FrameSourceUnavailable`.

Stalls (issue 30 §2). One ``read`` takes at most ``read_timeout_s`` in all (a deadline for the
whole call, not per receive: a server trickling a byte every 0.3 s held one read for 12.7 s
when each receive had its own timeout); what came of a packet stays for the next read. A
connection that gave no complete frame for ``stall_s`` (a Wi-Fi drop or a sleeping headset
that does not close the socket; or a trickle) is a stall: counted (``stalls``,
``dropped["stalled"]``), the socket closed (hl2ss serves one client per port: the app must
see this client leave before it accepts the next) and the stream reconnected, as after a lost
connection, with back-off: the first try ``retry_s`` later, then doubled per failure up to
``retry_max_s``, back to ``retry_s`` after a frame. A reconnect is bounded by the read's
deadline too, and a read ends by the time its connection would count as stalled (the stall is
found ``stall_s`` after the last packet, not up to a read later). :attr:`stalled` is True
from ``stall_s`` without a packet (connected or not) to the next packet: the follower says
"headset stream stalled" meanwhile.
"""

from __future__ import annotations

import contextlib
import select
import socket
import time
from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from humantele.config import ConfigModel, RemotePort
from humantele.geometry import Pose
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.frames import FrameSource, FrameSourceUnavailable, TrackingFrame
from humantele.tracking.hl2ss_backlog import BacklogMonitor
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration, download_ahat_calibration
from humantele.tracking.hl2ss_codec import (
    PROFILE_NAMES,
    AhatDecoder,
    default_bitrate,
    default_gop_size,
    unbias_h26x,
)
from humantele.tracking.hl2ss_protocol import (  # noqa: F401  (re-exported for callers)
    AHAT_HEIGHT,
    AHAT_PORT,
    AHAT_WIDTH,
    DEFAULT_RAW_BITRATE,
    DEPTH_PROFILE_SAME,
    GOP_SIZE_OPTION,
    HEADER,
    MAX_PAYLOAD_SIZE,
    MODE_FRAMES_POSE,
    POSE_BYTES,
    RAW_PAYLOAD_SIZE,
    VIDEO_PROFILE_RAW,
    AhatConfiguration,
    PacketError,
    decode_ahat_payload,
    encode_ahat_packet,
    frame_poses,
    pose_from_hl2ss,
)


def ahat_configuration(mode: int = MODE_FRAMES_POSE, divisor: int = 1,
                       bitrate: int = DEFAULT_RAW_BITRATE, profile_ab: int = VIDEO_PROFILE_RAW,
                       gop_size: int | None = None) -> bytes:  # fmt: skip
    """The configuration bytes this client sends: depth SAME, the AB profile (RAW or H.26x),
    default level, a bitrate > 0 and hl2ss_lnm's default option (GOP size: 1 for RAW, the
    frame rate for H.26x)."""
    gop = default_gop_size(profile_ab) if gop_size is None else gop_size
    return AhatConfiguration(mode=mode, divisor=divisor, profile_z=DEPTH_PROFILE_SAME,
                             profile_ab=profile_ab, bitrate=bitrate,
                             options={GOP_SIZE_OPTION: gop}).pack()  # fmt: skip


class Hl2ssFrameConfig(ConfigModel):
    """The ``hl2ss`` tracker backend: the headset's address, the stream's settings and where
    the AHAT calibration (intrinsics, undistortion, extrinsics) comes from."""

    backend: Literal["hl2ss"] = "hl2ss"
    host: str = "192.168.1.7"
    port: RemotePort = AHAT_PORT
    mode: Literal[0, 1] = Field(1, description="1: packets carry the rig pose (the follower "
                                "needs it); 0: frames only")  # fmt: skip
    divisor: int = Field(1, ge=1, le=255, description="send every n-th frame (45 Hz / n)")
    depth_profile: Literal["same", "zdepth"] = Field(
        "same", description="same: depth in the AB stream's frame (RAW: as is; H.26x: 4 mm "
        "steps); zdepth (lossless) is refused: its decoder is not on PyPI")  # fmt: skip
    ab_profile: Literal["raw", "h264_base", "h264_main", "h264_high", "h265_main"] = Field(
        "h264_high", description="raw: 1 MiB a frame, ~377 Mbit/s at 45 Hz (needs a wired "
        "link for 45 Hz); H.26x: lossy, at `bitrate` (docs/hololens.md: the chart that picked "
        "H.264)")  # fmt: skip
    bitrate: int | None = Field(None, gt=0, le=0xFFFFFFFF,
                                description="bit/s; None: hl2ss's default for the profile "
                                "(H.264 37.7 Mbit/s, H.265 18.9, RAW 1.5 G)")  # fmt: skip
    gop_size: int | None = Field(None, ge=1, le=0xFFFF,
                                 description="H.26x frames per key frame; None: hl2ss's "
                                 "default (45: one a second)")  # fmt: skip
    max_backlog_s: float = Field(
        0.5, gt=0, le=60, description="3 frames in a row this much later than the quickest "
        "(the headset queues what a slow link cannot carry) drop the connection, which "
        "empties the queue")  # fmt: skip
    calibration_file: str | None = Field(
        None,
        description="JSON saved by `humantele devices hl2ss-calibration` (relative: "
        "from the current directory); None: download it from the headset at open",
    )
    download_calibration: bool = Field(
        True, description="without calibration_file: download it at open (about 4 MB)"
    )
    intrinsics: CameraIntrinsics = Field(
        default_factory=CameraIntrinsics,
        description="used only without a calibration (then frames are not undistorted)",
    )
    newest: bool = Field(
        True,
        description="a reader that fell behind skips to the newest frame (counted as "
        "stale); false: every frame in order (replays read whole)",
    )
    connect_timeout_s: float = Field(3.0, gt=0, le=60)
    read_timeout_s: float = Field(1.0, gt=0, le=60, description="s one read takes at most")
    stall_s: float = Field(2.0, gt=0, le=60, description="s without a complete frame on a "
                           "connection: stalled, dropped and reconnected")  # fmt: skip
    retry_s: float = Field(1.0, ge=0, le=60, description="first wait before a reconnect (s)")
    retry_max_s: float = Field(4.0, ge=0, le=300, description="the back-off's cap (s)")

    @field_validator("depth_profile")
    @classmethod
    def _no_zdepth(cls, v: str) -> str:
        if v == "zdepth":
            raise ValueError(
                "zdepth needs hl2ss's pyzdepth decoder, which is not on PyPI (it is built from "
                "hl2ss's extensions/pyzdepth): use same, with ab_profile raw or H.26x"
            )
        return v

    @property
    def profile_ab(self) -> int:
        """hl2ss's AB profile number (0-3 H.26x, 255 RAW)."""
        return PROFILE_NAMES[self.ab_profile]

    @property
    def stream_bitrate(self) -> int:
        """The bitrate asked for: ``bitrate`` or hl2ss_lnm's default for the profile."""
        return self.bitrate or default_bitrate(self.profile_ab, self.divisor)

    @model_validator(mode="after")
    def _pose_needs_extrinsics(self) -> Hl2ssFrameConfig:
        if self.mode == 1 and self.calibration_file is None and not self.download_calibration:
            raise ValueError(
                "hl2ss mode 1 places the camera with the AHAT extrinsics: set "
                "calibration_file or download_calibration = true (or mode = 0)"
            )
        return self


class Hl2ssFrameSource(FrameSource):
    """AHAT frames from an hl2ss app. ``dropped`` counts unusable packets and losses by reason;
    ``no_pose`` counts frames returned without a pose, by reason; ``stalls`` the stalls found
    and ``reconnects`` the connections made after the first. Not thread-safe: one reader.
    ``last_pose`` is the last rig pose matrix as hl2ss sent it (row-vector, translation in
    the last row); ``T_rig_camera`` the AHAT camera in the rig (None without calibration).
    ``clock``: what stalls and back-off are timed on (s; tests drive it by hand); socket
    deadlines are always on ``time.monotonic``."""

    name = "hl2ss AHAT"
    unbias_h26x = True  # H.26x frames: take back the biases hl2ss's decode leaves (a recorder
    # keeps the frames as hl2ss's client decodes them)

    def __init__(
        self, config: Hl2ssFrameConfig | None = None, clock: Callable[[], float] = time.monotonic
    ):
        self.config = c = config or Hl2ssFrameConfig()
        self.clock = clock
        self.intrinsics = c.intrinsics
        if (c.intrinsics.width, c.intrinsics.height) != (AHAT_WIDTH, AHAT_HEIGHT):
            raise ValueError("hl2ss: AHAT frames are 512 x 512; set intrinsics to that size")
        self.calibration: Hl2ssAhatCalibration | None = None
        self.T_rig_camera: Pose | None = None
        self._undistort = False
        self.dropped: dict[str, int] = {}
        self.no_pose: dict[str, int] = {}
        self.received = 0
        self.last_timestamp: int | None = None
        self.last_sensor_ticks: int | None = None
        self.last_pose: np.ndarray | None = None
        self._sock: socket.socket | None = None
        self._buf = bytearray()
        self._seq = 0
        self._next_retry = 0.0
        self._backoff_s = c.retry_s
        self.stalls = 0
        self.reconnects = 0
        self._connections = 0
        self._last_packet_at: float | None = None  # the clock's time of the last whole packet
        self._opened_at: float | None = None  # the first connection
        self._waiting_since = clock()  # the last packet, or the connection's start if later
        self._decoder = AhatDecoder(DEPTH_PROFILE_SAME, c.profile_ab)
        self.backlog = BacklogMonitor(c.max_backlog_s)

    # --- opening --------------------------------------------------------------------------
    def open(self) -> None:
        """Get the calibration (file or download), then connect the stream."""
        c = self.config
        if self.calibration is None and (c.calibration_file or c.download_calibration):
            self._set_calibration(self._get_calibration())
        if self._sock is None:
            self._connect()

    def _get_calibration(self) -> Hl2ssAhatCalibration:
        c = self.config
        if c.calibration_file:
            try:
                return Hl2ssAhatCalibration.load(c.calibration_file)
            except ValueError as exc:
                raise FrameSourceUnavailable(
                    f"hl2ss: {exc}; save it again with `humantele devices hl2ss-calibration "
                    f"--host {c.host} --out FILE`") from exc  # fmt: skip
        try:
            return download_ahat_calibration(c.host, c.port, max(c.connect_timeout_s, 10.0))
        except (OSError, ValueError) as exc:
            raise FrameSourceUnavailable(
                f"hl2ss: cannot reach the HoloLens 2 AHAT stream at {c.host}:{c.port} for its "
                f"calibration ({exc}); is the hl2ss app running on the headset, and research "
                "mode enabled? (or set calibration_file)") from exc  # fmt: skip

    def _set_calibration(self, cal: Hl2ssAhatCalibration) -> None:
        self.calibration = cal
        self.T_rig_camera = cal.T_rig_camera()
        self.intrinsics = cal.intrinsics()
        self._undistort = not cal.is_identity_map()

    def _connect(self, timeout_s: float | None = None) -> None:
        """Connect and send the configuration, within ``timeout_s`` (default
        ``connect_timeout_s``)."""
        c = self.config
        timeout = c.connect_timeout_s if timeout_s is None else timeout_s
        try:
            sock = socket.create_connection((c.host, c.port), timeout=timeout)
        except OSError as exc:
            raise FrameSourceUnavailable(
                f"hl2ss: cannot reach the HoloLens 2 AHAT stream at {c.host}:{c.port} ({exc}); "
                "is the hl2ss app running on the headset, and research mode enabled?"
            ) from exc
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.sendall(ahat_configuration(c.mode, c.divisor, c.stream_bitrate,
                                            c.profile_ab, c.gop_size))  # fmt: skip
        except OSError as exc:
            sock.close()
            raise FrameSourceUnavailable(f"hl2ss: {c.host}:{c.port} left ({exc})") from exc
        if self._connections:
            self.reconnects += 1
        else:
            self._opened_at = self.clock()
        self._connections += 1
        self._sock, self._buf = sock, bytearray()
        self._waiting_since = self.clock()
        self._decoder = AhatDecoder(DEPTH_PROFILE_SAME, c.profile_ab)  # a new stream

    # --- reading --------------------------------------------------------------------------
    def _count(self, counter: dict[str, int], reason: str) -> None:
        counter[reason] = counter.get(reason, 0) + 1

    def _fill(self, n: int, deadline: float) -> None:
        """Receive until the buffer holds ``n`` bytes; TimeoutError at ``deadline``
        (``time.monotonic``), what came staying in the buffer."""
        assert self._sock is not None
        while len(self._buf) < n:
            left = deadline - time.monotonic()
            if left <= 0 and not select.select([self._sock], [], [], 0)[0]:
                raise TimeoutError("no complete packet by the read's deadline")
            self._sock.settimeout(max(left, 0.001))
            chunk = self._sock.recv(max(65536, n - len(self._buf)))
            if not chunk:
                raise ConnectionError("closed by the headset")
            self._buf.extend(chunk)

    @property
    def stalled(self) -> bool:
        """No packet for ``stall_s`` (connected or not), until the next packet (False before
        the first connection)."""
        since = self._last_packet_at if self._last_packet_at is not None else self._opened_at
        return since is not None and self.clock() - since >= self.config.stall_s

    def stats(self) -> dict:
        """Counters for the follower's stats: frames, losses and no-pose frames by reason,
        stalls, reconnects, and whether the stream is stalled now."""
        return {"received": self.received, "dropped": dict(self.dropped),
                "no_pose": dict(self.no_pose), "stalls": self.stalls,
                "reconnects": self.reconnects, "stalled": self.stalled}  # fmt: skip

    def read(self, t: float | None = None) -> TrackingFrame | None:
        """The next AHAT frame (stamped ``t``, default its arrival on ``time.monotonic``), or
        None when none could be had by the read's deadline (``read_timeout_s``; counted in
        ``dropped``)."""
        deadline = time.monotonic() + self.config.read_timeout_s
        if self._sock is None:
            if self.clock() < self._next_retry:
                return None
            try:
                self._connect(min(self.config.connect_timeout_s, self.config.read_timeout_s))
            except FrameSourceUnavailable:
                self._count(self.dropped, "reconnect_failed")
                self._back_off()
                return None
        # a read ends when the connection would be stalled, so the stall is found on time
        to_stall = self._waiting_since + self.config.stall_s - self.clock()
        deadline = min(deadline, time.monotonic() + max(0.0, to_stall))
        pose_bytes = POSE_BYTES if self.config.mode == MODE_FRAMES_POSE else 0
        try:
            self._fill(HEADER.size, deadline)
            ts, size = HEADER.unpack_from(self._buf, 0)
            if not 16 <= size <= MAX_PAYLOAD_SIZE:  # not a header: the bytes are out of step
                self._count(self.dropped, "out_of_step")
                self._drop_connection()
                return None
            end = HEADER.size + size + pose_bytes
            self._fill(end, deadline)  # a timeout here keeps the partial packet for the next read
        except TimeoutError:
            if self.clock() - self._waiting_since >= self.config.stall_s:
                self.stalls += 1  # no frame, no close: a stalled stream (or a trickle)
                self._count(self.dropped, "stalled")
                self._drop_connection()
            else:
                self._count(self.dropped, "timeout")
            return None
        except (ConnectionError, OSError):
            self._count(self.dropped, "disconnected")
            self._drop_connection()
            return None
        if self.config.newest:
            end = self._newest(end, pose_bytes)
        packet = bytes(self._buf[:end])
        size = len(packet) - HEADER.size - pose_bytes
        ts = HEADER.unpack_from(packet, 0)[0]
        del self._buf[:end]
        # a whole packet came: the link is not stalled
        self._waiting_since = self._last_packet_at = self.clock()
        try:
            p = self._decoder.decode(memoryview(packet)[HEADER.size : HEADER.size + size])
        except PacketError as exc:
            self._count(self.dropped, exc.reason)
            return None
        self.last_timestamp, self.last_sensor_ticks = ts, p.sensor_ticks
        if pose_bytes:
            self.last_pose = np.frombuffer(packet, "<f4", 16, HEADER.size + size).reshape(4, 4)
        matrix = self.last_pose if pose_bytes else None
        T_world_rig, T_world_camera = frame_poses(matrix, self.T_rig_camera, self.no_pose)
        depth, ab = p.depth_mm, p.ab
        paired = self._decoder.profile_ab != VIDEO_PROFILE_RAW
        intrinsics = self.intrinsics
        if paired and self.unbias_h26x:  # see hl2ss_codec.unbias_h26x
            depth, intrinsics = unbias_h26x(depth, intrinsics, self._undistort)
        if self._undistort and self.calibration is not None:
            depth, ab = self.calibration.undistort(depth, ab, 0.5 if paired else 0.0)
        self.received += 1
        self._seq += 1
        self._backoff_s = self.config.retry_s
        arrival = time.monotonic()
        # the headset queues what the link cannot carry: dropping the connection empties it
        if self.config.newest and self.backlog.late(ts * 1e-7, arrival):
            self._count(self.dropped, "backlog")
            self._drop_connection()
            self._next_retry = 0.0  # at once: the link is up, only the queue was long
        return TrackingFrame(
            t=arrival if t is None else t,
            ir=ab,
            depth_mm=depth,
            intrinsics=intrinsics,
            seq=self._seq,
            T_world_camera=T_world_camera,
            T_world_rig=T_world_rig,
            device_time_s=ts * 1e-7,  # hl2ss: 100 ns ticks
            ab_paired=paired and self.unbias_h26x,
        )

    def _newest(self, end: int, pose_bytes: int) -> int:
        """A reader slower than the headset would fall ever further behind (TCP keeps every
        frame): take what has already arrived and skip to the newest complete packet, the
        older ones counted as ``stale``. Returns the end of that packet; the buffer starts
        at it."""
        assert self._sock is not None
        with contextlib.suppress(OSError):  # a lost connection: the next read says so
            while len(self._buf) < end + 8 * (MAX_PAYLOAD_SIZE + HEADER.size + POSE_BYTES):
                if not select.select([self._sock], [], [], 0)[0]:
                    break  # nothing more has arrived
                chunk = self._sock.recv(1 << 20)
                if not chunk:
                    break
                self._buf.extend(chunk)
        while len(self._buf) >= end + HEADER.size:
            size = HEADER.unpack_from(self._buf, end)[1]
            nxt = end + HEADER.size + size + pose_bytes
            if not 16 <= size <= MAX_PAYLOAD_SIZE or len(self._buf) < nxt:
                break  # out of step (the next read says so) or not all there yet
            if self._decoder.profile_ab != VIDEO_PROFILE_RAW:  # later frames refer to it
                size_old = HEADER.unpack_from(self._buf, 0)[1]
                self._decoder.skip(bytes(self._buf[HEADER.size : HEADER.size + size_old]))
            del self._buf[:end]
            self._count(self.dropped, "stale")
            end = nxt - end
        return end

    def _drop_connection(self) -> None:
        """Close the socket (the app then accepts the next client) and retry after back-off."""
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
        self._sock = None
        self._buf = bytearray()
        self._back_off()

    def _back_off(self) -> None:
        """The next connection try after the back-off, which doubles (up to ``retry_max_s``)
        until a frame comes."""
        self._next_retry = self.clock() + self._backoff_s
        cap = max(self.config.retry_max_s, self.config.retry_s)
        self._backoff_s = min(cap, max(self._backoff_s * 2.0, 0.0))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
