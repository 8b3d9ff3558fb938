"""The exam's DICOM objects, written with pydicom and highdicom (no DICOM encoding by hand).

- a captured still: **Ultrasound Image** (single frame); a captured clip or a whole scan:
  **Ultrasound Multi-frame Image**, the frames' times in the Frame Time Vector (ms, from the
  capture times). Pixels are **JPEG baseline** (1.2.840.10008.1.2.4.50): the still is the
  very JPEG the sonographer saw on the console, encapsulated as it is (no second lossy
  pass), and every PACS and viewer decodes it (docs/archive.md: why not MPEG-4 AVC);
- the **Sequence of Ultrasound Regions**: one 2D tissue region over the whole image, its
  physical delta X/Y in cm per pixel from the scanner's pixel spacing (the console's
  calipers use the same, ``[expert.console] us_pixel_spacing_mm`` or the follower's
  ``UsScale``), depth 0 at the reference pixel's row;
- the calipers: a **Comprehensive 3D SR** with highdicom's TID 1500 Measurement Report, one
  planar ROI (the caliper's two points, a POLYLINE on the image) with its Length in mm each;
- calipers and notes drawn as a **Color Softcopy Presentation State** (the captures are
  colour JPEGs: a GSPS applies to grayscale images only), never into the original pixels.

Times: the capture times are on the expert's clock; ``unix_offset_s`` moves them to Unix
time and the objects carry UTC (Timezone Offset From UTC +0000).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import highdicom as hd
import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.sr.codedict import codes
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    JPEGBaseline8Bit,
    UltrasoundImageStorage,
    UltrasoundMultiFrameImageStorage,
    generate_uid,
)

from humantele.archive.exam import Exam

MANUFACTURER = "humantele"
MODEL = "humantele tele-ultrasound"
JPEG_METHOD = "ISO_10918_1"
_PHYSICAL_CM = 3  # Physical Units X/Y Direction: 3 = cm (PS3.3 C.8.5.5.1.15)


@dataclass(frozen=True)
class Equipment:
    """Who and where (``[expert.archive]``): the remote scan's people and places."""

    station_name: str = "humantele"
    institution: str = ""  # the place the patient is scanned (the clinic)
    operator: str = ""  # who holds the probe (the follower)
    performing_physician: str = ""  # the expert sonographer
    software: str = "0.1.0"


@dataclass(frozen=True)
class Placement:
    """Where an object goes in the exam: its series and instance number."""

    exam: Exam
    series_uid: str
    series_number: int
    instance_number: int
    series_description: str = ""
    sop_instance_uid: str = field(default_factory=generate_uid)


@dataclass(frozen=True)
class Scale:
    """The ultrasound image's scale: (row, col) mm per pixel and the row of depth 0."""

    pixel_spacing_mm: tuple[float, float] | None = None
    depth_origin_row: float | None = None


@dataclass(frozen=True)
class Caliper:
    """A caliper on an image: two points (x, y) in pixels (column, row), its length (mm)."""

    a_px: tuple[float, float]
    b_px: tuple[float, float]
    mm: float


@dataclass(frozen=True)
class Note:
    """A note placed on an image at (x, y) pixels."""

    at_px: tuple[float, float]
    text: str


def utc(unix_s: float) -> dt.datetime:
    return dt.datetime.fromtimestamp(unix_s, dt.UTC)


def _da(t: dt.datetime) -> str:
    return t.strftime("%Y%m%d")


def _tm(t: dt.datetime) -> str:
    return t.strftime("%H%M%S.%f")


def _dt(t: dt.datetime) -> str:
    return t.strftime("%Y%m%d%H%M%S.%f") + "+0000"


def jpeg_shape(jpeg: bytes) -> tuple[int, int, int]:
    """(rows, columns, components) of a baseline JPEG; ValueError if it does not decode."""
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a decodable JPEG")
    if jpeg[:2] != b"\xff\xd8" or b"\xff\xc0" not in jpeg[: min(len(jpeg), 4096)]:
        raise ValueError("not a baseline (SOF0) JPEG")
    return img.shape[0], img.shape[1], 1 if img.ndim == 2 else img.shape[2]


