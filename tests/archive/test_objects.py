"""The DICOM objects: what a reader needs to place and measure them, checked with pydicom
and with dciodvfy (Debian dicom3tools), a validator the project did not write."""

import shutil
import subprocess
import time

import av
import cv2
import numpy as np
import pytest
from exam_helpers import PATIENT, frame, jpeg
from pydicom import dcmread
from pydicom.uid import JPEGBaseline8Bit, UltrasoundImageStorage, UltrasoundMultiFrameImageStorage

from humantele.archive import objects as obj
from humantele.archive.exam import ExamStore
from humantele.archive.queue import to_bytes
from humantele.expert.console.jpeg import I420Jpeg

EQ = obj.Equipment(institution="Clinic North", operator="Novice^Nina",
                   performing_physician="Expert^Sam")  # fmt: skip
SCALE = obj.Scale((0.25, 0.2), 12.0)


@pytest.fixture
def exam(tmp_path):
    store = ExamStore(tmp_path)
    store.begin(PATIENT, 1_790_000_000.0)
    return store


def place(store, scan="scan 1"):
    uid, number = store.series_for(scan)
    return obj.Placement(store.exam, uid, number, store.next_instance())


def roundtrip(ds):
    import io

    return dcmread(io.BytesIO(to_bytes(ds)))


def test_a_still_is_an_us_image_of_the_very_jpeg_with_its_scale_and_utc_time(exam):
    data = jpeg(1)
    t = 1_790_000_123.25  # Unix s
    ds = roundtrip(obj.us_image(data, t, SCALE, place(exam), EQ))
    assert ds.SOPClassUID == UltrasoundImageStorage
    assert ds.file_meta.TransferSyntaxUID == JPEGBaseline8Bit
    assert ds.Modality == "US" and ds.Manufacturer == "humantele"
    assert (ds.Rows, ds.Columns, ds.SamplesPerPixel) == (480, 640, 3)
    assert ds.PatientID == "HT-0042" and str(ds.PatientName) == "Zyxwvutson^Quirinella"
    assert ds.AccessionNumber == "ACC7731" and ds.PatientSex == "F"
    assert ds.PatientBirthDate == "19710304"
    # the pixels are the console's JPEG itself (no second lossy pass)
    from pydicom.encaps import generate_frames

    assert next(generate_frames(ds.PixelData, number_of_frames=1)).rstrip(b"\0") == data.rstrip(
        b"\0"
    )
    # 2026-09-21 ... UTC, from the Unix time
    assert ds.AcquisitionDateTime.startswith(time.strftime("%Y%m%d%H%M%S", time.gmtime(t)))
    assert ds.TimezoneOffsetFromUTC == "+0000"
    region = ds.SequenceOfUltrasoundRegions[0]
    assert region.PhysicalUnitsXDirection == 3 and region.PhysicalUnitsYDirection == 3
    assert region.PhysicalDeltaX == pytest.approx(0.02)  # cm per column (0.2 mm)
    assert region.PhysicalDeltaY == pytest.approx(0.025)  # cm per row (0.25 mm)
    assert (region.RegionLocationMaxX1, region.RegionLocationMaxY1) == (639, 479)
    assert region.ReferencePixelY0 == 12
    assert ds.PerformingPhysicianName == "Expert^Sam" and ds.OperatorsName == "Novice^Nina"
    assert ds.InstitutionName == "Clinic North"
    # a reader measuring with the region's deltas gets what the console's calipers get
    a, b = (100, 50), (400, 250)
    reader_mm = 10 * np.hypot((b[0] - a[0]) * region.PhysicalDeltaX,
                              (b[1] - a[1]) * region.PhysicalDeltaY)  # fmt: skip
    console_mm = np.hypot((b[0] - a[0]) * 0.2, (b[1] - a[1]) * 0.25)
    assert reader_mm == pytest.approx(console_mm)


def test_no_pixel_spacing_means_no_region_rather_than_a_wrong_one(exam):
    ds = obj.us_image(jpeg(), 1.79e9, obj.Scale(), place(exam), EQ)
    assert "SequenceOfUltrasoundRegions" not in ds


def test_the_console_s_own_i420_jpeg_is_accepted_and_decodes_the_same(exam):
    yuv = cv2.cvtColor(frame(2), cv2.COLOR_BGR2YUV_I420)
    av_frame = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
    data = I420Jpeg(88).encode(av_frame)  # libavcodec's MJPEG: a COM marker, no JFIF APP0
    assert obj.jpeg_shape(data) == (480, 640, 3)
    ds = roundtrip(obj.us_image(data, 1.79e9, SCALE, place(exam), EQ))
    rgb = ds.pixel_array  # pydicom's own decoder, YBR_FULL_422 converted to RGB
    seen = cv2.cvtColor(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR),
                        cv2.COLOR_BGR2RGB)  # fmt: skip
    assert rgb.shape == seen.shape and np.abs(rgb.astype(float) - seen).mean() < 2.0


