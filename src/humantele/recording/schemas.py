"""The recorded channels: topic names, their fields (SI units, frames) and JSON schemas.

Every sample has ``t``: seconds on the clock of the daemon that records it (the expert daemon's
clock for ``/expert/*`` topics, the follower daemon's for ``/follower/*``); the ``clock_sync``
topics relate the two. Poses are ``T_patient_probe``: the probe's position (m) and orientation
(unit quaternion, x, y, z, w scalar-last) in the patient frame of the paper (x head to feet, y up
from the bed, z lateral), the frame shared by the expert's virtual probe and the tracked probe.

High-rate topics (``batch=True``) pack several samples into one MCAP message as columns,
``{"t": [t0, t1, ...], "position": [[x, y, z], ...], ...}`` (reading 600k samples as JSON
objects is too slow; see docs/analysis.md); the others hold one sample per message. Messages
are JSON with a JSON schema, so Foxglove opens the files directly. Ids are pseudonyms
(``F03``, ``S1``): no patient identity is ever recorded.
"""

from __future__ import annotations

import base64
import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
SESSION_METADATA = "humantele.session"

# A pseudonymous participant id: up to 4 letters, an optional '-' or '_', then 1-6 digits
# ("F03", "S1", "P-12"). Refuses names and e-mail addresses, which never match.
ID_PATTERN = re.compile(r"^[A-Za-z]{0,4}[-_]?[0-9]{1,6}$")

_MAX_STRING = 200
# Recorded precision: vectors 1e-7 (0.1 um, 0.1 uN), quaternions 1e-8, t 1 us. Short numbers
# make the JSON half the size and twice as fast to read, far below any sensor's noise.
VEC3_DECIMALS, QUAT_DECIMALS, T_DECIMALS = 7, 8, 6

# kind -> JSON schema of the value
_KINDS: dict[str, dict[str, Any]] = {
    "number": {"type": "number"},
    "integer": {"type": "integer"},
    "string": {"type": "string", "maxLength": _MAX_STRING},
    "boolean": {"type": "boolean"},
    "vec2": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
    "vec3": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "quat": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
    "bytes": {"type": "string", "contentEncoding": "base64"},
}
# An encoded video frame (one /expert/*_video message): at most this many bytes.
MAX_FRAME_BYTES = 4 << 20


@dataclass(frozen=True)
class ChannelSpec:
    """One recorded stream: its topic, fields ``name -> (kind, description)``, which are
    required, and whether samples are packed several per message (high-rate streams)."""

    topic: str
    description: str
    fields: dict[str, tuple[str, str]]
    required: tuple[str, ...] = ()
    batch: bool = False
    enums: dict[str, tuple[str, ...]] = field(default_factory=dict)
    image: bool = False  # a foxglove.CompressedImage (JPEG) channel, see image_sample

    @property
    def schema_name(self) -> str:
        if self.image:
            return IMAGE_SCHEMA
        return "humantele" + self.topic.replace("/", ".")


_POSE = {
    "position": ("vec3", "probe position in the patient frame, m"),
    "quaternion": ("quat", "probe orientation in the patient frame, unit (x, y, z, w)"),
}
_CLOCK_SYNC = {
    "offset_s": ("number", "peer clock minus this daemon's clock, s (t_peer = t + offset_s)"),
    "rtt_s": ("number", "round trip of the exchange that gave this estimate, s"),
}
_LATENCY = {
    "name": ("string", "what was measured, e.g. 'pose_one_way', 'video_glass_to_glass'"),
    "value_s": ("number", "the latency, s"),
}
_VIDEO = {
    "stream": ("string", "'pov' (follower camera) or 'us' (ultrasound image)"),
    "seq": ("integer", "frame number in its stream"),
    "event": ("string", "'captured', 'sent' or 'received'"),
    "quality": ("number", "sim US: known-answer image quality of the frame, 0-1 (captured)"),
    "coupling": ("number", "sim US: mean acoustic coupling of the beams, 0-1 (captured)"),
    "width": ("integer", "size sent, px (sent)"),
    "height": ("integer", "size sent, px (sent)"),
    "age_s": ("number", "capture (follower) to decoded (expert), s, via clock sync (received)"),
}
_ENCODED_VIDEO = {
    "data": (
        "bytes",
        "the encoded frame as received: a VP8 frame, or an H.264 access unit "
        "(Annex B); depacketised, not decoded",
    ),
    "codec": ("string", "'vp8' or 'h264'"),
    "keyframe": ("boolean", "the frame decodes on its own (VP8 key frame; H.264 IDR or SPS)"),
    "rtp_timestamp": ("integer", "its RTP timestamp as received, 90 kHz, sender's clock"),
    "t_capture": (
        "number",
        "capture time on this (expert) clock via clock sync, s; absent "
        "until the stream's RTP clock is tied to the follower's (its first frames)",
    ),
}
VIDEO_TOPICS = {"us": "/expert/us_video", "pov": "/expert/pov_video"}
IMAGE_SCHEMA = "foxglove.CompressedImage"
IMAGE_TOPICS = ("/follower/us_image", "/follower/pov_image")

