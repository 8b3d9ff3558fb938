"""The hl2ss wire format of the HoloLens 2 AHAT stream (RM ZHT), as hl2ss's own sources define it.

Checked against github.com/jdibenes/hl2ss at commit 9a70fad2 (2025-05-21): the client's
``viewer/hl2ss.py`` (``_create_configuration_for_rm_depth_ahat``, ``_unpacker``,
``decode_rm_depth_ahat``, ``download_calibration_rm_depth_ahat``) and the app's
``hl2ss/hl2ss/server_settings.cpp``, ``stream_rm_zht.cpp``, ``encoder_rm_zht.cpp`` and
``locator.cpp``. Shared by the client (:mod:`humantele.tracking.hl2ss_source`), the replay
server (:mod:`humantele.tracking.hl2ss_replay`) and the calibration command.

Configuration (client -> app, port 3804), all little-endian:
``<B`` mode (0: frames; 1: frames + rig pose; 2: calibration, nothing else follows), then for
modes 0/1 ``<B`` divisor (> 0), ``<B`` depth profile (0 SAME, 1 ZDEPTH), ``<BBI`` AB profile
(0-3 H.26x, 0xFF RAW), level, bitrate (> 0, even for RAW), ``<B`` option count and that many
``<QQ`` (key, value). The app refuses anything else by closing the socket.

Packet (app -> client): ``<QI`` timestamp (100 ns ticks) and payload size, the payload
``<II`` size_z, size_ab, the depth blob (size_z bytes), the AB blob (size_ab bytes), ``<Q``
sensor ticks; then in mode 1 the rig pose, 16 float32 (64 bytes, not counted in the payload
size). With depth SAME and AB RAW (what this project asks for): size_z = 0 and the AB blob is
the depth image then the AB image, 512 x 512 uint16 each (size_ab = 1 048 576); depth values
>= 4090 are set to 0 (invalid) by the app.

Rig pose: a Windows ``float4x4`` (row-vector convention, ``p_world = p_rig @ M``) written
row-major, so read as a numpy (4, 4) array the rotation is ``M[:3, :3] = R.T`` and the
translation is the LAST ROW ``M[3, :3]``; it is the transpose of the usual column-vector
matrix: ``T_world_rig = M.T``. "world" is the app's world coordinate system (a Windows
``SpatialCoordinateSystem``, y up, metres); "rig" is the research-mode rig node. A pose the
headset could not locate is all zeros (hl2ss's ``is_valid_pose``: ``M[3, 3] != 0``).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.geometry import Pose, matrix_to_quat

AHAT_PORT = 3804
AHAT_WIDTH = AHAT_HEIGHT = 512
AHAT_PIXELS = AHAT_WIDTH * AHAT_HEIGHT
AHAT_FPS = 45
AHAT_DEPTH_MASK = 4090  # RM_ZHT_MASK: the app sets depth >= this to 0

MODE_FRAMES, MODE_FRAMES_POSE, MODE_CALIBRATION = 0, 1, 2
DEPTH_PROFILE_SAME, DEPTH_PROFILE_ZDEPTH = 0, 1
VIDEO_PROFILE_RAW = 0xFF
VIDEO_PROFILES = (0, 1, 2, 3, VIDEO_PROFILE_RAW)  # H264 base/main/high, H265 main, RAW
LEVEL_DEFAULT = 0xFF
GOP_SIZE_OPTION = 10  # H26xEncoderProperty.CODECAPI_AVEncMPVGOPSize
# hl2ss_lnm.rx_rm_depth_ahat's default for RAW + SAME: width * height * fps * 12 * 1.0 * 16
DEFAULT_RAW_BITRATE = AHAT_WIDTH * AHAT_HEIGHT * AHAT_FPS * 12 * 16

HEADER = struct.Struct("<QI")  # timestamp, payload size
SIZES = struct.Struct("<II")  # size_z, size_ab
TICKS = struct.Struct("<Q")
POSE_BYTES = 64
RAW_AB_SIZE = 4 * AHAT_PIXELS  # depth then AB, uint16 each (SAME + RAW)
RAW_PAYLOAD_SIZE = SIZES.size + RAW_AB_SIZE + TICKS.size
MAX_PAYLOAD_SIZE = 4 * RAW_PAYLOAD_SIZE  # above this the stream is out of step


class ConfigurationRefused(ValueError):
    """The configuration bytes are ones the hl2ss app refuses (it closes the socket)."""


class PacketError(ValueError):
    """A packet that cannot be a RAW AHAT frame; ``reason`` is the counter's key."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class AhatConfiguration:
    """What a client asks the AHAT stream for (field names as hl2ss's)."""

    mode: int = MODE_FRAMES_POSE
    divisor: int = 1
    profile_z: int = DEPTH_PROFILE_SAME
    profile_ab: int = VIDEO_PROFILE_RAW
    level: int = LEVEL_DEFAULT
    bitrate: int = DEFAULT_RAW_BITRATE
    options: dict[int, int] = field(default_factory=lambda: {GOP_SIZE_OPTION: 1})

    def pack(self) -> bytes:
        """The bytes hl2ss's ``_create_configuration_for_rm_depth_ahat`` sends (mode 2: one
        byte, as ``_create_configuration_for_rm_mode2``)."""
        if self.mode == MODE_CALIBRATION:
            return struct.pack("<B", self.mode)
        out = struct.pack("<BBBBBI", self.mode, self.divisor, self.profile_z, self.profile_ab,
                          self.level, self.bitrate)  # fmt: skip
        out += struct.pack("<B", len(self.options))
        for key, value in self.options.items():
            out += struct.pack("<QQ", key, value)
        return out