def test_a_bad_frame_is_refused_with_a_reason(exam):
    with pytest.raises(ValueError, match="JPEG"):
        obj.us_image(b"\xff\xd8 not a jpeg", 1.79e9, SCALE, place(exam), EQ)
    ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError):
        obj.us_image(png.tobytes(), 1.79e9, SCALE, place(exam), EQ)


def test_a_clip_has_its_frames_and_their_capture_intervals(exam):
    times = [1_790_000_000.0 + t for t in (0.0, 0.05, 0.11, 0.15)]
    ds = roundtrip(obj.us_multiframe([jpeg(i) for i in range(4)], times, SCALE, place(exam), EQ))
    assert ds.SOPClassUID == UltrasoundMultiFrameImageStorage
    assert ds.NumberOfFrames == 4
    assert ds.FrameIncrementPointer == 0x00181065
    assert [float(x) for x in ds.FrameTimeVector] == pytest.approx([0, 50, 60, 40], abs=1e-3)
    with pytest.raises(ValueError, match="increase"):
        obj.us_multiframe([jpeg(0), jpeg(1)], [5.0, 5.0], SCALE, place(exam), EQ)


def test_the_sr_measures_the_caliper_on_the_image_it_references(exam):
    image = obj.us_image(jpeg(), 1.79e9, SCALE, place(exam), EQ)
    c = obj.Caliper((100.0, 200.0), (300.0, 200.0), 40.0)
    sr = roundtrip(obj.measurement_report([image], [(0, c)], place(exam, "reports"), EQ))
    assert sr.StudyInstanceUID == image.StudyInstanceUID and sr.PatientID == "HT-0042"
    evidence = sr.CurrentRequestedProcedureEvidenceSequence[0].ReferencedSeriesSequence[0]
    assert evidence.ReferencedSOPSequence[0].ReferencedSOPInstanceUID == image.SOPInstanceUID
    import highdicom as hd

    report = hd.sr.Comprehensive3DSR.from_dataset(sr)
    groups = report.content.get_planar_roi_measurement_groups()
    assert len(groups) == 1
    m = groups[0].get_measurements()[0]
    assert m.value == pytest.approx(40.0) and m.unit.value == "mm"
    region = groups[0].roi
    assert region.ContentSequence[0].ReferencedSOPSequence[0].ReferencedSOPInstanceUID == (
        image.SOPInstanceUID
    )
    assert np.allclose(region.value, [[100.5, 200.5], [300.5, 200.5]])


def test_marks_go_in_a_presentation_state_not_in_the_image(exam):
    image = obj.us_image(jpeg(), 1.79e9, SCALE, place(exam), EQ)
    before = bytes(image.PixelData)
    ps = obj.presentation_state(
        image,
        [obj.Caliper((1, 2), (30, 40), 9.0)],
        [obj.Note((5, 6), "gallbladder")],
        place(exam, "reports"),
        EQ,
    )
    assert bytes(image.PixelData) == before
    ann = ps.GraphicAnnotationSequence[0]
    assert ann.ReferencedImageSequence[0].ReferencedSOPInstanceUID == image.SOPInstanceUID
    assert {t.UnformattedTextValue for t in ann.TextObjectSequence} == {"9.0 mm", "gallbladder"}


NO_DCIODVFY = "dciodvfy (Debian package dicom3tools) is not installed; CI has it"


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason=NO_DCIODVFY)
def test_dciodvfy_finds_no_error_in_any_object(exam, tmp_path):
    image = obj.us_image(jpeg(), 1.79e9, SCALE, place(exam), EQ)
    clip = obj.us_multiframe([jpeg(i) for i in range(3)], [1.79e9, 1.79e9 + 0.05, 1.79e9 + 0.1],
                             SCALE, place(exam), EQ)  # fmt: skip
    c = obj.Caliper((10, 20), (30, 40), 5.0)
    sr = obj.measurement_report([image], [(0, c)], place(exam, "reports"), EQ)
    ps = obj.presentation_state(image, [c], [obj.Note((5, 5), "x")], place(exam, "reports"), EQ)
    for name, ds in {"image": image, "clip": clip, "sr": sr, "ps": ps}.items():
        path = tmp_path / f"{name}.dcm"
        path.write_bytes(to_bytes(ds))
        out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True)
        text = out.stdout + out.stderr
        errors = [line for line in text.splitlines() if line.startswith("Error")]
        assert errors == [], f"{name}: {text}"
