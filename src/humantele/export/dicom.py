"""``humantele export --dicom RECORDING...``: the same DICOM objects the expert sends to the
archive (:mod:`humantele.archive.objects`), made from a session's recording: each captured
still (the JPEG attached to the expert's recording) as an Ultrasound Image, its calipers as a
TID 1500 SR and its calipers and notes as a presentation state, and with ``--dicom-scans``
each scan's ultrasound stream as an Ultrasound Multi-frame Image (``--dicom-fps`` frames a
second). For studies (the patient is the recording's pseudonymous session id unless
``--patient-id`` says otherwise) and for exams whose archive was unreachable until after the
session. Written as Part 10 files in ``--out``/``SESSION_dicom/``; times from the recording's
``clock_unix_offset_s`` (a recording without it is left out: its dates would be wrong).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path
from typing import Any

import av
import cv2

from humantele.archive import objects as obj
from humantele.archive.exam import Exam, Patient
from humantele.archive.queue import to_bytes
from humantele.config import ConfigError
from humantele.recording.reader import RecordingReadError, read_recording


def add_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("DICOM (--dicom)")
    g.add_argument(
        "--dicom",
        action="store_true",
        help="write DICOM objects of the captures (and scans) instead of MP4/MCAP",
    )
    g.add_argument("--patient-id", default=None, help="default: the recording's session id")
    g.add_argument("--patient-name", default="", metavar="FAMILY^GIVEN")
    g.add_argument("--birth-date", default=None, metavar="YYYY-MM-DD")
    g.add_argument("--sex", default="", choices=["", "M", "F", "O"])
    g.add_argument("--accession", default="")
    g.add_argument(
        "--pixel-spacing-mm",
        type=float,
        nargs=2,
        default=None,
        metavar=("ROW", "COL"),
        help="the ultrasound's mm per pixel (calibration)",
    )
    g.add_argument("--depth-origin-row", type=float, default=None)
    g.add_argument(
        "--dicom-scans",
        action="store_true",
        help="also each scan's ultrasound as a multi-frame image",
    )
    g.add_argument("--dicom-fps", type=float, default=10.0,
                   help="frames a second kept of a scan (default 10)")  # fmt: skip


def _patient(args: argparse.Namespace, session_id: str) -> Patient:
    family, _, given = (args.patient_name or "").partition("^")
    try:
        born = None if not args.birth_date else dt.date.fromisoformat(args.birth_date)
        return Patient(patient_id=args.patient_id or session_id, family_name=family,
                       given_name=given, birth_date=born, sex=args.sex,
                       accession_number=args.accession)  # fmt: skip
    except ValueError as exc:
        raise ConfigError(f"--patient-*: {exc}") from exc


class _Writer:
    """Numbers the exam's series and instances and writes each object."""

    def __init__(self, exam: Exam, out: Path, eq: obj.Equipment) -> None:
        self.exam, self.out, self.eq = exam, out, eq
        self.n = 0
        out.mkdir(parents=True, exist_ok=True)

    def place(self, series: str, description: str = "") -> obj.Placement:
        from pydicom.uid import generate_uid

        if series not in self.exam.series:
            self.exam.series[series] = generate_uid()
            self.exam.series_numbers[series] = len(self.exam.series)
        self.exam.instances += 1
        return obj.Placement(self.exam, self.exam.series[series],
                             self.exam.series_numbers[series], self.exam.instances,
                             description)  # fmt: skip

    def write(self, ds: Any, kind: str) -> Path:
        self.n += 1
        path = self.out / f"{self.n:04d}_{kind}.dcm"
        path.write_bytes(to_bytes(ds))
        return path


def _attachments(path: Path) -> dict[str, bytes]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        try:
            return {a.name: a.data for a in make_reader(fh).iter_attachments()}
        except Exception:  # noqa: BLE001 - a damaged summary: the stills are then missing
            return {}


def _scan_frames(frames: list[Any], codec: str, lo: float, hi: float, fps: float,
                 quality: int = 88) -> list[tuple[float, bytes]]:  # fmt: skip
    """The scan's frames decoded, one every 1/fps s, as (t, JPEG)."""
    ctx = av.CodecContext.create("libvpx" if codec.lower() == "vp8" else codec.lower(), "r")
    out: list[tuple[float, bytes]] = []
    next_t = lo
    for f in frames:
        if f.t > hi:
            break
        try:
            decoded = ctx.decode(av.Packet(f.data))
        except av.error.FFmpegError:
            continue
        for d in decoded:
            if f.t < next_t:
                continue
            ok, buf = cv2.imencode(".jpg", d.to_ndarray(format="bgr24"),
                                   [cv2.IMWRITE_JPEG_QUALITY, quality])  # fmt: skip
            if ok:
                out.append((f.t, buf.tobytes()))
                next_t = f.t + 1.0 / fps
    return out


