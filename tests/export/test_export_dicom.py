"""``humantele export --dicom``: the captures of an expert recording (its attached JPEGs and
console events) become the archive's objects, with the recording's clock moved to UTC; a
scan's ultrasound stream becomes a multi-frame image."""

import sys
import time
from pathlib import Path

import pytest
from pydicom import dcmread
from video_fixtures import session_with_video

from humantele.cli import main
from humantele.recording import Recorder

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "archive"))
from exam_helpers import jpeg  # noqa: E402


def test_the_captures_and_calipers_of_a_recording_become_dicom(tmp_path, capsys):
    rec = Recorder(tmp_path / "s.expert.mcap", "expert")
    sid = rec.metadata["session_id"]
    offset = float(rec.metadata["clock_unix_offset_s"])
    still = jpeg(4)
    rec.write("/expert/console", 50.0, {"event": "caliper", "seq": 7, "t_capture": 49.9,
                                        "mm": 12.5, "a_px": [1, 2], "b_px": [40, 50]})  # fmt: skip
    rec.write("/expert/console", 50.1, {"event": "annotation", "seq": 7, "t_capture": 49.9,
                                        "text": "cyst", "a_px": [5, 5]})  # fmt: skip
    rec.write("/expert/console", 50.2, {"event": "capture", "seq": 7, "t_capture": 49.9,
                                        "file": "capture-x-000007.jpg"})  # fmt: skip
    rec.attach("capture-x-000007.jpg", "image/jpeg", still, 49.9)
    rec.close()
    out = tmp_path / "out"
    args = ["export", str(tmp_path / "s.expert.mcap"), "--dicom", "--out", str(out),
            "--pixel-spacing-mm", "0.2", "0.25", "--patient-name", "Doe^Jo"]  # fmt: skip
    assert main(args) == 0
    files = sorted((out / f"{sid}_dicom").iterdir())
    assert [f.name.split("_")[1] for f in files] == ["image.dcm", "sr.dcm", "pr.dcm"]
    image = dcmread(files[0])
    assert image.PatientID == sid and str(image.PatientName) == "Doe^Jo"  # pseudonymous id
    assert image.AcquisitionDateTime.startswith(
        time.strftime("%Y%m%d%H%M%S", time.gmtime(49.9 + offset)))  # fmt: skip
    assert image.SequenceOfUltrasoundRegions[0].PhysicalDeltaX == pytest.approx(0.025)
    sr = dcmread(files[1])
    assert sr.StudyInstanceUID == image.StudyInstanceUID
    assert "12.5" in str(sr.ContentSequence)


def test_a_scan_becomes_a_multi_frame_image(tmp_path, capsys):
    paths = session_with_video(tmp_path, n_scans=1, duration_s=4.0,
                               metadata={"clock_unix_offset_s": "1790000000.0"})  # fmt: skip
    out = tmp_path / "out"
    assert main(["export", *map(str, paths), "--dicom", "--dicom-scans", "--dicom-fps", "5",
                 "--out", str(out)]) == 0  # fmt: skip
    (scan,) = sorted((out / "vid01_dicom").iterdir())
    ds = dcmread(scan)
    assert ds.SOPClassUID.name == "Ultrasound Multi-frame Image Storage"
    assert ds.NumberOfFrames >= 2
    assert all(190 <= float(v) <= 260 for v in ds.FrameTimeVector[1:])  # ~ 1/5 s apart


def test_a_recording_without_its_clock_offset_is_left_out(tmp_path, capsys):
    paths = session_with_video(tmp_path, n_scans=1, duration_s=4.0)
    assert main(["export", *map(str, paths), "--dicom", "--out", str(tmp_path / "o")]) == 2
    assert "clock_unix_offset_s" in capsys.readouterr().err
