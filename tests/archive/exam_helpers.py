"""Shared by the archive tests: a patient, JPEG frames like the console's, an archive config."""

from __future__ import annotations

import datetime as dt

import cv2
import numpy as np

from humantele.archive.exam import Patient

PATIENT = Patient(
    patient_id="HT-0042", family_name="Zyxwvutson", given_name="Quirinella",
    birth_date=dt.date(1971, 3, 4), sex="F", accession_number="ACC7731",
)  # fmt: skip
SECRET_NAME = "Zyxwvutson"  # appears nowhere but in the DICOM objects and their queue


def frame(i: int = 0, w: int = 640, h: int = 480) -> np.ndarray:
    """A BGR picture like an ultrasound frame: speckle, a dark cyst moving with ``i``."""
    rng = np.random.default_rng(i)
    img = (rng.random((h, w)) * 90 + 40).astype(np.uint8)
    cv2.circle(img, (200 + 5 * i, 240), 60, 10, -1)
    cv2.rectangle(img, (400, 100), (500, 380), 220, -1)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def jpeg(i: int = 0, quality: int = 88) -> bytes:
    ok, buf = cv2.imencode(".jpg", frame(i), [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()
