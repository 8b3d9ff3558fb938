"""Bright blobs in an IR image: sub-pixel centroids, size, roundness and range from depth.

Thresholding and connected components are done by OpenCV on the whole frame; the per-blob
measurements only touch a small window around each blob.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.tracking.camera import CameraIntrinsics

CentroidMethod = Literal["weighted", "binary", "peak"]
DepthMethod = Literal["sphere", "mean", "peak", "size"]


@dataclass(frozen=True)
class BlobParams:
    """Detection and measurement settings. Counts are IR units, sizes pixels, ranges m."""

    threshold: float = 1000.0
    centroid_floor: float = 400.0
    min_area: int = 3
    max_area: int = 600
    min_roundness: float = 0.45
    centroid: CentroidMethod = "weighted"
    depth: DepthMethod = "sphere"
    sphere_offset: float = 0.47  # fitted on the sim: median bright-core range -> centre, x R
    min_range: float = 0.15  # blobs whose apparent size puts them nearer or farther are dropped
    max_range: float = 0.58  # (too small and dim beyond: depth mixes with the background)
    unwrap: bool = True
    depth_wrap_m: float = 1.0
    max_blobs: int = 24


@dataclass(frozen=True)
class Blobs:
    """Detected blobs: ``uv`` (N, 2) px, ``area`` (N,) px above threshold, ``size_range``
    (N,) m (range from apparent size), ``points`` (N, 3) m marker centres in the camera frame
    (NaN when no range), ``rejected`` how many components were dropped by size or shape."""

    uv: NDArray[np.float64]
    area: NDArray[np.int64]
    size_range: NDArray[np.float64]
    points: NDArray[np.float64]
    rejected: int


def _blob_range(
    ir_w: NDArray,
    core: NDArray,
    dep_w: NDArray | None,
    size_range: float,
    radius: float,
    p: BlobParams,
) -> float:
    """Range (m) from the camera to the sphere centre along the blob's ray."""
    if p.depth == "size" or dep_w is None:
        return size_range
    valid = dep_w > 0
    if p.depth == "peak":
        ok = np.flatnonzero(valid.ravel())
        if ok.size == 0:
            return np.nan
        r = dep_w.ravel()[ok[np.argmax(ir_w.ravel()[ok])]] / 1000.0 + radius
    else:
        d = dep_w[core & valid].astype(np.float64) / 1000.0
        if d.size == 0:
            return np.nan
        if p.depth == "mean":
            r = float(d.mean())
        else:
            r = float(np.median(d)) + p.sphere_offset * radius
    if p.unwrap and np.isfinite(size_range):
        ks = np.arange(3)
        cands = r + ks * p.depth_wrap_m
        r = float(cands[np.argmin(np.abs(np.log(cands / size_range)))])
    return r


def _ratio(m: dict[str, float]) -> float:
    """Minor/major variance ratio of image moments (1 = round)."""
    a, b, c = m["mu20"], m["mu02"], m["mu11"]
    tr, det = a + b, a * b - c * c
    disc = np.sqrt(max(tr * tr / 4.0 - det, 0.0))
    return (tr / 2.0 - disc) / max(tr / 2.0 + disc, 1e-12)


def detect_blobs(
    ir: NDArray,
    depth_mm: NDArray | None,
    intrinsics: CameraIntrinsics,
    radius: float,
    params: BlobParams | None = None,
) -> Blobs:
    """Blobs of ``ir`` (uint16) brighter than the threshold and their 3D centres (camera frame).

    ``radius`` is the marker sphere radius (m): used for the range from apparent size and the
    correction from the measured sphere surface to its centre.
    """
    p = params or BlobParams()
    k = intrinsics
    mask = cv2.compare(ir, p.threshold, cv2.CMP_GT)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    h_img, w_img = ir.shape
    uvs, areas, sizes, pts = [], [], [], []
    rejected = 0
    max_side = 2.0 * np.sqrt(p.max_area)
    for cnt in contours:
        x, y, w, h = cv2.boundingRect(cnt)
        if w > max_side or h > max_side or len(uvs) >= p.max_blobs:
            rejected += 1
            continue
        x0, y0 = max(x - 1, 0), max(y - 1, 0)
        x1, y1 = min(x + w + 1, w_img), min(y + h + 1, h_img)
        area = int(np.count_nonzero(mask[y : y + h, x : x + w]))
        if area < p.min_area or area > p.max_area:
            rejected += 1
            continue
        ir_w = ir[y0:y1, x0:x1].astype(np.float32)
        peak = float(ir_w.max())
        core = ir_w >= 0.5 * peak  # half-maximum area: the sphere's disc
        mc = cv2.moments(core.view(np.uint8), binaryImage=True)
        n_core = mc["m00"]
        cu, cv_ = mc["m10"] / n_core + x0, mc["m01"] / n_core + y0
        off2 = ((cu - k.cx) / k.fx) ** 2 + ((cv_ - k.cy) / k.fy) ** 2
        expected = 1.0 / (1.0 + off2)  # a sphere's image: axis ratio cos(off-axis angle)
        if n_core >= 5 and _ratio(mc) < p.min_roundness * expected:
            rejected += 1
            continue
        if p.centroid == "weighted":
            mw = cv2.moments(np.clip(ir_w - p.centroid_floor, 0.0, None))
            u, v = mw["m10"] / mw["m00"] + x0, mw["m01"] / mw["m00"] + y0
        elif p.centroid == "binary":
            mb = cv2.moments(mask[y : y + h, x : x + w], binaryImage=True)
            u, v = mb["m10"] / mb["m00"] + x, mb["m01"] / mb["m00"] + y
        else:
            iy, ix = np.unravel_index(int(np.argmax(ir_w)), ir_w.shape)
            u, v = float(x0 + ix), float(y0 + iy)
        r_px = np.sqrt(n_core / np.pi * np.sqrt(expected))
        size_range = k.fx * radius / max(r_px, 0.5) * np.sqrt(1.0 + off2)
        dep_w = None if depth_mm is None else depth_mm[y0:y1, x0:x1]
        if not p.min_range <= size_range <= p.max_range:
            rejected += 1
            continue
        rng = _blob_range(ir_w, ir_w >= 0.8 * peak, dep_w, size_range, radius, p)
        if not p.min_range <= rng <= p.max_range:  # measured range: too far to trust
            rejected += 1
            continue
        uvs.append((u, v))
        areas.append(area)
        sizes.append(size_range)
        pts.append(k.rays(u, v) * rng)
    return Blobs(
        uv=np.array(uvs, dtype=float).reshape(-1, 2),
        area=np.array(areas, dtype=np.int64),
        size_range=np.array(sizes, dtype=float),
        points=np.array(pts, dtype=float).reshape(-1, 3),
        rejected=rejected,
    )
