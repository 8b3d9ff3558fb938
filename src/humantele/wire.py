"""Wire messages between the expert and the follower daemons.

Three data channels carry them (see :mod:`humantele.transport`):

- ``pose`` (expert -> follower, unordered, unreliable): :class:`PoseMessage`, fixed-size binary.
- ``state`` (follower -> expert, unordered, unreliable): :class:`StateMessage`, fixed-size binary.
- ``control`` (reliable, ordered): JSON objects with a ``type`` field, validated by pydantic
  (:data:`ControlMessage`, :func:`parse_control`, :func:`encode_control`).

Units and frames: SI (m, s, N, rad). Poses are ``T_patient_probe``: the position (m) and unit
quaternion (x, y, z, w), scalar last, of the transducer in the shared patient frame of the paper
(x head to feet, y up from the bed, z lateral); both daemons map their own frames into it.
``t_sent`` is the sender's ``time.monotonic()`` (s) when the message was sent; the receiver
turns it into an age with the link's clock sync (:meth:`PeerLink.age_of`).

Binary layout (little endian, no padding)::

    header  u8 version | u8 kind | u32 sequence | f64 t_sent              14 bytes
    pose    f64 position[3] | f64 quaternion[4] | u8 buttons | u8 clutch  72 bytes in all
    state   f64 position[3] | f64 quaternion[4] | u8 tracking (TRACKING_CODES) |
            f64 force[3] (N, probe frame) | u8 contact                    96 bytes in all

Decoding never trusts the bytes: a wrong size, version or kind, a non-finite or out-of-range
number, or a quaternion that is not unit raises :class:`WireError`, whose ``reason`` is a short
key the link uses to count dropped messages. Encoding checks the same things, so a NaN is never
sent.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from humantele.geometry import Pose
from humantele.haptics.ellipsoid import (
    MAX_BODY_CENTER_M,
    MAX_BODY_SEMI_AXIS,
    MAX_LONGITUDINAL,
    MIN_BODY_SEMI_AXIS,
)
from humantele.tracking.status import TrackingStatus

PROTOCOL_VERSION = 1
"""Version of every message format here; a peer with another version is refused."""

MAX_POSITION_M = 10.0
"""Largest position magnitude (m) accepted on the wire; anything farther is nonsense."""
MAX_FORCE_N = 500.0
"""Largest force magnitude (N) accepted on the wire."""
MAX_CONTROL_BYTES = 16 * 1024
"""Largest control message (bytes of JSON)."""
QUATERNION_TOLERANCE = 1e-3
"""How far from 1 the norm of a wire quaternion may be."""

KIND_POSE = 1
KIND_STATE = 2

_HEADER = "<BBId"
_POSE = struct.Struct(_HEADER + "3d4dBB")
_STATE = struct.Struct(_HEADER + "3d4dB3dB")
POSE_SIZE = _POSE.size
STATE_SIZE = _STATE.size


class WireError(ValueError):
    """A message that cannot be used. ``reason`` is a short key for counters, e.g. ``"size"``,
    ``"version"``, ``"kind"``, ``"nonfinite"``, ``"range"``, ``"quaternion"``, ``"field"``,
    ``"too_long"``, ``"json"``, ``"schema"``."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


TRACKING_CODES: dict[TrackingStatus, int] = {
    TrackingStatus.LOST: 0,
    TrackingStatus.TRACKED: 1,
    TrackingStatus.PREDICTED: 2,
    TrackingStatus.AMBIGUOUS: 3,
}
"""The state message's one-byte code of each :class:`TrackingStatus`."""
_TRACKING_BY_CODE = {code: status for status, code in TRACKING_CODES.items()}


Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def _check_header(data: bytes, st: struct.Struct, kind: int, name: str) -> None:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireError("type", f"{name} message must be bytes, got {type(data).__name__}")
    if len(data) != st.size:
        raise WireError("size", f"{name} message must be {st.size} bytes, got {len(data)}")
    if data[0] != PROTOCOL_VERSION:
        raise WireError("version", f"{name} message version {data[0]} != {PROTOCOL_VERSION}")
    if data[1] != kind:
        raise WireError("kind", f"expected a {name} message (kind {kind}), got kind {data[1]}")


