"""The probe's field of view: its beams, the samples along them, and the scan conversion.

Tip frame: origin at the centre of the transducer face, +z along the beam (into the patient),
+x along the array (the image plane is the tip's x-z plane). The image shows the plane with
columns along +x (left to right) and rows along +z (depth, top to bottom), square pixels.

- ``curvilinear``: a convex array of radius ``radius_m`` whose face centre is the tip origin;
  beams fan out over ``fov_deg`` from the centre of curvature (0, 0, -radius_m), each from its
  point on the face; depth is counted along each beam from the face.
- ``linear``: beams parallel to +z from ``aperture_m`` of face along x.

The echo model works on a beam x sample grid (``beams`` x ``samples``, like a scanner's
lines) which :meth:`ScanGeometry.to_image` scan-converts to the (H, W) image. The pixel spacing
is the one that fits the whole field of view into the image.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

MARGIN = 0.02  # of the image kept free around the field of view


class ScanGeometry:
    """Beams, samples and the polar-to-image maps of one probe; all fixed at construction.

    Arrays (float32 unless said): ``face`` (beams, 3) where each beam leaves the face and
    ``direction`` (beams, 3), tip frame; ``x``, ``z`` (beams * samples,): tip-frame position of
    every sample, beam-major; ``range_m`` (samples,): depth of each sample along its beam;
    ``cell_area_m2`` (beams * samples,): area of the image plane each sample stands for;
    ``fov_mask`` (H, W) bool: pixels inside the field of view; ``spacing_m``: pixel size (m);
    ``origin_m`` (x, z) tip-frame position of pixel (row 0, col 0)'s centre.
    """

    def __init__(
        self,
        kind: Literal["curvilinear", "linear"],
        width: int,
        height: int,
        depth_m: float,
        fov_deg: float = 70.0,
        radius_m: float = 0.05,
        aperture_m: float = 0.04,
        beams: int = 128,
        samples: int = 256,
    ) -> None:
        self.kind = kind
        self.width, self.height = int(width), int(height)
        self.depth_m = float(depth_m)
        self.beams, self.samples = int(beams), int(samples)
        dr = self.depth_m / self.samples
        self.range_m = ((np.arange(self.samples) + 0.5) * dr).astype(np.float32)
        if kind == "curvilinear":
            half = math.radians(fov_deg) / 2.0
            self.radius_m = float(radius_m)
            theta = np.linspace(-half, half, self.beams)
            d = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1)
            face = d * self.radius_m - np.array([0.0, 0.0, self.radius_m])
            rho = self.radius_m + self.range_m.astype(float)
            dtheta = 2.0 * half / max(self.beams - 1, 1)
            area = np.broadcast_to(rho * dtheta * dr, (self.beams, self.samples))
            far = self.radius_m + self.depth_m
            x_lo, x_hi = -far * math.sin(half), far * math.sin(half)
            z_lo, z_hi = self.radius_m * (math.cos(half) - 1.0), self.depth_m
            self._half, self._dtheta = half, dtheta
        else:
            x = np.linspace(-aperture_m / 2.0, aperture_m / 2.0, self.beams)
            d = np.tile([0.0, 0.0, 1.0], (self.beams, 1))
            face = np.stack([x, np.zeros_like(x), np.zeros_like(x)], -1)
            dx = aperture_m / max(self.beams - 1, 1)
            area = np.full((self.beams, self.samples), dx * dr)
            x_lo, x_hi, z_lo, z_hi = -aperture_m / 2.0, aperture_m / 2.0, 0.0, self.depth_m
            self._x0, self._dx = -aperture_m / 2.0, dx
        self.face = face.astype(np.float32)
        self.direction = d.astype(np.float32)
        pts = face[:, None, :] + d[:, None, :] * self.range_m[None, :, None]
        self.x = np.ascontiguousarray(pts[..., 0].reshape(-1), dtype=np.float32)
        self.z = np.ascontiguousarray(pts[..., 2].reshape(-1), dtype=np.float32)
        self.cell_area_m2 = area.reshape(-1).astype(np.float32)
        # Square pixels that fit the field of view with a margin, centred.
        w_m, h_m = (x_hi - x_lo), (z_hi - z_lo)
        self.spacing_m = max(w_m / self.width, h_m / self.height) / (1.0 - 2.0 * MARGIN)
        s = self.spacing_m
        cx = (x_lo + x_hi) / 2.0
        x0 = cx - s * (self.width - 1) / 2.0
        z0 = z_lo - s * (self.height * MARGIN)
        self.origin_m = (x0, z0)
        self._maps: dict[int, tuple[NDArray, NDArray, NDArray]] = {}
        self.fov_mask = self._maps_for(1)[2]
        # Two zero rows and columns after the grid: every pixel outside the field of view reads
        # its four bilinear taps inside the buffer (zeros), so cv2.remap never takes its slow
        # per-pixel border path (about 3x slower when half of the image is outside the fan).
        self._buffer = np.zeros((self.samples + 2, self.beams + 2), dtype=np.float32)

    @property
    def pixel_spacing_mm(self) -> tuple[float, float]:
        """(row, col) pixel size in mm (square pixels)."""
        return (self.spacing_m * 1e3, self.spacing_m * 1e3)

    @property
    def depth_origin_row(self) -> float:
        """The image row (px, fractional) of depth 0: the centre of the probe's face (the tip
        origin), where the depth scale starts."""
        return self.tip_to_pixel(0.0, 0.0)[0]

    def pixel_to_tip(self, row: float, col: float) -> tuple[float, float]:
        """Tip-frame (x, z) in m of the centre of pixel (row, col)."""
        return (self.origin_m[0] + col * self.spacing_m, self.origin_m[1] + row * self.spacing_m)

    def tip_to_pixel(self, x: float, z: float) -> tuple[float, float]:
        """(row, col), fractional, of tip-frame point (x, z) in m."""
        return ((z - self.origin_m[1]) / self.spacing_m, (x - self.origin_m[0]) / self.spacing_m)

    def _maps_for(self, step: int) -> tuple[NDArray, NDArray, NDArray]:
        """Remap maps (beam, sample; OpenCV's fixed-point pair) and field-of-view mask for an
        image of every ``step``-th column: ``ceil(W / step)`` columns, column j centred on full
        column ``step*j + (step - 1) / 2`` (where ``cv2.resize`` puts it when stretching back
        to W)."""
        if step in self._maps:
            return self._maps[step]
        ncols = -(-self.width // step)
        cols = np.arange(ncols, dtype=np.float64) * step + (step - 1) / 2.0
        rows = np.arange(self.height, dtype=np.float64)
        x = self.origin_m[0] + cols[None, :] * self.spacing_m
        z = self.origin_m[1] + rows[:, None] * self.spacing_m
        x, z = np.broadcast_arrays(x, z)
        dr = self.depth_m / self.samples
        if self.kind == "curvilinear":
            zc = z + self.radius_m
            rho = np.hypot(x, zc)
            theta = np.arctan2(x, zc)
            beam = (theta + self._half) / self._dtheta
            sample = (rho - self.radius_m) / dr - 0.5
            inside = (np.abs(theta) <= self._half) & (rho >= self.radius_m)
            inside &= rho <= self.radius_m + self.depth_m
        else:
            beam = (x - self._x0) / self._dx
            sample = z / dr - 0.5
            inside = (beam >= 0) & (beam <= self.beams - 1) & (z >= 0) & (z <= self.depth_m)
        # Outside the field of view: the zero cells padded after the last beam and sample
        # (a lookup inside the source image, which OpenCV does fastest).
        beam = np.where(inside, np.clip(beam, 0, self.beams - 1), self.beams)
        sample = np.where(inside, np.clip(sample, 0, self.samples - 1), self.samples)
        # OpenCV's fixed-point maps (1/32 px, what remap makes of float maps on every call).
        xy, frac = cv2.convertMaps(beam.astype(np.float32), sample.astype(np.float32), cv2.CV_16SC2)
        maps = (xy, frac, inside)
        self._maps[step] = maps
        return maps

    def to_image(
        self,
        grid: NDArray[np.float32],
        step: int = 1,
        regions: list[tuple[int, int, int, int]] | None = None,
        out: NDArray[np.float32] | None = None,
    ) -> NDArray[np.float32]:
        """Scan conversion: a (beams, samples) float32 grid to the (H, W) image (every
        ``step``-th column, see :meth:`_maps_for`), bilinear; zero outside the field of view.
        ``regions`` (row0, row1, col0, col1) that hold the whole field of view: only those are
        computed, into ``out`` (zero elsewhere, which the caller keeps so)."""
        mb, ms, _ = self._maps_for(step)
        buf = self._buffer
        buf[: self.samples, : self.beams] = grid.T  # rows = samples; the padding stays 0
        if regions is None:
            return cv2.remap(buf, mb, ms, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if out is None:
            out = np.zeros(mb.shape[:2], dtype=np.float32)
        for r0, r1, c0, c1 in regions:
            cv2.remap(
                buf,
                mb[r0:r1, c0:c1],
                ms[r0:r1, c0:c1],
                cv2.INTER_LINEAR,
                dst=out[r0:r1, c0:c1],
                borderMode=cv2.BORDER_CONSTANT,
            )
        return out

    def fov_mask_at(self, step: int) -> NDArray[np.bool_]:
        """The field-of-view mask of the ``step``-decimated image."""
        return self._maps_for(step)[2]
