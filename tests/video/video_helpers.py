"""Scenes and measurements shared by the video tests."""

from __future__ import annotations

import math

import cv2
import numpy as np

from humantele.geometry import Pose
from humantele.video.scene import DEFAULT_PATIENT, SceneSnapshot, look_at, probe_on_skin

P = DEFAULT_PATIENT
A = float(P.semi_axes[2])  # lateral semi-axis (m)
B = float(P.semi_axes[1])  # vertical semi-axis (m)
KIDNEY = (0.12, -0.2 * B, 0.45 * A)  # the default phantom's kidney centre, patient frame
SAGITTAL = math.pi / 2


def on_kidney(**kw) -> Pose:
    """The probe on the skin above the kidney centre, sagittal, pressed 8 mm."""
    return probe_on_skin(P, (KIDNEY[0], 0.0, KIDNEY[2]), rotate_rad=SAGITTAL, **kw)


def snap(tip: Pose | None, force: float = 5.0, head: Pose | None = None, virtual=None):
    return SceneSnapshot(0.0, P, tip, force, head, virtual)


def head_over(tip: Pose) -> Pose:
    """The POV camera 0.5 m from the probe, above and to the patient's right, looking at it."""
    eye = P.T_world_patient.apply((0.02, 0.45, 0.42))
    return look_at(eye, tip.position)


def grey(frame) -> np.ndarray:
    return frame.image[..., 0].astype(np.float64)


def window_mean(img: np.ndarray, row: float, col: float, half: int) -> float:
    r, c = int(round(row)), int(round(col))
    return float(img[r - half : r + half + 1, c - half : c + half + 1].mean())


def highpass(img: np.ndarray) -> np.ndarray:
    """The speckle: the image minus its 15 px local mean."""
    return img - cv2.blur(img, (15, 15))


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