def _check_numbers(seq: int, t_sent: float, position: Vec3, quaternion: Quat, name: str) -> None:
    if len(position) != 3 or len(quaternion) != 4:
        raise WireError("field", f"{name} needs 3 position and 4 quaternion components")
    if not 0 <= seq <= 0xFFFFFFFF:
        raise WireError("field", f"{name} sequence {seq} is not a u32")
    values = (t_sent, *position, *quaternion)
    if not all(math.isfinite(v) for v in values):
        raise WireError("nonfinite", f"{name} message holds a NaN or infinite number")
    if math.hypot(*position) > MAX_POSITION_M:
        raise WireError("range", f"{name} position farther than {MAX_POSITION_M} m")
    if abs(math.sqrt(sum(q * q for q in quaternion)) - 1.0) > QUATERNION_TOLERANCE:
        raise WireError("quaternion", f"{name} quaternion is not a unit quaternion")


@dataclass(frozen=True, slots=True)
class PoseMessage:
    """Expert -> follower: where the virtual transducer is (``T_patient_probe``).

    ``buttons`` is the stylus button bitmask (bit 0 = first button); ``clutch`` is True while the
    expert's clutch is engaged (the follower's probe should not follow).
    """

    seq: int
    t_sent: float
    position: Vec3
    quaternion: Quat
    buttons: int = 0
    clutch: bool = False

    @classmethod
    def from_pose(
        cls, seq: int, t_sent: float, pose: Pose, buttons: int = 0, clutch: bool = False
    ) -> PoseMessage:
        """Build from a :class:`humantele.geometry.Pose` ``T_patient_probe``."""
        return cls(
            seq & 0xFFFFFFFF,
            float(t_sent),
            tuple(float(v) for v in pose.position),
            tuple(float(v) for v in pose.quaternion),
            buttons,
            clutch,
        )

    @property
    def pose(self) -> Pose:
        """The carried ``T_patient_probe`` as a geometry Pose."""
        return Pose(np.array(self.position), np.array(self.quaternion))

    def encode(self) -> bytes:
        """The 72-byte wire form; WireError if a field is NaN, out of range or malformed."""
        _check_numbers(self.seq, self.t_sent, self.position, self.quaternion, "pose")
        if not 0 <= self.buttons <= 0xFF:
            raise WireError("field", f"pose buttons {self.buttons} is not a u8 bitmask")
        try:
            return _POSE.pack(
                PROTOCOL_VERSION, KIND_POSE, self.seq, self.t_sent,
                *self.position, *self.quaternion, self.buttons, 1 if self.clutch else 0,
            )  # fmt: skip
        except (struct.error, TypeError) as exc:
            raise WireError("field", f"pose message cannot be packed: {exc}") from exc

    @classmethod
    def decode(cls, data: bytes) -> PoseMessage:
        """Parse the wire form; WireError (with ``reason``) on anything malformed."""
        _check_header(data, _POSE, KIND_POSE, "pose")
        f = _POSE.unpack(data)
        msg = cls(f[2], f[3], f[4:7], f[7:11], f[11], bool(f[12]))
        if f[12] > 1:
            raise WireError("field", f"pose clutch flag {f[12]} is not 0 or 1")
        _check_numbers(msg.seq, msg.t_sent, msg.position, msg.quaternion, "pose")
        return msg


