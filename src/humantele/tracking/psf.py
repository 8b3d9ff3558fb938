"""Calibrate the camera's blur (PSF sigma, px) from IR frames of the markers, no ground truth.

The sphere model (:mod:`humantele.tracking.sphere`) needs the blur of the optics. A wrong
value biases the range (too sharp a model: ranges too far) and makes whole spheres misfit so
they are refused. The right value is the one whose model images fit the observed blobs best:
:func:`estimate_psf_sigma` minimises the median IR misfit over the blobs of a few frames
(golden-section search). Run it once per device on ~10-20 frames of the probe held still or
moving; put the result in the pipeline config (``psf_sigma_px``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from humantele.tracking.blobs import BlobParams, detect_blobs
from humantele.tracking.frames import TrackingFrame


def psf_misfit(
    frames: Sequence[TrackingFrame],
    radius: float,
    psf_sigma_px: float,
    params: BlobParams | None = None,
) -> float:
    """Median IR misfit (fraction of brightness) of all blobs in ``frames`` for a PSF sigma."""
    p = params or BlobParams()
    sphere = dataclasses.replace(p.sphere, psf_sigma_px=psf_sigma_px, max_ir_misfit=math.inf)
    p = dataclasses.replace(p, depth="model", sphere=sphere)
    vals = []
    for f in frames:
        b = detect_blobs(f.ir, f.depth_mm, f.intrinsics, radius, p)
        if b.ir_misfit is not None:
            vals.append(b.ir_misfit)
    v = np.concatenate(vals) if vals else np.zeros(0)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else math.inf


def estimate_psf_sigma(
    frames: Sequence[TrackingFrame],
    radius: float,
    lo: float = 0.2,
    hi: float = 1.6,
    tol: float = 0.02,
    params: BlobParams | None = None,
) -> float:
    """The PSF sigma (px) in [lo, hi] whose sphere model best fits the blobs of ``frames``."""
    if not frames:
        raise ValueError("estimate_psf_sigma needs at least one frame")
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = psf_misfit(frames, radius, c, params), psf_misfit(frames, radius, d, params)
    while b - a > tol:
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = psf_misfit(frames, radius, c, params)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = psf_misfit(frames, radius, d, params)
    return round((a + b) / 2.0, 3)
