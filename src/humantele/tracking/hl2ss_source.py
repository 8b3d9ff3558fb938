"""HoloLens 2 research-mode AHAT frames over the network, as the open hl2ss server sends them.

hl2ss (github.com/jdibenes/hl2ss, the usual way to get research-mode streams off a HoloLens 2)
runs a TCP server on the headset; the AHAT (short-throw depth + active brightness) stream is
port 3804. Wire format, as in hl2ss's ``viewer/hl2ss.py`` (1.0.3x):

- the client sends its configuration: ``<B`` mode (0: frames; 1: frames + rig pose),
  ``<B`` divisor, ``<B`` depth profile (0: SAME as AB), ``<BBI`` AB profile (0xFF: RAW),
  level, bitrate, ``<B`` number of encoder options (then that many ``<QQ`` key/value);
- the server then sends packets: ``<QI`` timestamp (100 ns ticks) and payload size, the
  payload, and in mode 1 a 4x4 float32 pose (64 bytes);
- a RAW/SAME AHAT payload: 8 header bytes (unused here), depth (512 x 512 uint16, mm), active
  brightness (512 x 512 uint16), then 8 bytes of sensor ticks (uint64).

This backend asks for RAW (no H.264/zdepth decoding: no codec dependency, no compression
artefacts on the marker blobs) and turns each packet into a :class:`TrackingFrame`. A packet
of the wrong size is dropped and counted; a lost connection is counted and retried on the next
``read`` (at most once per ``retry_s``). ``open`` failing is :class:`FrameSourceUnavailable`.
"""

from __future__ import annotations

import socket
import struct
import time
from typing import Literal

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.frames import FrameSourceUnavailable, TrackingFrame

AHAT_PORT = 3804
AHAT_WIDTH = AHAT_HEIGHT = 512
AHAT_PIXELS = AHAT_WIDTH * AHAT_HEIGHT
DEPTH_PROFILE_SAME = 0
VIDEO_PROFILE_RAW = 0xFF
HEADER = struct.Struct("<QI")
PAYLOAD_BASE = 8  # bytes before the depth image
PAYLOAD_TAIL = 8  # sensor ticks after the AB image
RAW_PAYLOAD_SIZE = PAYLOAD_BASE + 4 * AHAT_PIXELS + PAYLOAD_TAIL


def ahat_configuration(mode: int = 0) -> bytes:
    """The configuration bytes a client sends on connecting: RAW depth and AB, no options."""
    return struct.pack("<BBBBBIB", mode, 1, DEPTH_PROFILE_SAME, VIDEO_PROFILE_RAW, 0xFF, 0, 0)


def encode_ahat_packet(
    timestamp: int, depth_mm: np.ndarray, ab: np.ndarray, sensor_ticks: int = 0,
    pose: np.ndarray | None = None,
) -> bytes:  # fmt: skip
    """One packet as the hl2ss server sends it (used by the tests' replay server)."""
    payload = (
        bytes(PAYLOAD_BASE)
        + np.ascontiguousarray(depth_mm, dtype="<u2").tobytes()
        + np.ascontiguousarray(ab, dtype="<u2").tobytes()
        + struct.pack("<Q", sensor_ticks)
    )
    tail = b"" if pose is None else np.asarray(pose, dtype="<f4").tobytes()
    return HEADER.pack(timestamp, len(payload)) + payload + tail


class Hl2ssFrameConfig(ConfigModel):
    """The ``hl2ss`` tracker backend: the headset's address and the AHAT camera's intrinsics
    (from hl2ss's calibration download, or the AHAT-like defaults)."""

    backend: Literal["hl2ss"] = "hl2ss"
    host: str = "192.168.1.7"
    port: int = Field(AHAT_PORT, ge=1, le=65535)
    intrinsics: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    mode: Literal[0, 1] = Field(0, description="1: packets also carry the rig pose")
    connect_timeout_s: float = Field(3.0, gt=0, le=60)
    read_timeout_s: float = Field(1.0, gt=0, le=60)
    retry_s: float = Field(1.0, ge=0, le=60)


