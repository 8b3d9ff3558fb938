"""Bright blobs in an IR image: sub-pixel centroids, size, roundness and range from depth.

Thresholding and contours are done by OpenCV on the whole frame; every per-blob measurement
then runs batched (NumPy over an (N, H, W) stack of small windows), so the cost hardly grows
with the number of blobs and has no Python loop over pixels.

Range of a marker's centre (``depth``): ``"model"`` fits the sphere's ToF image (coverage,
blur, background mixing; :mod:`humantele.tracking.sphere`); ``"sphere"`` is the median range
of the bright core plus a fixed fraction of the radius (fitted once on the sim: biased with
distance); ``"mean"`` the core's mean range; ``"peak"`` the brightest pixel's range + R;
``"size"`` the range from the blob's apparent size alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.sphere import SphereFitParams, _masked_median, fit_sphere_ranges

CentroidMethod = Literal["weighted", "binary", "peak"]
DepthMethod = Literal["model", "sphere", "mean", "peak", "size"]


@dataclass(frozen=True)
class BlobParams:
    """Detection and measurement settings. Counts are IR units, sizes pixels, ranges m."""

    threshold: float = 1000.0
    centroid_floor: float = 400.0
    min_area: int = 3
    max_area: int = 600
    min_roundness: float = 0.45
    centroid: CentroidMethod = "weighted"
    depth: DepthMethod = "model"
    sphere_offset: float = 0.47  # "sphere" depth: median bright-core range -> centre, x R
    min_range: float = 0.15  # blobs whose apparent size puts them nearer or farther are dropped
    max_range: float = 0.58  # (too small and dim beyond: depth mixes with the background)
    unwrap: bool = True
    depth_wrap_m: float = 1.0
    max_blobs: int = 24
    sphere: SphereFitParams = field(default_factory=SphereFitParams)


@dataclass(frozen=True)
class Blobs:
    """Detected blobs: ``uv`` (N, 2) px, ``area`` (N,) px above threshold, ``size_range``
    (N,) m (range from apparent size), ``points`` (N, 3) m marker centres in the camera frame,
    ``rejected`` how many components were dropped (size, shape, range, no depth fit), of which
    ``not_sphere`` because their image did not look like a whole sphere (partly hidden)."""

    uv: NDArray[np.float64]
    area: NDArray[np.int64]
    size_range: NDArray[np.float64]
    points: NDArray[np.float64]
    rejected: int
    not_sphere: int = 0


def _empty(rejected: int) -> Blobs:
    z = np.zeros((0,), dtype=float)
    return Blobs(z.reshape(0, 2), np.zeros(0, np.int64), z, z.reshape(0, 3), rejected)


def _sums(w: NDArray, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Zeroth moment and centroid (x, y) of weights ``w`` (N, H, W) per window."""
    m0 = w.sum(axis=(1, 2))
    safe = np.where(m0 > 0, m0, 1.0)
    return m0, (w * x).sum(axis=(1, 2)) / safe, (w * y).sum(axis=(1, 2)) / safe


