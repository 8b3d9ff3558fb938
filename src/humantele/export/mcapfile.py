"""The Foxglove file of one scan: the ultrasound and POV as ``foxglove.CompressedVideo``
(H.264, Annex B, one message per frame, SPS/PPS with each keyframe), the expert's virtual
probe and the tracked real probe as ``foxglove.PoseInFrame`` (frame ``patient``), and both
forces, all JSON and all on the expert's clock, so Foxglove plays the video in time with the
poses and force. Log times and ``timestamp`` s are that clock moved to Unix time by the
recording's ``clock_unix_offset_s`` (Foxglove shows the session's date and time; a recording
without it: the clock as it is, near 1970); the force messages' ``t`` stays the expert's.
"""

from __future__ import annotations

import base64
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from humantele.analysis.alignment import PoseTrack
from humantele.recording.schemas import CHANNELS, json_schema

VIDEO_SCHEMA = "foxglove.CompressedVideo"
POSE_SCHEMA = "foxglove.PoseInFrame"
_TIME = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}
VIDEO_JSON_SCHEMA = {
    "type": "object",
    "title": VIDEO_SCHEMA,
    "description": "A single frame of a compressed video bitstream (Foxglove's schema)",
    "properties": {
        "timestamp": {**_TIME, "description": "capture time, expert clock"},
        "frame_id": {"type": "string"},
        "data": {
            "type": "string",
            "contentEncoding": "base64",
            "description": "H.264 access unit, Annex B",
        },
        "format": {"type": "string", "description": "'h264'"},
    },
}
_XYZ = {k: {"type": "number"} for k in "xyz"}
POSE_JSON_SCHEMA = {
    "type": "object",
    "title": POSE_SCHEMA,
    "description": "A timestamped pose in a named frame (Foxglove's schema); T_patient_probe",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": {
            "type": "object",
            "properties": {
                "position": {"type": "object", "properties": _XYZ},
                "orientation": {"type": "object", "properties": {**_XYZ, "w": {"type": "number"}}},
            },
        },
    },
}
VIDEO_OUT = {"us": "/us/video", "pov": "/pov/video"}
POSES_OUT = {"virtual": "/expert/pose", "real": "/follower/probe_pose"}


def _stamp(t: float) -> dict[str, int]:
    sec = math.floor(t)
    return {"sec": int(sec), "nsec": min(int(round((t - sec) * 1e9)), 999_999_999)}


def _ns(t: float) -> int:
    return max(0, int(round(t * 1e9)))


def clock_metadata(unix_offset_s: float | None) -> dict[str, str]:
    """What the file's times are, for its metadata."""
    if unix_offset_s is None:
        return {"clock": "expert daemon clock (s); log time = that in ns"}
    return {
        "clock": "Unix time: expert daemon clock (s) + clock_unix_offset_s; log time in ns",
        "clock_unix_offset_s": f"{unix_offset_s:.6f}",
    }


class ScanMcap:
    """Collects a scan's messages, then :meth:`write` sorts them by time into one file."""

    def __init__(self, unix_offset_s: float = 0.0) -> None:
        self.offset = unix_offset_s  # added to the expert's clock (s) for times shown
        self._msgs: list[tuple[int, str, bytes]] = []
        self._schemas: dict[str, tuple[str, dict[str, Any]]] = {}

    def _add(self, topic: str, schema: str, js: dict[str, Any], t: float, msg: dict) -> None:
        self._schemas.setdefault(topic, (schema, js))
        data = json.dumps(msg, separators=(",", ":")).encode()
        self._msgs.append((_ns(t + self.offset), topic, data))

    def video(self, stream: str, frames: list[tuple[float, bytes, bool]]) -> None:
        """H.264 frames ``(t, Annex B bytes, keyframe)`` of ``stream`` ('us' or 'pov')."""
        for t, data, _key in frames:
            msg = {
                "timestamp": _stamp(t + self.offset),
                "frame_id": stream,
                "data": base64.b64encode(data).decode("ascii"),
                "format": "h264",
            }
            self._add(VIDEO_OUT[stream], VIDEO_SCHEMA, VIDEO_JSON_SCHEMA, t, msg)

    def poses(self, which: str, track: PoseTrack, start: float, stop: float) -> None:
        """``which`` 'virtual' or 'real': the track's poses in [start, stop]."""
        sel = (track.t >= start) & (track.t <= stop)
        for t, p, q in zip(track.t[sel], track.position[sel], track.quaternion[sel], strict=True):
            msg = {
                "timestamp": _stamp(float(t) + self.offset),
                "frame_id": "patient",
                "pose": {
                    "position": dict(zip("xyz", map(float, p), strict=True)),
                    "orientation": dict(zip("xyzw", map(float, q), strict=True)),
                },
            }
            self._add(POSES_OUT[which], POSE_SCHEMA, POSE_JSON_SCHEMA, float(t), msg)

    def force(self, topic: str, t: np.ndarray, f: np.ndarray, start: float, stop: float) -> None:
        """One message per force sample in [start, stop] (the recording's fields, unpacked)."""
        spec = replace(CHANNELS[topic], batch=False)
        js = json_schema(spec)
        sel = (t >= start) & (t <= stop)
        for tt, ff in zip(t[sel], f[sel], strict=True):
            msg = {"t": round(float(tt), 6), "force": [round(float(x), 7) for x in ff]}
            self._add(topic, spec.schema_name, js, float(tt), msg)

    def event(self, topic: str, t: float, msg: dict[str, Any]) -> None:
        spec = CHANNELS[topic]
        self._add(topic, spec.schema_name, json_schema(spec), t, msg)

    def write(self, path: Path, metadata: dict[str, str]) -> int:
        """Write the file (replacing an earlier export); the number of messages."""
        self._msgs.sort(key=lambda m: m[0])
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as stream:
            w = Writer(stream, compression=CompressionType.ZSTD)
            w.start(profile="", library="humantele export")
            w.add_metadata("humantele.export", metadata)
            ids: dict[str, int] = {}
            for topic, (schema, js) in self._schemas.items():
                sid = w.register_schema(schema, "jsonschema", json.dumps(js).encode())
                ids[topic] = w.register_channel(topic, "json", sid)
            seq: dict[str, int] = {}
            for t_ns, topic, data in self._msgs:
                n = seq.get(topic, 0)
                seq[topic] = n + 1
                w.add_message(ids[topic], t_ns, data, t_ns, n)
            w.finish()
        return len(self._msgs)