class Hl2ssFrameSource:
    """AHAT frames from an hl2ss server; ``dropped`` counts unusable packets and losses by
    reason ("size", "timeout", "disconnected"). Not thread-safe: one reader thread."""

    def __init__(self, config: Hl2ssFrameConfig | None = None):
        self.config = c = config or Hl2ssFrameConfig()
        self.intrinsics = c.intrinsics
        if (c.intrinsics.width, c.intrinsics.height) != (AHAT_WIDTH, AHAT_HEIGHT):
            raise ValueError("hl2ss: AHAT frames are 512 x 512; set intrinsics to that size")
        self.dropped: dict[str, int] = {}
        self.received = 0
        self.last_timestamp: int | None = None
        self.last_pose: np.ndarray | None = None
        self._sock: socket.socket | None = None
        self._buf = bytearray()
        self._seq = 0
        self._next_retry = 0.0
        self._connect()

    def _connect(self) -> None:
        c = self.config
        try:
            sock = socket.create_connection((c.host, c.port), timeout=c.connect_timeout_s)
            sock.settimeout(c.read_timeout_s)
            sock.sendall(ahat_configuration(c.mode))
        except OSError as exc:
            raise FrameSourceUnavailable(
                f"hl2ss: cannot reach the HoloLens 2 AHAT stream at {c.host}:{c.port} ({exc}); "
                "is the hl2ss app running on the headset, and research mode enabled?"
            ) from exc
        self._sock, self._buf = sock, bytearray()

    def _count(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def _recv_exactly(self, n: int) -> bytes:
        assert self._sock is not None
        while len(self._buf) < n:
            chunk = self._sock.recv(max(65536, n - len(self._buf)))
            if not chunk:
                raise ConnectionError("closed by the headset")
            self._buf.extend(chunk)
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def read(self, t: float | None = None) -> TrackingFrame | None:
        """The next AHAT frame (stamped ``t``, default its arrival on ``time.monotonic``), or
        None when none could be had now (counted)."""
        if self._sock is None:
            if time.monotonic() < self._next_retry:
                return None
            try:
                self._connect()
            except FrameSourceUnavailable:
                self._next_retry = time.monotonic() + self.config.retry_s
                self._count("reconnect_failed")
                return None
        try:
            ts, size = HEADER.unpack(self._recv_exactly(HEADER.size))
            if size > 8 * RAW_PAYLOAD_SIZE:  # garbage: the stream is out of step
                raise ConnectionError(f"payload size {size} out of step")
            payload = self._recv_exactly(size)
            pose = self._recv_exactly(64) if self.config.mode == 1 else None
        except TimeoutError:
            self._count("timeout")
            return None
        except (ConnectionError, OSError):
            self._count("disconnected")
            self._drop_connection()
            return None
        if size != RAW_PAYLOAD_SIZE:
            self._count("size")  # e.g. an encoded (H.264/zdepth) stream: not what we asked for
            return None
        depth = np.frombuffer(payload, "<u2", AHAT_PIXELS, PAYLOAD_BASE).reshape(512, 512)
        ab = np.frombuffer(payload, "<u2", AHAT_PIXELS, PAYLOAD_BASE + 2 * AHAT_PIXELS)
        self.last_timestamp = ts
        self.last_pose = None if pose is None else np.frombuffer(pose, "<f4").reshape(4, 4)
        self.received += 1
        self._seq += 1
        return TrackingFrame(
            t=time.monotonic() if t is None else t,
            ir=ab.reshape(512, 512).astype(np.uint16),
            depth_mm=depth.astype(np.uint16),
            intrinsics=self.intrinsics,
            seq=self._seq,
        )

    def _drop_connection(self) -> None:
        if self._sock is not None:
            self._sock.close()
        self._sock = None
        self._next_retry = time.monotonic() + self.config.retry_s

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