def read_configuration(recv_exactly: Callable[[int], bytes]) -> AhatConfiguration:
    """Read a client's configuration as the app does (``Channel_RM_ZHT::Run``,
    ``server_settings.cpp``), raising :class:`ConfigurationRefused` where the app would return
    and close the socket. ``recv_exactly(n)`` returns n bytes or raises ConnectionError."""
    (mode,) = struct.unpack("<B", recv_exactly(1))
    mode &= 3  # the app switches on mode & 3
    if mode == MODE_CALIBRATION:
        return AhatConfiguration(mode=mode, options={})
    if mode == 3:
        raise ConfigurationRefused("mode 3 is reserved")
    (divisor,) = struct.unpack("<B", recv_exactly(1))
    if divisor <= 0:
        raise ConfigurationRefused("divisor must be > 0")
    (profile_z,) = struct.unpack("<B", recv_exactly(1))
    if profile_z not in (DEPTH_PROFILE_SAME, DEPTH_PROFILE_ZDEPTH):
        raise ConfigurationRefused(f"depth profile {profile_z} is not SAME (0) or ZDEPTH (1)")
    profile_ab, level, bitrate = struct.unpack("<BBI", recv_exactly(6))
    if profile_ab not in VIDEO_PROFILES:
        raise ConfigurationRefused(f"AB profile {profile_ab} is not H.26x (0-3) or RAW (255)")
    if bitrate <= 0:
        raise ConfigurationRefused("bitrate must be > 0 (also for RAW)")
    (count,) = struct.unpack("<B", recv_exactly(1))
    raw = recv_exactly(16 * count)
    options = {k: v for k, v in (struct.unpack_from("<QQ", raw, 16 * i) for i in range(count))}
    return AhatConfiguration(mode, divisor, profile_z, profile_ab, level, bitrate, options)


def encode_ahat_packet(
    timestamp: int,
    depth_mm: ArrayLike,
    ab: ArrayLike,
    sensor_ticks: int = 0,
    pose: ArrayLike | None = None,
) -> bytes:
    """One RAW (depth SAME, AB RAW) AHAT packet exactly as the app sends it: header, size_z = 0,
    size_ab, depth (>= 4090 set to 0, as the app does) and AB images, sensor ticks, then
    ``pose`` (the hl2ss 4x4 float32 matrix, see :func:`hl2ss_matrix_from_pose`) in mode 1."""
    depth = np.ascontiguousarray(depth_mm, dtype="<u2").reshape(AHAT_HEIGHT, AHAT_WIDTH)
    depth = np.where(depth >= AHAT_DEPTH_MASK, 0, depth).astype("<u2")
    images = depth.tobytes() + np.ascontiguousarray(ab, dtype="<u2").reshape(depth.shape).tobytes()
    payload = SIZES.pack(0, len(images)) + images + TICKS.pack(sensor_ticks)
    tail = b""
    if pose is not None:
        m = np.asarray(pose, dtype="<f4")
        if m.shape != (4, 4):
            raise ValueError(f"the rig pose is a 4x4 matrix, got {m.shape}")
        tail = m.tobytes()
    return HEADER.pack(timestamp, len(payload)) + payload + tail


@dataclass(frozen=True)
class AhatPayload:
    """A decoded RAW payload: depth (range along the ray, mm, 0 invalid) and active brightness,
    both (512, 512) uint16, and the sensor's own tick count."""

    depth_mm: NDArray[np.uint16]
    ab: NDArray[np.uint16]
    sensor_ticks: int


