"""Speckle tied to the tissue: a fixed random 3D field sampled on the image plane.

The field is the envelope ``sqrt(I^2 + Q^2)`` of two smooth Gaussian fields (so its values
are Rayleigh distributed, as a B-mode speckle's are), each the sum of one periodic 2D noise
texture seen along three oblique directions of the patient frame: ``T(B_k p)`` for k = 1..3,
``B_k`` the rows of a fixed rotation taken two at a time. A function of the patient-frame point
only, so the speckle moves with the anatomy when the probe moves; any image plane cuts at
least two of the three projections at a slant, so there are no streaks. The image plane maps
affinely to each texture, so a frame costs three ``cv2.warpAffine`` (in bands of rows that
hold what the caller needs, each band's three warps, their uint8 sum and its blur while they
are in cache), then one table lookup from (I, Q) to the displayed contrast.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import quat_from_axis_angle, quat_to_matrix

PERIOD = 256  # texels of the periodic texture
# The uint8 texture holds I and Q at 42.5 + 13 per standard deviation in [0, 85], so the sum
# of the three projections fits a uint8 (no 16-bit sums: the envelope costs a third as much).
_MEAN, _STD, _MAX = 42.5, 13.0, 85
# A generic fixed rotation: no texture direction lies along a patient axis.
_B = quat_to_matrix(quat_from_axis_angle((0.41, 0.77, 0.49), 0.93))
_PLANES = [(_B[0], _B[1]), (_B[1], _B[2]), (_B[2], _B[0])]
_OFFSETS = [(0.0, 0.0), (0.37 * PERIOD, 0.61 * PERIOD), (0.71 * PERIOD, 0.19 * PERIOD)]
_AXES = np.array([[u, v] for u, v in _PLANES])  # (3, 2, 3): each texture's (u, v) axes
_OFFSET = np.array(_OFFSETS)  # (3, 2)
# The plane on which ``contrast`` is scaled to mean 1 (patient frame, m; 200 x 200 px).
Regions = list[tuple[int, int, int, int]]
_REF_PLANE = (np.zeros(3), np.array([1e-3, 0.0, 0.0]), np.array([0.0, 3e-4, 0.0]), 200, 200)


class SpeckleField:
    """The speckle at any plane's pixels; ``texel_m`` sets the grain.

    ``max_extent_m``: the largest distance across any image it will be asked for (the
    texture is tiled that much beyond one period, so no lookup falls off it). The texture is
    uint8 with 4 channels (I, Q and two unused), the layout ``cv2.warpAffine`` is fastest on.
    A frame's speckle is three ``cv2.warpAffine`` summed in uint8, the lateral blur in uint8,
    and one table lookup from (I, Q) to the displayed contrast ``|I + jQ| ** gamma``.
    """

    def __init__(self, texel_m: float, max_extent_m: float, seed: int = 0) -> None:
        self.texel_m = float(texel_m)
        rng = np.random.default_rng(seed)
        noise = rng.standard_normal((PERIOD, PERIOD, 2)).astype(np.float32)
        k = 4  # a periodic blur: wrap, blur, crop
        wrapped = np.pad(noise, ((k, k), (k, k), (0, 0)), mode="wrap")
        smooth = cv2.GaussianBlur(wrapped, (0, 0), 1.0)[k:-k, k:-k]
        smooth /= smooth.std(axis=(0, 1), keepdims=True)
        margin = int(math.ceil(max_extent_m / self.texel_m)) + 4
        tiled = np.pad(smooth, ((0, margin), (0, margin), (0, 0)), mode="wrap")
        tex = np.zeros((*tiled.shape[:2], 4), dtype=np.uint8)
        tex[..., :2] = np.clip(np.rint(tiled * _STD + _MEAN), 0, _MAX)
        self._tex = tex
        # Patient frame (m) to the three textures' (u, v) texels: a 6 x 4 affine matrix.
        self._maps = np.concatenate(
            [_AXES.reshape(6, 3) / self.texel_m, _OFFSET.reshape(6, 1)], axis=1
        ).astype(np.float32)
        self._luts: dict[tuple[float, float], NDArray[np.float32]] = {}
        self._buffers: dict[tuple[int, int], list[NDArray[np.uint8]]] = {}

    def gaussian(self, points: tuple[NDArray[np.float32], ...]) -> NDArray[np.float32]:
        """The smooth Gaussian field (mean 0, std about 1) at patient-frame points (x, y, z
        float32 arrays, m), e.g. a coarse field (a large ``texel_m``) for organ texture."""
        pts = np.stack([np.asarray(p, dtype=np.float32).reshape(-1) for p in points], -1)
        n = pts.shape[0]
        # The three textures' (u, v) of every point in one pass, then one lookup of all 3 n.
        uv = cv2.transform(pts[:, None, :], self._maps).reshape(n, 3, 2)
        uv -= np.floor(uv * np.float32(1.0 / PERIOD)) * np.float32(PERIOD)  # (np.mod: 5x)
        s = cv2.remap(
            self._tex, uv.reshape(1, 3 * n, 2), None, cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip
        acc = s[0, :, 0].reshape(n, 3).sum(axis=1, dtype=np.float32)
        return (acc - np.float32(3 * _MEAN)) * np.float32(1.0 / (math.sqrt(3.0) * _STD))

    def _iq(
        self,
        origin,
        ex,
        ey,
        width: int,
        height: int,
        lateral_blur_px: float,
        regions: Regions | None = None,
    ) -> NDArray[np.uint8]:
        """(height, width, 4) uint8: I and Q (channels 0, 1; 3 * _MEAN at zero) of the field at
        the pixels ``origin + col * ex + row * ey``, blurred along the rows; only inside
        ``regions`` (row0, row1, col0, col1) when given (the rest is left as it was). A buffer
        reused by the next call of the same size."""
        h = self.texel_m
        bufs = self._buffers.get((width, height))
        if bufs is None:
            bufs = [np.zeros((height, width, 4), dtype=np.uint8) for _ in range(3)]
            self._buffers[(width, height)] = bufs
        regions = regions or [(0, height, 0, width)]
        box = np.array(regions, dtype=float)  # (n, 4): row0, row1, col0, col1
        corner = box[:, [2, 0]]  # (n, 2): the band's first (col, row)
        extent = box[:, [3, 1]] - corner  # (n, 2): its (cols, rows)
        # The texture coordinates of each projection: A @ (col, row) + t, (3, 2, 2) and (3, 2).
        lin = np.stack([_AXES @ ex, _AXES @ ey], axis=-1) / h  # (3, 2, 2)
        off = _AXES @ origin / h + _OFFSET  # (3, 2)
        # Per band: its first pixel's coordinates; then shifted by whole periods so the band's
        # corners fall on the tiled texture (its lowest corner in the first period).
        t = off[:, None, :] + np.einsum("kij,nj->kni", lin, corner)  # (3, n, 2)
        low = np.minimum(lin[:, None, :, :] * extent[None, :, None, :], 0.0).sum(-1)
        t -= np.floor((t + low) / PERIOD) * PERIOD
        mats = np.concatenate(
            [np.broadcast_to(lin[:, None], (3, len(regions), 2, 2)), t[..., None]], axis=-1
        ).astype(np.float32)  # (3, n, 2, 3)
        kb = 2 * int(math.ceil(2.5 * lateral_blur_px)) + 1
        for n, (r0, r1, c0, c1) in enumerate(regions):  # a band at a time: stays in cache
            roi = [buf[r0:r1, c0:c1] for buf in bufs]
            for k in range(3):
                cv2.warpAffine(
                    self._tex,
                    mats[k, n],
                    (c1 - c0, r1 - r0),
                    dst=roi[k],
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_REPLICATE,
                )
            cv2.add(roi[0], roi[1], dst=roi[0])  # at most 3 * _MAX = 255: no saturation
            cv2.add(roi[0], roi[2], dst=roi[0])
            if lateral_blur_px > 0.0:  # the beam's width: speckle longer across the beam
                cv2.GaussianBlur(roi[0], (kb, 1), sigmaX=lateral_blur_px, sigmaY=0, dst=roi[1])
        return bufs[1] if lateral_blur_px > 0.0 else bufs[0]

    def _lut(self, gamma: float, lateral_blur_px: float) -> NDArray[np.float32]:
        """``|I + jQ| ** gamma`` by the uint16 ``I + 256 Q`` of :meth:`_iq`, scaled to mean 1 on
        the reference plane at this blur."""
        key = (float(gamma), float(lateral_blur_px))
        lut = self._luts.get(key)
        if lut is None:
            i = np.arange(256, dtype=np.float64) - 3 * _MEAN
            mag2 = i[None, :] ** 2 + i[:, None] ** 2  # [q, i]
            lut = (mag2 ** (gamma / 2.0)).astype(np.float32).reshape(-1)
            ref = self._iq(*_REF_PLANE, lateral_blur_px)
            lut /= float(np.mean(lut[ref.view(np.uint16)[..., 0]]))
            self._luts[key] = lut
        return lut

    def contrast(
        self,
        origin: NDArray[np.float64],
        ex: NDArray[np.float64],
        ey: NDArray[np.float64],
        width: int,
        height: int,
        lateral_blur_px: float = 0.0,
        gamma: float = 1.0,
        regions: Regions | None = None,
    ) -> NDArray[np.float32]:
        """(height, width) float32 ``envelope ** gamma`` at the pixels ``origin + col * ex + row
        * ey`` (patient frame, m; ``ex``, ``ey``: the step per column and per row), scaled to
        mean 1 on a reference plane. The envelope is ``|I + jQ|`` of the two Gaussian fields,
        Rayleigh distributed, its I and Q blurred along the rows by a Gaussian of
        ``lateral_blur_px`` (the beam's width); ``gamma`` < 1 lowers its contrast as a
        scanner's speckle reduction does. ``regions``: (row0, row1, col0, col1) bands of the
        image that are needed (the rest is undefined), e.g. a field of view and the blur's
        margin, which costs two thirds of the rectangle's time."""
        lut = self._lut(gamma, lateral_blur_px)
        iq = self._iq(origin, ex, ey, width, height, lateral_blur_px, regions)
        index = iq.view(np.uint16)[..., 0]  # I + 256 Q (or Q + 256 I: the table is symmetric)
        return np.take(lut, index)
