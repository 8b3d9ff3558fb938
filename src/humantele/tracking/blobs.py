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
    depth_wrap_m: float = 1.055  # AHAT range ambiguity (hl2ss mode-2 calibration: alias 1055)
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
    ir_misfit: NDArray[np.float64] | None = None  # (N,) "model" depth: IR misfit to a sphere


def _empty(rejected: int) -> Blobs:
    z = np.zeros((0,), dtype=float)
    return Blobs(z.reshape(0, 2), np.zeros(0, np.int64), z, z.reshape(0, 3), rejected)


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
    sphere model that turns the measured surface ranges into the centre's range.
    """
    p = params or BlobParams()
    k = intrinsics
    mask = cv2.compare(ir, p.threshold, cv2.CMP_GT)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    h_img, w_img = ir.shape
    sig = np.hypot(p.sphere.psf_sigma_px, 0.3)
    r_near = k.fx * radius / p.min_range  # disc radius (px) of the nearest sphere, on axis
    boxes = []
    rejected = 0
    for cnt in contours:
        b = cv2.boundingRect(cnt)
        bu, bv = (b[0] + b[2] / 2.0 - k.cx) / k.fx, (b[1] + b[3] / 2.0 - k.cy) / k.fy
        side = 2.0 * r_near * (1.0 + bu * bu + bv * bv) + 4.0 * sig + 3.0  # largest sphere
        ok = b[2] <= side and b[3] <= side and b[2] * b[3] >= p.min_area
        if ok and b[2] * b[3] >= 20:  # big enough for the outline's shape to mean something
            m = cv2.moments(cnt)  # a bar or a cable is no sphere: refuse it before measuring
            ok = m["m00"] <= 0 or _ratio(m) >= 0.5 * p.min_roundness / (1.0 + bu * bu + bv * bv)
        if not ok or len(boxes) >= p.max_blobs:
            rejected += 1
        else:
            boxes.append(b)
    if not boxes:
        return _empty(rejected)
    bx = np.array(boxes, dtype=np.int64)
    x, y, w, h = bx.T
    n = len(bx)
    half = int(np.ceil(bx[:, 2:].max() / 2.0 + 3.0 * sig + 2.0))
    span = np.arange(-half, half + 1)
    rows = (y + h // 2)[:, None] + span  # (N, S) image rows of each window
    cols = (x + w // 2)[:, None] + span
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= h_img or cols.max() >= w_img:
        in_img = ((rows >= 0) & (rows < h_img))[:, :, None] & ((cols >= 0) & (cols < w_img))[
            :, None, :
        ]
        rows_c, cols_c = np.clip(rows, 0, h_img - 1), np.clip(cols, 0, w_img - 1)
    else:
        in_img, rows_c, cols_c = np.ones((1, 1, 1), bool), rows, cols
    ir_w = ir[rows_c[:, :, None], cols_c[:, None, :]] * in_img  # (N, S, S), 0 off the image
    # the bounding box and one pixel around it: this blob's own pixels
    r_in = (rows >= (y - 1)[:, None]) & (rows <= (y + h)[:, None])
    c_in = (cols >= (x - 1)[:, None]) & (cols <= (x + w)[:, None])
    ir_r = ir_w * (r_in[:, :, None] & c_in[:, None, :])
    area = (ir_r > p.threshold).sum(axis=(1, 2))
    peak = ir_r.max(axis=(1, 2)).astype(np.float64)
    n_core = (ir_r >= 0.5 * peak[:, None, None]).sum(axis=(1, 2))  # half maximum: the disc
    if p.centroid == "peak":
        iy, ix = np.unravel_index(ir_r.reshape(n, -1).argmax(axis=1), ir_r.shape[1:])
        u, v = cols[np.arange(n), ix].astype(float), rows[np.arange(n), iy].astype(float)
    else:
        if p.centroid == "weighted":
            wgt = np.clip(ir_r - p.centroid_floor, 0.0, None)
        else:
            wgt = (ir_r > p.threshold).astype(np.float64)
        wx, wy = wgt.sum(axis=1), wgt.sum(axis=2)  # column and row profiles
        m0 = np.maximum(wx.sum(axis=1), 1e-9)
        u, v = (wx * cols).sum(axis=1) / m0, (wy * rows).sum(axis=1) / m0
    off2 = ((u - k.cx) / k.fx) ** 2 + ((v - k.cy) / k.fy) ** 2
    r_px = np.sqrt(n_core / np.pi / np.sqrt(1.0 + off2))  # an ellipse: r^2 / cos^3(off-axis)
    size_range = k.fx * radius / np.maximum(r_px, 0.5) * np.sqrt(1.0 + off2)
    keep = (area >= p.min_area) & (area <= p.max_area)
    keep &= (size_range >= p.min_range) & (size_range <= p.max_range)

    ranges = _Ranges(p, k, radius, depth_mm, rows_c, cols_c, in_img, ir_w, ir_r, peak)
    rng, not_sphere, misfit = ranges.measure(u, v, size_range)
    keep &= np.isfinite(rng) & (rng >= p.min_range) & (rng <= p.max_range) & ~not_sphere
    idx = np.flatnonzero(keep)
    pts = k.rays(u[idx], v[idx]) * rng[idx, None]
    return Blobs(
        uv=np.stack([u[idx], v[idx]], axis=1),
        area=area[idx].astype(np.int64),
        size_range=size_range[idx],
        points=pts.reshape(-1, 3),
        rejected=rejected + n - len(idx),
        not_sphere=int(np.count_nonzero(not_sphere & ~np.isnan(rng))),
        ir_misfit=None if misfit is None else misfit[idx],
    )


@dataclass
class _Ranges:
    """The windows of one frame's blobs and how to measure their centres' ranges."""

    p: BlobParams
    k: CameraIntrinsics
    radius: float
    depth_mm: NDArray | None
    rows: NDArray
    cols: NDArray
    in_img: NDArray
    ir_w: NDArray
    ir_r: NDArray
    peak: NDArray

    def measure(
        self, u: NDArray, v: NDArray, size_range: NDArray
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64] | None]:
        """Range (m) from the camera to each sphere centre along its centroid ray (NaN: no
        depth to measure it), which blobs the sphere model refuses (not a whole sphere) and
        their IR misfit to it (None unless ``depth == "model"``)."""
        p, k, n = self.p, self.k, len(u)
        no = np.zeros(n, dtype=bool)
        if p.depth == "size" or self.depth_mm is None:
            return size_range.copy(), no, None
        d = self.depth_mm[self.rows[:, :, None], self.cols[:, None, :]] * (self.in_img / 1000.0)
        valid = d > 0
        if p.depth == "peak":
            flat = np.where(valid, self.ir_r, -1.0).reshape(n, -1)
            j = flat.argmax(axis=1)
            r = np.where(flat[np.arange(n), j] > 0, d.reshape(n, -1)[np.arange(n), j], np.nan)
            r = r + self.radius
        else:
            core = valid & (self.ir_r >= 0.8 * self.peak[:, None, None])
            if p.depth == "mean":
                cnt = core.sum(axis=(1, 2))
                r = np.where(cnt > 0, (d * core).sum(axis=(1, 2)) / np.maximum(cnt, 1), np.nan)
            else:
                r = _masked_median(d, core, np.full(n, np.nan)) + p.sphere_offset * self.radius
        if p.unwrap:
            cands = r[:, None] + np.arange(3)[None, :] * p.depth_wrap_m
            with np.errstate(invalid="ignore", divide="ignore"):
                j = np.argmin(np.abs(np.log(cands / size_range[:, None])), axis=1)
            r = np.where(np.isfinite(r), cands[np.arange(n), j], np.nan)
        if p.depth != "model":
            return r, no, None
        s0 = np.where(np.isfinite(r), r, size_range)
        rw = np.where(valid, d, np.nan)
        if p.unwrap:
            rw = rw + p.depth_wrap_m * np.round((s0[:, None, None] - rw) / p.depth_wrap_m)
        fit = fit_sphere_ranges(
            np.where(self.in_img, self.ir_w, np.nan),
            rw,
            (self.cols - u[:, None])[:, None, :],
            ((self.rows - v[:, None]) * (k.fx / k.fy))[:, :, None],
            np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy], axis=1),
            s0,
            self.radius,
            k.fx,
            p.threshold,
            p.sphere,
            p.depth_wrap_m if p.unwrap else None,
        )
        return fit.range_m, ~fit.shape_ok, fit.ir_misfit
