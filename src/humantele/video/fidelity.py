"""How close a decoded frame is to its source: PSNR and SSIM (OpenCV's implementations).

Both compare in grey (BT.601 luma, what the codecs code at full resolution); images are
(H, W, 3) BGR or (H, W) uint8 of the same size. ``region`` (row0, row1, col0, col1) limits
the comparison, e.g. to leave out the frame counter's corner.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

Region = tuple[int, int, int, int]


def _grey(image: NDArray[np.uint8], region: Region | None) -> NDArray[np.uint8]:
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY)
    if region is not None:
        r0, r1, c0, c1 = region
        image = image[r0:r1, c0:c1]
    return np.ascontiguousarray(image)


def _pair(a, b, region):
    if a.shape[:2] != b.shape[:2]:
        raise ValueError(f"images differ in size: {a.shape[:2]} and {b.shape[:2]}")
    return _grey(a, region), _grey(b, region)


def psnr(
    reference: NDArray[np.uint8], decoded: NDArray[np.uint8], region: Region | None = None
) -> float:
    """Peak signal-to-noise ratio in dB (``cv2.PSNR``, peak 255); inf for identical images."""
    a, b = _pair(reference, decoded, region)
    if np.array_equal(a, b):
        return float("inf")
    return float(cv2.PSNR(a, b))


def ssim(
    reference: NDArray[np.uint8], decoded: NDArray[np.uint8], region: Region | None = None
) -> float:
    """Mean structural similarity in [-1, 1] (``cv2.quality.QualitySSIM``, Gaussian window);
    1 for identical images."""
    a, b = _pair(reference, decoded, region)
    score, _ = cv2.quality.QualitySSIM_compute(a, b)
    return float(score[0])