CHANNELS: dict[str, ChannelSpec] = {
    spec.topic: spec
    for spec in [
        ChannelSpec(
            "/expert/pose",
            "the virtual probe commanded by the expert (T_patient_probe), servo rate",
            {**_POSE, "velocity": ("vec3", "probe velocity in the patient frame, m/s")},
            ("position", "quaternion"),
            batch=True,
        ),
        ChannelSpec(
            "/expert/force",
            "force rendered to the haptic device from the ellipsoid model, patient frame",
            {
                "force": ("vec3", "force on the expert's hand, patient frame, N"),
                "depth_m": ("number", "penetration into the ellipsoid, m"),
            },
            ("force",),
            batch=True,
        ),
        ChannelSpec(
            "/expert/servo_stats",
            "servo loop statistics, about once a second",
            {
                "rate_hz": ("number", "mean loop rate, Hz"),
                "period_p99_s": ("number", "99th percentile loop period, s"),
                "late_ticks": ("integer", "ticks over their deadline since the last report"),
                "state": ("string", "servo state, e.g. 'running', 'fault'"),
            },
            ("rate_hz",),
        ),
        ChannelSpec(
            "/expert/scan",
            "scan start and stop, from the expert; ids are pseudonyms",
            {
                "event": ("string", "'start' or 'stop'"),
                "scan": ("integer", "scan number (>= 0)"),
                "follower_id": ("string", "pseudonymous follower id, e.g. 'F03'"),
                "sonographer_id": ("string", "pseudonymous sonographer id, e.g. 'S1'"),
            },
            ("event", "scan"),
            enums={"event": ("start", "stop")},
        ),
        ChannelSpec(
            "/follower/scan",
            "scan start and stop as the follower received them from the expert (follower clock)",
            {
                "event": ("string", "'start' or 'stop'"),
                "scan": ("integer", "scan number (>= 0)"),
            },
            ("event", "scan"),
            enums={"event": ("start", "stop")},
        ),
        ChannelSpec(
            "/expert/clock_sync",
            "clock offset estimates to the follower",
            _CLOCK_SYNC,
            ("offset_s",),
        ),
        ChannelSpec(
            "/follower/clock_sync",
            "clock offset estimates to the expert",
            _CLOCK_SYNC,
            ("offset_s",),
        ),
        ChannelSpec(
            "/expert/latency",
            "latency figures measured by the expert",
            _LATENCY,
            ("name", "value_s"),
        ),
        ChannelSpec(
            "/follower/latency",
            "latency figures measured by the follower",
            _LATENCY,
            ("name", "value_s"),
        ),
        ChannelSpec(
            "/expert/video_frame", "video frame timestamps at the expert", _VIDEO, ("stream", "seq")
        ),
        ChannelSpec(
            "/follower/video_frame",
            "video frame timestamps at the follower",
            _VIDEO,
            ("stream", "seq"),
        ),
        ChannelSpec(
            "/expert/console",
            "the sonographer's console tools on the ultrasound image (freeze, live, calipers, "
            "annotations, captures, their clips); points are image px (x right, y down from "
            "the top-left)",
            {
                "event": (
                    "string",
                    "'freeze', 'live', 'caliper', 'annotation', 'capture' or 'clip'",
                ),
                "seq": ("integer", "ultrasound frame number the tool was used on"),
                "t_capture": ("number", "that frame's capture time, expert clock, s"),
                "mm": ("number", "caliper distance, mm (from the source's pixel spacing)"),
                "a_px": ("vec2", "caliper start or annotation point, image px"),
                "b_px": ("vec2", "caliper end, image px"),
                "text": ("string", "annotation text"),
                "file": (
                    "string",
                    "capture: the saved JPEG (also attached to this recording); "
                    "clip: the saved MP4 (H.264) of the cine's seconds up to the capture",
                ),
                "still": ("string", "clip: its capture's JPEG"),
                "frames": ("integer", "clip: frames in it"),
                "duration_s": ("number", "clip: first to last frame, s"),
                **_POSE,
                "virtual_position": ("vec3", "the expert's virtual probe, patient frame, m"),
                "virtual_quaternion": ("quat", "the expert's virtual probe orientation"),
            },
            ("event",),
            enums={"event": ("freeze", "live", "caliper", "annotation", "capture", "clip")},
        ),
        *(
            ChannelSpec(
                topic,
                f"the {name} stream's encoded frames as the expert received them, every frame "
                "(t: when complete at the expert, before decoding, expert clock)",
                _ENCODED_VIDEO,
                ("data", "codec", "keyframe", "rtp_timestamp"),
                enums={"codec": ("vp8", "h264")},
            )
            for name, topic in VIDEO_TOPICS.items()
        ),
        ChannelSpec(
            "/follower/us_image",
            "the ultrasound image as sent, JPEG, at [follower.video] record_us_hz",
            {"seq": ("integer", "frame number in the us stream")},
            image=True,
        ),
        ChannelSpec(
            "/follower/pov_image",
            "the follower's point of view as sent, JPEG, at [follower.video] record_pov_hz",
            {"seq": ("integer", "frame number in the pov stream")},
            image=True,
        ),
        ChannelSpec(
            "/follower/probe_pose",
            "the real probe tracked by the headset (T_patient_probe), one per tracker frame",
            {
                **_POSE,
                "tracked": ("boolean", "false when the tool was not found in this frame"),
                "markers": ("integer", "markers matched in this frame"),
                "device_time_s": ("number", "the tracker frame's time on the device's clock, s"),
            },
            ("position", "quaternion", "tracked"),
        ),
        ChannelSpec(
            "/follower/force",
            "force measured by the probe's sensor, probe frame",
            {"force": ("vec3", "force on the probe, probe frame, N")},
            ("force",),
            batch=True,
        ),
        ChannelSpec(
            "/follower/ellipsoid",
            "the fitted patient model (eqs. 1-5), sent to the expert after calibration",
            {
                "center": ("vec3", "ellipsoid centre in the headset world frame, m"),
                "semi_axes": ("vec3", "semi-axes along patient x, y, z (c, b, a), m"),
                "heading": ("number", "T_world_patient: rotation about world +y, rad"),
            },
            ("center", "semi_axes"),
        ),
        ChannelSpec(
            "/follower/calibration",
            "calibration events: a landmark collected, the fit done or refused",
            {
                "event": ("string", "'point', 'fit', 'reset' or 'error'"),
                "landmark": ("string", "'xiphoid', 'left', 'right' or 'bed'"),
                "position": ("vec3", "collected probe tip position, patient/world frame, m"),
                "message": ("string", "why a fit was refused"),
            },
            ("event",),
        ),
    ]
}