def decode_ahat_payload(payload: bytes | bytearray | memoryview) -> AhatPayload:
    """Check a payload's size_z/size_ab against its length and RAW's sizes, then unpack it;
    :class:`PacketError` ("size": the sizes disagree with the length; "encoding": not a RAW
    SAME frame, e.g. H.26x or Zdepth) otherwise."""
    n = len(payload)
    if n < SIZES.size + TICKS.size:
        raise PacketError("size", f"payload of {n} bytes is shorter than its own header")
    size_z, size_ab = SIZES.unpack_from(payload, 0)
    if SIZES.size + size_z + size_ab + TICKS.size != n:
        raise PacketError("size", f"size_z {size_z} + size_ab {size_ab} disagree with {n} bytes")
    if size_z != 0 or size_ab != RAW_AB_SIZE:
        raise PacketError("encoding", f"not a RAW frame (size_z {size_z}, size_ab {size_ab})")
    img = np.frombuffer(payload, "<u2", 2 * AHAT_PIXELS, SIZES.size)
    (ticks,) = TICKS.unpack_from(payload, n - TICKS.size)
    depth = img[:AHAT_PIXELS].reshape(AHAT_HEIGHT, AHAT_WIDTH).astype(np.uint16)
    ab = img[AHAT_PIXELS:].reshape(AHAT_HEIGHT, AHAT_WIDTH).astype(np.uint16)
    return AhatPayload(depth, ab, int(ticks))


# --- matrices -------------------------------------------------------------------------------

ROTATION_TOLERANCE = 1e-3  # float32 rotations from the headset are orthonormal to ~1e-6


def pose_from_hl2ss(matrix: ArrayLike) -> tuple[Pose | None, str]:
    """Our ``T_a_b`` from an hl2ss 4x4 matrix (row-vector convention, translation in the last
    row: ``p_a = p_b @ M``, so ``T_a_b = M.T``), with "" or why it is no pose: "not_located"
    (all zeros: the headset lost tracking; hl2ss's ``is_valid_pose``), "not_finite",
    "not_rigid" (not a rotation plus translation, e.g. a column-vector matrix sent by mistake).
    """
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4):
        raise ValueError(f"an hl2ss matrix is 4x4, got {m.shape}")
    if not np.all(np.isfinite(m)):
        return None, "not_finite"
    if m[3, 3] == 0.0:
        return None, "not_located"
    T = m.T
    R = T[:3, :3]
    tol = ROTATION_TOLERANCE
    if (
        np.abs(T[3, :3]).max() > tol
        or abs(T[3, 3] - 1.0) > tol
        or np.abs(R @ R.T - np.eye(3)).max() > tol
        or abs(np.linalg.det(R) - 1.0) > tol
    ):
        return None, "not_rigid"
    return Pose(T[:3, 3], matrix_to_quat(R)), ""


def frame_poses(
    matrix: ArrayLike | None, T_rig_camera: Pose | None, no_pose: dict[str, int]
) -> tuple[Pose | None, Pose | None]:
    """(``T_world_rig``, ``T_world_camera``) of a frame from its hl2ss rig matrix (None: mode
    0) and the AHAT extrinsics; a frame without them counts why in ``no_pose``."""
    why = "mode_0"
    T_world_rig = None
    if matrix is not None:
        T_world_rig, why = pose_from_hl2ss(matrix)
        if T_world_rig is not None and T_rig_camera is not None:
            return T_world_rig, T_world_rig @ T_rig_camera
        why = why or "no_extrinsics"
    no_pose[why] = no_pose.get(why, 0) + 1
    return T_world_rig, None


def hl2ss_matrix_from_pose(T_a_b: Pose) -> NDArray[np.float32]:
    """The 4x4 float32 matrix hl2ss would send for ``T_a_b`` (the transpose of ours)."""
    return T_a_b.as_matrix().T.astype(np.float32)


def rig_camera_from_extrinsics(extrinsics: ArrayLike) -> Pose:
    """``T_rig_camera`` from hl2ss's AHAT extrinsics (research mode's
    ``GetCameraExtrinsicsMatrix``, row-vector: ``p_camera = p_rig @ E``, so ``T_camera_rig =
    E.T``). hl2ss maps camera to world as ``inv(E) @ pose`` in its row-vector convention
    (``hl2ss_3dcv.camera_to_rignode(E) @ reference_to_world(pose)``); this is its column-vector
    form. ValueError when E is not rigid."""
    T_camera_rig, why = pose_from_hl2ss(extrinsics)
    if T_camera_rig is None:
        raise ValueError(f"hl2ss AHAT extrinsics are not a rigid transform ({why})")
    return T_camera_rig.inverse()
