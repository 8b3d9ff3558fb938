"""Transcoding one stream of one scan: the recorded frames (VP8 or H.264, as received at the
expert) decoded with PyAV and encoded H.264 (libx264) into an MP4, and the same H.264 frames
kept, Annex B, for Foxglove's ``foxglove.CompressedVideo``.

Runs in a worker process (:func:`transcode` takes and returns plain data). Decoding starts at
the last keyframe at or before the clip's first frame (frames before it are decoded, not
written); a frame that fails to decode is counted and skipped (the decoder keeps its state,
as aiortc's does). The H.264 stream has no B-frames (Foxglove cannot play them), a keyframe
every ``gop_s`` seconds, and each keyframe message carries the SPS and PPS.
"""

from __future__ import annotations

import fractions
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np

log = logging.getLogger(__name__)
TIME_BASE = fractions.Fraction(1, 1000)  # ms: the MP4's and the encoder's time base


@dataclass
class EncodedFrame:
    """A recorded frame: ``t`` its time (s, expert clock: capture time where known),
    ``data`` the encoded bytes, ``keyframe`` whether it decodes on its own."""

    t: float
    data: bytes
    keyframe: bool


@dataclass
class TranscodeJob:
    """One clip: ``frames`` in arrival (decode) order, the clip ``start``/``stop`` (s, same
    clock as the frames' ``t``), the recorded ``codec`` and where the MP4 goes."""

    name: str
    frames: list[EncodedFrame]
    start: float
    stop: float
    codec: str
    mp4: Path
    crf: int = 20
    gop_s: float = 2.0
    keep_frames: tuple[int, ...] = ()  # clip frame indices whose decoded pictures to return


@dataclass
class TranscodeResult:
    """What :func:`transcode` made: the H.264 frames ``(t, data Annex B, keyframe)``, counts,
    and the decoded source pictures asked for in ``keep_frames`` (BGR, for checks)."""

    name: str
    h264: list[tuple[float, bytes, bool]] = field(default_factory=list)
    frames_in: int = 0  # recorded frames in the clip
    frames_out: int = 0  # frames written to the MP4
    decode_errors: int = 0
    skipped_before_keyframe: int = 0
    size: tuple[int, int] | None = None
    duration_s: float = 0.0
    kept: dict[int, np.ndarray] = field(default_factory=dict)
    error: str | None = None


def first_decodable(frames: list[EncodedFrame], start: float) -> int | None:
    """Index of the keyframe decoding should start at: the last one at or before the first
    frame at/after ``start``, else the first one after it; None when there is none."""
    first = next((i for i, f in enumerate(frames) if f.t >= start), None)
    if first is None:
        return None
    before = [i for i in range(first + 1) if frames[i].keyframe]
    if before:
        return before[-1]
    return next((i for i in range(first, len(frames)) if frames[i].keyframe), None)


def _annexb_headers(extradata: bytes | None) -> bytes:
    """libx264's SPS and PPS (its extradata, Annex B when the container wants global headers)."""
    if not extradata:
        return b""
    return (
        bytes(extradata)
        if extradata[:3] == b"\x00\x00\x01" or extradata[:4] == b"\x00\x00\x00\x01"
        else b""
    )


def _has_sps(data: bytes) -> bool:
    i = data.find(b"\x00\x00\x01")
    while i != -1 and i + 3 < len(data):
        if data[i + 3] & 0x1F == 7:
            return True
        i = data.find(b"\x00\x00\x01", i + 3)
    return False


def transcode(job: TranscodeJob, progress: Callable[[int], None] | None = None) -> TranscodeResult:
    """Decode ``job.frames`` in the clip and write them H.264 to ``job.mp4`` (see module doc).
    Never raises: a failure is in ``error`` (the MP4 then may be partial or absent)."""
    res = TranscodeResult(job.name)
    try:
        _transcode(job, res, progress)
    except (av.FFmpegError, OSError, ValueError) as exc:
        res.error = f"{type(exc).__name__}: {exc}"
    return res


def _transcode(
    job: TranscodeJob, res: TranscodeResult, progress: Callable[[int], None] | None
) -> None:
    frames = job.frames
    in_clip = [f for f in frames if job.start <= f.t <= job.stop]
    res.frames_in = len(in_clip)
    begin = first_decodable(frames, job.start)
    if begin is None or not in_clip:
        res.skipped_before_keyframe = len(in_clip)
        return
    decoder = av.CodecContext.create(job.codec, "r")
    out: av.container.OutputContainer | None = None
    stream = None
    headers = b""
    last_pts = -1
    t0: float | None = None
    clip_index = 0
    done = 0

    def emit(packets: list[av.Packet]) -> None:
        nonlocal headers
        assert out is not None and stream is not None
        for p in packets:
            data = bytes(p)
            if p.is_keyframe and not _has_sps(data):
                if not headers:
                    headers = _annexb_headers(stream.codec_context.extradata)
                data = headers + data
            t = (float(p.pts) * float(TIME_BASE) if p.pts is not None else 0.0) + (t0 or 0.0)
            res.h264.append((t, data, bool(p.is_keyframe)))
            out.mux(p)

    try:
        for f in frames[begin:]:
            if f.t > job.stop:
                break
            try:
                decoded = decoder.decode(av.Packet(f.data))
            except av.FFmpegError:
                res.decode_errors += 1
                continue
            if f.t < job.start:
                continue  # decoded for the reference, not shown
            done += 1
            if progress is not None and done % 10 == 0:
                progress(10)
            for pic in decoded:
                if out is None:
                    job.mp4.parent.mkdir(parents=True, exist_ok=True)
                    out = av.open(str(job.mp4), "w")
                    stream = out.add_stream(
                        "libx264",
                        options={
                            "preset": "veryfast",
                            "crf": str(job.crf),
                            "bf": "0",
                            "g": str(max(1, int(job.gop_s * 20))),
                        },
                    )
                    stream.width, stream.height = pic.width, pic.height
                    stream.pix_fmt = "yuv420p"
                    stream.time_base = TIME_BASE
                    stream.codec_context.time_base = TIME_BASE
                    stream.codec_context.max_b_frames = 0
                    stream.thread_count = 1
                    res.size = (pic.width, pic.height)
                    t0 = f.t
                pts = max(int(round((f.t - (t0 or f.t)) / float(TIME_BASE))), last_pts + 1)
                last_pts = pts
                if clip_index in job.keep_frames:
                    res.kept[clip_index] = pic.to_ndarray(format="bgr24")
                clip_index += 1
                if (pic.width, pic.height) != res.size:
                    pic = pic.reformat(width=res.size[0], height=res.size[1])
                frame = pic.reformat(format="yuv420p")
                frame.pts, frame.time_base = pts, TIME_BASE
                frame.pict_type = av.video.frame.PictureType.NONE
                emit(stream.encode(frame))
                res.frames_out += 1
        if out is not None and stream is not None:
            emit(stream.encode(None))
            res.duration_s = last_pts * float(TIME_BASE)
    finally:
        if out is not None:
            out.close()
        if progress is not None and done % 10:
            progress(done % 10)
    res.skipped_before_keyframe = max(0, res.frames_in - res.frames_out - res.decode_errors)