def image_json_schema(spec: ChannelSpec) -> dict[str, Any]:
    """Foxglove's ``foxglove.CompressedImage`` as a JSON schema (bytes as base64), plus the
    sample's ``t`` and ``seq``: Foxglove's Image panel shows these channels."""
    time_schema = {
        "type": "object",
        "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
    }
    return {
        "type": "object",
        "title": IMAGE_SCHEMA,
        "description": spec.description,
        "properties": {
            "timestamp": {**time_schema, "description": "capture time, this daemon's clock"},
            "frame_id": {"type": "string", "description": "'us' or 'pov'"},
            "data": {"type": "string", "contentEncoding": "base64", "description": "JPEG"},
            "format": {"type": "string", "description": "'jpeg'"},
            "t": {"type": "number", "description": "time on this daemon's clock, s"},
            "seq": {"type": "integer", "description": "frame number in its stream"},
        },
        "required": ["timestamp", "frame_id", "data", "format", "t"],
    }


def image_sample(spec: ChannelSpec, t: float, payload: dict[str, Any]) -> dict[str, Any]:
    """A ``foxglove.CompressedImage`` message from ``{"data": JPEG bytes, "seq": n}``."""
    data = payload.get("data")
    if not isinstance(data, bytes | bytearray) or data[:2] != b"\xff\xd8":
        raise ValueError(f"{spec.topic}: field 'data' must be JPEG bytes")
    tt = round(_value("number", t), T_DECIMALS)
    sec = math.floor(tt)
    sample: dict[str, Any] = {
        "timestamp": {"sec": int(sec), "nsec": int(round((tt - sec) * 1e9)) % 1_000_000_000},
        "frame_id": spec.topic.rsplit("/", 1)[-1].removesuffix("_image"),
        "data": base64.b64encode(bytes(data)).decode("ascii"),
        "format": "jpeg",
        "t": tt,
    }
    if "seq" in payload:
        sample["seq"] = _value("integer", payload["seq"])
    return sample