def _base(
    sop_class: str, where: Placement, eq: Equipment, t: dt.datetime, now: dt.datetime
) -> Dataset:
    """The modules every object of the exam shares: patient, study, series, equipment."""
    exam, p = where.exam, where.exam.patient
    study_t = utc(exam.started_unix)
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.MediaStorageSOPInstanceUID = where.sop_instance_uid
    ds.file_meta.TransferSyntaxUID = JPEGBaseline8Bit
    ds.file_meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = where.sop_instance_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = _da(now), _tm(now)
    ds.TimezoneOffsetFromUTC = "+0000"
    # Patient
    ds.PatientName = p.dicom_name
    ds.PatientID = p.patient_id
    ds.PatientBirthDate = "" if p.birth_date is None else p.birth_date.strftime("%Y%m%d")
    ds.PatientSex = p.sex
    # General Study
    ds.StudyInstanceUID = exam.study_instance_uid
    ds.StudyDate, ds.StudyTime = _da(study_t), _tm(study_t)
    ds.StudyID = exam.study_id
    ds.AccessionNumber = p.accession_number
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = p.requested_procedure or "Tele-ultrasound"
    # General Series
    ds.Modality = "US"
    ds.SeriesInstanceUID = where.series_uid
    ds.SeriesNumber = where.series_number
    ds.SeriesDate, ds.SeriesTime = _da(t), _tm(t)
    ds.Laterality = ""  # (2C) not a paired organ known here
    if where.series_description:
        ds.SeriesDescription = where.series_description
    if eq.operator:
        ds.OperatorsName = eq.operator
    if eq.performing_physician:
        ds.PerformingPhysicianName = eq.performing_physician
    # General Equipment
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MODEL
    ds.SoftwareVersions = eq.software
    ds.StationName = eq.station_name
    if eq.institution:
        ds.InstitutionName = eq.institution
    return ds


def _image_pixels(ds: Dataset, rows: int, cols: int, comps: int, raw: int, size: int) -> None:
    ds.Rows, ds.Columns = rows, cols
    ds.SamplesPerPixel = comps
    # A baseline JPEG of three components is YCbCr (JFIF), the chroma subsampled: PS3.5 8.2.1
    ds.PhotometricInterpretation = "YBR_FULL_422" if comps == 3 else "MONOCHROME2"
    if comps == 3:
        ds.PlanarConfiguration = 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    ds.LossyImageCompression = "01"
    ds.LossyImageCompressionRatio = f"{raw / max(1, size):.2f}"[:16]
    ds.LossyImageCompressionMethod = JPEG_METHOD