def run_dicom(args: argparse.Namespace) -> int:
    if args.dicom_fps <= 0 or args.dicom_fps > 100:
        raise ConfigError(f"--dicom-fps: must be within 0-100, got {args.dicom_fps}")
    scale = obj.Scale(tuple(args.pixel_spacing_mm) if args.pixel_spacing_mm else None,
                      args.depth_origin_row)  # fmt: skip
    written = 0
    sessions: dict[str, dict[str, Any]] = {}
    for p in args.recordings:
        try:
            rec = read_recording(p, ("/expert/console",))
        except RecordingReadError as exc:
            print(f"humantele export: {exc}; left out", file=sys.stderr)
            continue
        if rec.session.get("role") != "expert":
            continue
        sid = rec.session.get("session_id") or Path(p).stem
        try:
            offset = float(rec.session.get("clock_unix_offset_s", "nan"))
        except ValueError:
            offset = float("nan")
        if offset != offset:
            print(f"humantele export: {p}: no clock_unix_offset_s (its dates would be wrong); "
                  "left out", file=sys.stderr)  # fmt: skip
            continue
        sessions[sid] = {"path": Path(p), "events": rec.samples("/expert/console"),
                         "offset": offset}  # fmt: skip
    if not sessions:
        print("humantele export: no expert recording to make DICOM of", file=sys.stderr)
        return 2
    for sid, s in sessions.items():
        offset = s["offset"]
        patient = _patient(args, sid)
        from pydicom.uid import generate_uid

        events = s["events"]
        start = min((float(e["t"]) for e in events), default=0.0) + offset
        exam = Exam(patient=patient, study_instance_uid=generate_uid(),
                    study_id=time.strftime("%y%m%d%H%M", time.gmtime(start)),
                    started_unix=start)  # fmt: skip
        w = _Writer(exam, Path(args.out) / f"{sid}_dicom", obj.Equipment())
        attached = _attachments(s["path"])
        marks: dict[int, tuple[list, list]] = {}
        for e in events:
            seq = e.get("seq")
            if e.get("event") == "caliper" and "b_px" in e:
                marks.setdefault(seq, ([], []))[0].append(
                    obj.Caliper(tuple(e["a_px"]), tuple(e["b_px"]), float(e["mm"]))
                )
            elif e.get("event") == "annotation":
                marks.setdefault(seq, ([], []))[1].append(obj.Note(tuple(e["a_px"]), e["text"]))
        for e in events:
            if e.get("event") != "capture":
                continue
            jpeg = attached.get(e.get("file", ""))
            if jpeg is None:
                print(f"humantele export: {sid}: capture {e.get('file')} not attached; "
                      "left out", file=sys.stderr)  # fmt: skip
                continue
            image = obj.us_image(jpeg, float(e["t_capture"]) + offset, scale,
                                 w.place("captures", "captures"), w.eq)  # fmt: skip
            print(w.write(image, "image"))
            written += 1
            calipers, notes = marks.get(e.get("seq"), ([], []))
            if calipers:
                sr = obj.measurement_report([image], [(0, c) for c in calipers],
                                            w.place("reports", "measurements"), w.eq)  # fmt: skip
                print(w.write(sr, "sr"))
                written += 1
            if calipers or notes:
                pr = obj.presentation_state(image, calipers, notes,
                                            w.place("reports", "measurements"), w.eq)  # fmt: skip
                print(w.write(pr, "pr"))
                written += 1
        if args.dicom_scans:
            written += _scans(args, sid, w, scale, offset)
    return 0 if written else 1


def _scans(args: argparse.Namespace, sid: str, w: _Writer, scale: obj.Scale,
           offset: float) -> int:  # fmt: skip
    from humantele.export.source import load

    loaded, problems = load(args.recordings)
    for line in problems:
        print(f"humantele export: {line}", file=sys.stderr)
    n = 0
    for es in loaded:
        if es.session_id != sid or "us" not in es.video:
            continue
        stream = es.video["us"]
        for iv in es.scans:
            frames = _scan_frames(stream.frames, stream.codec, iv.start, iv.stop, args.dicom_fps)
            if len(frames) < 2:
                continue
            ds = obj.us_multiframe([j for _, j in frames], [t + offset for t, _ in frames],
                                   scale, w.place(f"scan {iv.scan}", f"scan {iv.scan}"),
                                   w.eq)  # fmt: skip
            print(f"{w.write(ds, 'scan')}: scan {iv.scan}, {len(frames)} frames")
            n += 1
    return n