def json_schema(spec: ChannelSpec) -> dict[str, Any]:
    """The JSON schema of one message of ``spec`` (Foxglove reads it)."""
    if spec.image:
        return image_json_schema(spec)
    props: dict[str, Any] = {
        "t": {"type": "number", "description": "time on this daemon's clock, s"}
    }
    for name, (kind, desc) in spec.fields.items():
        props[name] = {**_KINDS[kind], "description": desc}
        if name in spec.enums:
            props[name]["enum"] = list(spec.enums[name])
    sample = {
        "type": "object",
        "title": spec.schema_name,
        "description": spec.description,
        "properties": props,
        "required": ["t", *spec.required],
    }
    if not spec.batch:
        return sample
    columns = {k: {"type": "array", "items": v} for k, v in props.items()}
    return {
        "type": "object",
        "title": spec.schema_name,
        "description": spec.description
        + " (columnar batch: each field is a list with one entry per sample)",
        "properties": columns,
        "required": ["t", *spec.required],
    }


def schema_bytes(spec: ChannelSpec) -> bytes:
    return json.dumps(json_schema(spec)).encode()


def _finite(x: Any) -> float:
    v = float(x)
    if not math.isfinite(v):
        raise ValueError("not finite")
    return v


_VECTORS = {"vec2": (2, VEC3_DECIMALS), "vec3": (3, VEC3_DECIMALS)}  # kind -> length, digits


def _value(kind: str, v: Any) -> Any:
    if kind == "number":
        if isinstance(v, bool):
            raise ValueError("expected a number")
        return _finite(v)
    if kind == "integer":
        if isinstance(v, bool) or int(v) != v:
            raise ValueError("expected an integer")
        return int(v)
    if kind == "string":
        if not isinstance(v, str) or len(v) > _MAX_STRING:
            raise ValueError(f"expected a string of at most {_MAX_STRING} characters")
        return v
    if kind == "bytes":
        if not isinstance(v, bytes | bytearray | memoryview) or not 0 < len(v) <= MAX_FRAME_BYTES:
            raise ValueError(f"expected 1 to {MAX_FRAME_BYTES} bytes")
        return base64.b64encode(v).decode("ascii")
    if kind == "boolean":
        if not isinstance(v, bool | int) or v not in (0, 1):
            raise ValueError("expected a boolean")
        return bool(v)
    n, digits = _VECTORS.get(kind, (4, QUAT_DECIMALS))
    vals = [round(_finite(x), digits) for x in (v.tolist() if hasattr(v, "tolist") else v)]
    if len(vals) != n:
        raise ValueError(f"expected {n} numbers")
    if kind == "quat" and not 0.5 < math.sqrt(sum(x * x for x in vals)) < 1.5:
        raise ValueError("quaternion is not unit length")
    return vals


def make_sample(spec: ChannelSpec, t: float, payload: dict[str, Any]) -> dict[str, Any]:
    """The sample ``{"t": t, **fields}`` of ``spec`` with plain JSON values (numpy arrays become
    lists); ValueError naming the field if a value is missing, unknown, non-finite or mistyped."""
    if spec.image:
        return image_sample(spec, t, payload)
    sample: dict[str, Any] = {"t": round(_value("number", t), T_DECIMALS)}
    for name in payload:
        if name != "t" and name not in spec.fields:
            raise ValueError(f"{spec.topic}: unknown field {name!r}")
    for name in spec.fields:  # the spec's order: every sample of a topic has one key order
        if name not in payload:
            continue
        v = payload[name]
        try:
            sample[name] = _value(spec.fields[name][0], v)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{spec.topic}: field {name!r}: {exc}") from None
        if name in spec.enums and sample[name] not in spec.enums[name]:
            raise ValueError(f"{spec.topic}: field {name!r} must be one of {spec.enums[name]}")
    missing = [name for name in spec.required if name not in sample]
    if missing:
        raise ValueError(f"{spec.topic}: missing field(s) {', '.join(missing)}")
    return sample


def check_participant_id(value: str, what: str = "id") -> str:
    """``value`` if it is an opaque pseudonym like 'F03' or 'S1'; ValueError otherwise (so a
    name or an e-mail address is never written into a recording)."""
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise ValueError(
            f"{what} {value!r} is not a pseudonymous id: use up to 4 letters and 1-6 digits, "
            "e.g. 'F03' or 'S1' (no names or e-mail addresses)"
        )
    return value