def _regions(rows: int, cols: int, scale: Scale) -> list[Dataset]:
    """The Sequence of Ultrasound Regions: one 2D tissue region over the image, calibrated
    when the pixel spacing is known (nothing otherwise: a reader then measures nothing)."""
    if scale.pixel_spacing_mm is None:
        return []
    row_mm, col_mm = scale.pixel_spacing_mm
    r = Dataset()
    r.RegionSpatialFormat = 1  # 2D (tissue or flow)
    r.RegionDataType = 1  # tissue
    r.RegionFlags = 0
    r.RegionLocationMinX0, r.RegionLocationMinY0 = 0, 0
    r.RegionLocationMaxX1, r.RegionLocationMaxY1 = cols - 1, rows - 1
    r.PhysicalUnitsXDirection = r.PhysicalUnitsYDirection = _PHYSICAL_CM
    r.PhysicalDeltaX = float(col_mm) / 10.0  # cm per pixel
    r.PhysicalDeltaY = float(row_mm) / 10.0
    if scale.depth_origin_row is not None:
        r.ReferencePixelX0 = int(cols // 2)
        r.ReferencePixelY0 = int(round(scale.depth_origin_row))
        r.ReferencePixelPhysicalValueX = 0.0
        r.ReferencePixelPhysicalValueY = 0.0  # depth 0 (the skin under the probe's face)
    return [r]


def us_image(
    jpeg: bytes, t_unix: float, scale: Scale, where: Placement, eq: Equipment,
    now_unix: float | None = None,
) -> Dataset:  # fmt: skip
    """An Ultrasound Image of a captured still (``jpeg``: the JPEG the console showed;
    ``t_unix``: its capture time, Unix s)."""
    rows, cols, comps = jpeg_shape(jpeg)
    t = utc(t_unix)
    ds = _base(UltrasoundImageStorage, where, eq, t, utc(now_unix or t_unix))
    _image_common(ds, where, t, "ORIGINAL", rows, cols, comps, scale)
    _image_pixels(ds, rows, cols, comps, rows * cols * comps, len(jpeg))
    ds.PixelData = encapsulate([jpeg])
    ds["PixelData"].VR = "OB"
    return ds


def us_multiframe(
    jpegs: Sequence[bytes], times_unix: Sequence[float], scale: Scale, where: Placement,
    eq: Equipment, now_unix: float | None = None,
) -> Dataset:  # fmt: skip
    """An Ultrasound Multi-frame Image of a clip or a scan (``jpegs``: its frames, oldest
    first; ``times_unix``: their capture times). ValueError if the frames differ in size, or
    their times are not increasing."""
    if len(jpegs) < 2 or len(jpegs) != len(times_unix):
        raise ValueError("a clip needs 2 or more frames, each with its time")
    shapes = {jpeg_shape(j) for j in jpegs}
    if len(shapes) != 1:
        raise ValueError(f"the clip's frames differ in size: {sorted(shapes)}")
    deltas = np.diff(np.asarray(times_unix, dtype=float))
    if not np.all(np.isfinite(deltas)) or np.any(deltas <= 0):
        raise ValueError("the clip's frame times must increase")
    rows, cols, comps = shapes.pop()
    t = utc(times_unix[0])
    ds = _base(UltrasoundMultiFrameImageStorage, where, eq, t, utc(now_unix or times_unix[-1]))
    _image_common(ds, where, t, "ORIGINAL", rows, cols, comps, scale)
    _image_pixels(ds, rows, cols, comps, rows * cols * comps * len(jpegs), sum(map(len, jpegs)))
    ds.NumberOfFrames = len(jpegs)
    ds.FrameIncrementPointer = 0x00181065  # Frame Time Vector
    ds.FrameTimeVector = [0.0] + [round(float(d) * 1000.0, 3) for d in deltas]  # ms
    ds.ActualFrameDuration = int(round(float(np.median(deltas)) * 1000.0))
    ds.CineRate = int(round(1.0 / float(np.mean(deltas))))
    ds.EffectiveDuration = round(float(times_unix[-1] - times_unix[0]), 3)
    ds.PixelData = encapsulate(list(jpegs), has_bot=True)
    ds["PixelData"].VR = "OB"
    return ds


def _image_common(
    ds: Dataset, where: Placement, t: dt.datetime, kind: str, rows: int, cols: int,
    comps: int, scale: Scale,
) -> None:  # fmt: skip
    ds.InstanceNumber = where.instance_number
    ds.PatientOrientation = ""
    ds.ImageType = [kind, "PRIMARY"]
    ds.ContentDate, ds.ContentTime = _da(t), _tm(t)
    ds.AcquisitionDate, ds.AcquisitionTime = _da(t), _tm(t)
    ds.AcquisitionDateTime = _dt(t)
    ds.BurnedInAnnotation = "NO"
    regions = _regions(rows, cols, scale)
    if regions:
        ds.SequenceOfUltrasoundRegions = regions


def measurement_report(
    images: Sequence[Dataset], calipers: Sequence[tuple[int, Caliper]], where: Placement,
    eq: Equipment, observer: str = "",
) -> Dataset:  # fmt: skip
    """The calipers as a Comprehensive 3D SR, highdicom's TID 1500 Measurement Report: one
    planar ROI per caliper (``(i, caliper)``: ``images[i]`` it was taken on), its region the
    caliper's line on that image, its Length (mm). ValueError if there is none."""
    if not calipers:
        raise ValueError("no calipers to report")
    groups = []
    for k, (i, c) in enumerate(calipers, start=1):
        region = hd.sr.ImageRegion(
            graphic_type=hd.sr.GraphicTypeValues.POLYLINE,
            graphic_data=np.array([c.a_px, c.b_px], dtype=float) + 0.5,  # pixel centres
            source_image=hd.sr.SourceImageForRegion.from_source_image(images[i]),
        )
        groups.append(
            hd.sr.PlanarROIMeasurementsAndQualitativeEvaluations(
                tracking_identifier=hd.sr.TrackingIdentifier(
                    uid=generate_uid(), identifier=f"caliper {k}"
                ),
                referenced_region=region,
                measurements=[
                    hd.sr.Measurement(
                        name=codes.SCT.Length, value=float(c.mm), unit=codes.UCUM.Millimeter
                    )
                ],
            )
        )
    observer_ctx = hd.sr.ObservationContext(
        observer_person_context=hd.sr.ObserverContext(
            observer_type=codes.DCM.Person,
            observer_identifying_attributes=hd.sr.PersonObserverIdentifyingAttributes(
                name=observer or "sonographer^"
            ),
        )
    )
    report = hd.sr.MeasurementReport(
        observation_context=observer_ctx,
        procedure_reported=codes.SCT.Ultrasonography,
        imaging_measurements=groups,
    )
    sr = hd.sr.Comprehensive3DSR(
        evidence=list(images),
        content=report,
        series_instance_uid=where.series_uid,
        series_number=where.series_number,
        sop_instance_uid=where.sop_instance_uid,
        instance_number=where.instance_number,
        manufacturer=MANUFACTURER,
        institution_name=eq.institution or None,
        is_complete=True,
    )
    sr.TimezoneOffsetFromUTC = "+0000"
    sr.ManufacturerModelName = MODEL
    sr.SoftwareVersions = eq.software
    return sr


def srgb_profile() -> bytes:
    """An sRGB ICC profile (littleCMS's, through Pillow) declared an input device's
    ('scnr': the images come from the scanner, which DICOM's presentation state asks)."""
    from PIL import ImageCms

    icc = bytearray(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    icc[12:16] = b"scnr"  # profile/device class (ICC.1 7.2.5)
    icc[84:100] = bytes(16)  # profile ID: none (it would cover the changed header)
    return bytes(icc)


def presentation_state(
    image: Dataset, calipers: Sequence[Caliper], notes: Sequence[Note], where: Placement,
    eq: Equipment,
) -> Dataset:  # fmt: skip
    """The calipers (a line and its length) and notes on ``image`` as a Color Softcopy
    Presentation State (the original pixels stay as they are)."""
    layer = hd.pr.GraphicLayer(layer_name="MEASUREMENTS", order=1)
    objects, texts = [], []
    for c in calipers:
        pts = np.array([c.a_px, c.b_px], dtype=float) + 0.5
        objects.append(hd.pr.GraphicObject(hd.pr.GraphicTypeValues.POLYLINE, pts,
                                           units=hd.pr.AnnotationUnitsValues.PIXEL))  # fmt: skip
        texts.append(hd.pr.TextObject(f"{c.mm:.1f} mm", units=hd.pr.AnnotationUnitsValues.PIXEL,
                                      anchor_point=tuple(pts[1])))  # fmt: skip
    for n in notes:
        at = (n.at_px[0] + 0.5, n.at_px[1] + 0.5)
        texts.append(hd.pr.TextObject(n.text[:64], units=hd.pr.AnnotationUnitsValues.PIXEL,
                                      anchor_point=at))  # fmt: skip
    annotation = hd.pr.GraphicAnnotation(
        referenced_images=[image], graphic_layer=layer,
        graphic_objects=objects or None, text_objects=texts or None,
    )  # fmt: skip
    ps = hd.pr.ColorSoftcopyPresentationState(
        referenced_images=[image],
        series_instance_uid=where.series_uid,
        series_number=where.series_number,
        sop_instance_uid=where.sop_instance_uid,
        instance_number=where.instance_number,
        manufacturer=MANUFACTURER,
        manufacturer_model_name=MODEL,
        software_versions=eq.software,
        device_serial_number="0",
        content_label="MEASUREMENTS",
        content_description="calipers and notes",
        graphic_layers=[layer],
        graphic_annotations=[annotation],
        institution_name=eq.institution or None,
        icc_profile=srgb_profile(),
    )
    ps.TimezoneOffsetFromUTC = "+0000"
    ps.Laterality = ""
    return ps