def detect_blobs(
    ir: NDArray,
    depth_mm: NDArray | None,
    intrinsics: CameraIntrinsics,
    radius: float,
    params: BlobParams | None = None,
) -> Blobs:
    """Blobs of ``ir`` (uint16) brighter than the threshold and their 3D centres (camera frame).

    ``radius`` is the marker sphere radius (m): used for the range from apparent size and the
    sphere model that turns the measured surface ranges into the centre's range.
    """
    p = params or BlobParams()
    k = intrinsics
    mask = cv2.compare(ir, p.threshold, cv2.CMP_GT)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    h_img, w_img = ir.shape
    max_side = 2.0 * np.sqrt(p.max_area)
    boxes = []
    rejected = 0
    for cnt in contours:
        b = cv2.boundingRect(cnt)
        if b[2] > max_side or b[3] > max_side or len(boxes) >= p.max_blobs:
            rejected += 1
        else:
            boxes.append(b)
    if not boxes:
        return _empty(rejected)
    bx = np.array(boxes, dtype=np.int64)
    x, y, w, h = bx.T
    sig = np.hypot(p.sphere.psf_sigma_px, 0.3)
    half = int(np.ceil(bx[:, 2:].max() / 2.0 + 3.0 * sig + 3.0))
    span = np.arange(-half, half + 1)
    rows = (y + h // 2)[:, None] + span  # (N, S)
    cols = (x + w // 2)[:, None] + span
    in_img = ((rows >= 0) & (rows < h_img))[:, :, None] & ((cols >= 0) & (cols < w_img))[:, None, :]
    rc, cc = np.clip(rows, 0, h_img - 1), np.clip(cols, 0, w_img - 1)
    ir_w = ir[rc[:, :, None], cc[:, None, :]].astype(np.float64)
    yy, xx = rows[:, :, None].astype(np.float64), cols[:, None, :].astype(np.float64)

    def box(lo: NDArray, n: NDArray, idx: NDArray, m: int) -> NDArray:
        return (idx >= (lo - m)[:, None]) & (idx < (lo + n + m)[:, None])

    inbox = box(y, h, rows, 0)[:, :, None] & box(x, w, cols, 0)[:, None, :] & in_img
    rect = box(y, h, rows, 1)[:, :, None] & box(x, w, cols, 1)[:, None, :] & in_img
    above = ir_w > p.threshold
    area = (above & inbox).sum(axis=(1, 2))
    keep = (area >= p.min_area) & (area <= p.max_area)

    ir_r = np.where(rect, ir_w, 0.0)
    peak = ir_r.max(axis=(1, 2))
    core = rect & (ir_w >= 0.5 * peak[:, None, None])  # half maximum: the sphere's disc
    n_core, cu, cv = _sums(core.astype(np.float64), xx, yy)
    dxc, dyc = xx - cu[:, None, None], yy - cv[:, None, None]
    a = (core * dxc * dxc).sum(axis=(1, 2))
    b_ = (core * dyc * dyc).sum(axis=(1, 2))
    c_ = (core * dxc * dyc).sum(axis=(1, 2))
    tr, det = a + b_, a * b_ - c_ * c_
    disc = np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
    ratio = (tr / 2.0 - disc) / np.maximum(tr / 2.0 + disc, 1e-12)
    off2 = ((cu - k.cx) / k.fx) ** 2 + ((cv - k.cy) / k.fy) ** 2
    expected = 1.0 / (1.0 + off2)  # a sphere's image: axis ratio cos(off-axis angle)
    keep &= (n_core < 5) | (ratio >= p.min_roundness * expected)

    if p.centroid == "weighted":
        _, u, v = _sums(np.clip(ir_r - p.centroid_floor, 0.0, None), xx, yy)
    elif p.centroid == "binary":
        _, u, v = _sums((above & inbox).astype(np.float64), xx, yy)
    else:
        flat = ir_r.reshape(len(bx), -1).argmax(axis=1)
        iy, ix = np.unravel_index(flat, ir_r.shape[1:])
        u, v = (
            cols[np.arange(len(bx)), ix].astype(float),
            rows[np.arange(len(bx)), iy].astype(float),
        )
    r_px = np.sqrt(n_core / np.pi * np.sqrt(expected))
    size_range = k.fx * radius / np.maximum(r_px, 0.5) * np.sqrt(1.0 + off2)
    keep &= (size_range >= p.min_range) & (size_range <= p.max_range)

    rng, not_sphere = _ranges(
        p, k, depth_mm, rc, cc, in_img, rect, ir_w, peak, u, v, size_range, radius, keep
    )
    keep &= np.isfinite(rng) & (rng >= p.min_range) & (rng <= p.max_range)
    keep &= ~not_sphere
    idx = np.flatnonzero(keep)
    pts = k.rays(u[idx], v[idx]) * rng[idx, None]
    return Blobs(
        uv=np.stack([u[idx], v[idx]], axis=1),
        area=area[idx].astype(np.int64),
        size_range=size_range[idx],
        points=pts.reshape(-1, 3),
        rejected=rejected + len(bx) - len(idx),
        not_sphere=int(np.count_nonzero(not_sphere)),
    )


def _ranges(
    p: BlobParams,
    k: CameraIntrinsics,
    depth_mm: NDArray | None,
    rc: NDArray,
    cc: NDArray,
    in_img: NDArray,
    rect: NDArray,
    ir_w: NDArray,
    peak: NDArray,
    u: NDArray,
    v: NDArray,
    size_range: NDArray,
    radius: float,
    keep: NDArray,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Range (m) from the camera to each sphere centre along its centroid ray, and which
    blobs the sphere model refuses (NaN range: no depth to measure it)."""
    n = len(u)
    no = np.zeros(n, dtype=bool)
    if p.depth == "size" or depth_mm is None:
        return size_range.copy(), no
    d = depth_mm[rc[:, :, None], cc[:, None, :]].astype(np.float64) / 1000.0
    valid = in_img & (d > 0)
    rng_w = np.where(valid, d, np.nan)
    if p.depth == "peak":
        flat = np.where(valid & rect, ir_w, -1.0).reshape(n, -1)
        j = flat.argmax(axis=1)
        r = np.where(flat[np.arange(n), j] >= 0, rng_w.reshape(n, -1)[np.arange(n), j], np.nan)
        r = r + radius
    else:
        core = rect & valid & (ir_w >= 0.8 * peak[:, None, None])
        if p.depth == "mean":
            cnt = core.sum(axis=(1, 2))
            r = np.where(
                cnt > 0, np.where(core, d, 0.0).sum(axis=(1, 2)) / np.maximum(cnt, 1), np.nan
            )
        else:
            r = _masked_median(d, core, np.full(n, np.nan)) + p.sphere_offset * radius
    if p.unwrap:
        cands = r[:, None] + np.arange(3)[None, :] * p.depth_wrap_m
        with np.errstate(invalid="ignore", divide="ignore"):
            j = np.argmin(np.abs(np.log(cands / size_range[:, None])), axis=1)
        r = np.where(np.isfinite(r), cands[np.arange(n), j], np.nan)
    if p.depth != "model":
        return r, no
    s0 = np.where(np.isfinite(r), r, size_range)
    go = keep & (s0 >= p.min_range) & (s0 <= p.max_range)
    out = np.full(n, np.nan)
    if not go.any():
        return out, no
    g = np.flatnonzero(go)
    rw = rng_w[g]
    if p.unwrap:
        rw = rw + p.depth_wrap_m * np.round((s0[g, None, None] - rw) / p.depth_wrap_m)
    dx = (cc[g] - u[g, None]).astype(np.float64)[:, None, :]
    dy = ((rc[g] - v[g, None]) * (k.fx / k.fy)).astype(np.float64)[:, :, None]
    bearing = np.stack([(u[g] - k.cx) / k.fx, (v[g] - k.cy) / k.fy], axis=1)
    fit = fit_sphere_ranges(
        np.where(in_img[g], ir_w[g], np.nan),
        rw,
        dx,
        dy,
        bearing,
        s0[g],
        radius,
        k.fx,
        p.threshold,
        p.sphere,
        p.depth_wrap_m if p.unwrap else None,
    )
    out[g] = fit.range_m
    no[g] = ~fit.shape_ok
    return out, no