@dataclass(frozen=True, slots=True)
class StateMessage:
    """Follower -> expert: the tracked probe (``T_patient_probe``), the measured force on it
    (N, in the probe frame) and whether the probe touches the patient."""

    seq: int
    t_sent: float
    position: Vec3
    quaternion: Quat
    tracking: TrackingStatus = TrackingStatus.TRACKED
    force: Vec3 = (0.0, 0.0, 0.0)
    contact: bool = False

    @property
    def pose(self) -> Pose:
        return Pose(np.array(self.position), np.array(self.quaternion))

    def encode(self) -> bytes:
        """The 96-byte wire form; WireError if a field is NaN, out of range or malformed."""
        _check_numbers(self.seq, self.t_sent, self.position, self.quaternion, "state")
        _check_force(self.force)
        code = TRACKING_CODES.get(self.tracking)  # type: ignore[call-overload]
        if code is None:
            raise WireError("field", f"state tracking status {self.tracking!r} is unknown")
        try:
            return _STATE.pack(
                PROTOCOL_VERSION, KIND_STATE, self.seq, self.t_sent,
                *self.position, *self.quaternion, code,
                *self.force, 1 if self.contact else 0,
            )  # fmt: skip
        except (struct.error, TypeError) as exc:
            raise WireError("field", f"state message cannot be packed: {exc}") from exc

    @classmethod
    def decode(cls, data: bytes) -> StateMessage:
        """Parse the wire form; WireError (with ``reason``) on anything malformed."""
        _check_header(data, _STATE, KIND_STATE, "state")
        f = _STATE.unpack(data)
        tracking = _TRACKING_BY_CODE.get(f[11])
        if tracking is None:
            raise WireError("field", f"state tracking status {f[11]} is unknown")
        if f[15] > 1:
            raise WireError("field", f"state contact flag {f[15]} is not 0 or 1")
        msg = cls(f[2], f[3], f[4:7], f[7:11], tracking, f[12:15], bool(f[15]))
        _check_numbers(msg.seq, msg.t_sent, msg.position, msg.quaternion, "state")
        _check_force(msg.force)
        return msg


def _check_force(force: Vec3) -> None:
    if len(force) != 3 or not all(math.isfinite(v) for v in force):
        raise WireError("nonfinite", "state force must be 3 finite numbers")
    if math.hypot(*force) > MAX_FORCE_N:
        raise WireError("range", f"state force above {MAX_FORCE_N} N")


# --- control messages (JSON on the reliable channel) ----------------------------------------

Finite = Annotated[float, Field(allow_inf_nan=False)]
Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_POSITION_M, le=MAX_POSITION_M)]
Time = Finite  # a monotonic clock reading (s); any finite value
Text = Annotated[str, Field(max_length=200)]
BodyCoordinate = Annotated[
    float, Field(allow_inf_nan=False, ge=-MAX_BODY_CENTER_M, le=MAX_BODY_CENTER_M)
]
BodySemiAxis = Annotated[
    float, Field(allow_inf_nan=False, ge=MIN_BODY_SEMI_AXIS, le=MAX_BODY_SEMI_AXIS)
]
LongitudinalSemiAxis = Annotated[
    float, Field(allow_inf_nan=False, ge=MIN_BODY_SEMI_AXIS, le=MAX_LONGITUDINAL)
]


class _Control(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Hello(_Control):
    """First message each side sends when the channels open."""

    type: Literal["hello"] = "hello"
    protocol: int = PROTOCOL_VERSION
    role: Literal["expert", "follower"]
    software: Text = ""


class EllipsoidParams(_Control):
    """The patient model, exactly as ``Ellipsoid.to_dict()`` gives it, in the patient frame the
    poses use (the follower sends ``Calibration.model_patient()``: center (0, 0, 0) m and
    heading 0 rad; other values place it in that frame): center (m), semi-axes (m, along
    patient x, y, z), heading (rad). Only a body is accepted (``ellipsoid.body_problem``):
    vertical and lateral semi-axes 1 cm to 2 m, the longitudinal one (the paper makes it very
    large) 1 cm to 100 m, the centre within 5 m of the origin."""

    center: tuple[BodyCoordinate, BodyCoordinate, BodyCoordinate]
    semi_axes: tuple[LongitudinalSemiAxis, BodySemiAxis, BodySemiAxis]
    heading: Annotated[float, Field(allow_inf_nan=False, ge=-10.0, le=10.0)]


class EllipsoidModel(_Control):
    """Follower -> expert: a newly fitted patient model (once per calibration)."""

    type: Literal["ellipsoid"] = "ellipsoid"
    model: EllipsoidParams


LANDMARKS: tuple[str, ...] = ("xiphoid", "left", "right", "bed")
"""The patient calibration's landmarks, in the order they are touched (the one list: the
follower's calibration and the expert's console use it); :class:`CalibrationProgress`'s
``index`` is an index into it."""


class CalibrationProgress(_Control):
    """Calibration progress: ``start``, a landmark ``point`` (index 0-3 in :data:`LANDMARKS`,
    position m in the patient/world frame the calibration uses), ``done``, ``cancel`` or
    ``error``. (The fitted calibration itself is
    :class:`humantele.follower.calibration.Calibration`.)"""

    type: Literal["calibration"] = "calibration"
    event: Literal["start", "point", "done", "cancel", "error"]
    index: Annotated[int, Field(ge=0, le=15)] | None = None
    point: tuple[Coordinate, Coordinate, Coordinate] | None = None
    detail: Text = ""


PixelSize = Annotated[float, Field(allow_inf_nan=False, gt=0.0, lt=100.0)]


class UsScale(_Control):
    """The follower's ultrasound picture's scale, as its source is configured (a real
    scanner's: ``[follower.video.us]``): (row, col) mm per pixel of the frames it sends and the
    image row (px) of depth 0. Sent after each Hello; the expert's console uses it for its
    calipers and depth scale unless its own configuration sets them."""

    type: Literal["us_scale"] = "us_scale"
    pixel_spacing_mm: tuple[PixelSize, PixelSize]
    depth_origin_row: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=8192.0)]


class Scan(_Control):
    """Scan start/stop (the recording follows it). No patient identity here, ever."""

    type: Literal["scan"] = "scan"
    action: Literal["start", "stop"]
    scan_id: Annotated[str, Field(max_length=64, pattern=r"^[A-Za-z0-9_.-]*$")] = ""


class Ping(_Control):
    """Clock sync request: ``t0`` is the sender's monotonic time (s) when sent."""

    type: Literal["ping"] = "ping"
    seq: Annotated[int, Field(ge=0)]
    t0: Time


class Pong(_Control):
    """Clock sync reply: echoes ``seq`` and ``t0``; ``t1``/``t2`` are the replier's monotonic
    times (s) when the ping arrived and when the pong left."""

    type: Literal["pong"] = "pong"
    seq: Annotated[int, Field(ge=0)]
    t0: Time
    t1: Time
    t2: Time


class Heartbeat(_Control):
    """Liveness, sent a few times a second; ``t`` is the sender's monotonic time (s)."""

    type: Literal["heartbeat"] = "heartbeat"
    t: Time


class Bye(_Control):
    """The sender is leaving on purpose (not a failure)."""

    type: Literal["bye"] = "bye"
    reason: Text = ""


ControlMessage = Annotated[
    Hello | EllipsoidModel | CalibrationProgress | Scan | Ping | Pong | Heartbeat | Bye | UsScale,
    Field(discriminator="type"),
]
_CONTROL = TypeAdapter(ControlMessage)


def parse_control(text: str | bytes) -> ControlMessage:
    """Validate one control message (JSON text); WireError with reason ``too_long``, ``json``
    or ``schema`` (the message names the first bad field)."""
    if len(text) > MAX_CONTROL_BYTES:
        raise WireError("too_long", f"control message of {len(text)} bytes > {MAX_CONTROL_BYTES}")
    try:
        return _CONTROL.validate_json(text)
    except ValidationError as exc:
        err = exc.errors()[0]
        reason = "json" if err["type"] == "json_invalid" else "schema"
        loc = ".".join(str(p) for p in err["loc"]) or "(message)"
        raise WireError(reason, f"bad control message: {loc}: {err['msg']}") from None


def encode_control(msg: _Control) -> str:
    """The JSON text of a control message (compact)."""
    return msg.model_dump_json()
