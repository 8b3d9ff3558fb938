"""Speckle tied to the tissue: a fixed random 3D field sampled on the image plane.

The field is the envelope ``sqrt(I^2 + Q^2)`` of two smooth Gaussian fields (so its values
are Rayleigh distributed, as a B-mode speckle's are), each the sum of one periodic 2D noise
texture seen along three oblique directions of the patient frame: ``T(B_k p)`` for k = 1..3,
``B_k`` the rows of a fixed rotation taken two at a time. A function of the patient-frame point
only, so the speckle moves with the anatomy when the probe moves; any image plane cuts at
least two of the three projections at a slant, so there are no streaks. The image plane maps
affinely to each texture, so a frame costs three ``cv2.warpAffine``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import quat_from_axis_angle, quat_to_matrix

PERIOD = 256  # texels of the periodic texture
_STD = 40.0  # grey levels per standard deviation of the uint8 texture (mean 128)
# A generic fixed rotation: no texture direction lies along a patient axis.
_B = quat_to_matrix(quat_from_axis_angle((0.41, 0.77, 0.49), 0.93))
_PLANES = [(_B[0], _B[1]), (_B[1], _B[2]), (_B[2], _B[0])]
_OFFSETS = [(0.0, 0.0), (0.37 * PERIOD, 0.61 * PERIOD), (0.71 * PERIOD, 0.19 * PERIOD)]


class SpeckleField:
    """The speckle envelope (mean 1) at any plane's pixels; ``texel_m`` sets the grain.

    ``max_extent_m``: the largest distance across any image it will be asked for (the
    texture is tiled that much beyond one period, so no lookup falls off it). The texture is
    uint8 with 4 channels (I, Q and two unused), the layout ``cv2.warpAffine`` is fastest on.
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
        tex[..., :2] = np.clip(np.rint(tiled * _STD + 128.0), 0, 255)
        self._tex = tex
        # E|I + jQ| for I, Q ~ N(0, 3 STD^2): normalise the envelope to mean 1.
        self._norm = 1.0 / (math.sqrt(3.0) * _STD * math.sqrt(math.pi / 2.0))

    def gaussian(self, points: tuple[NDArray[np.float32], ...]) -> NDArray[np.float32]:
        """The smooth Gaussian field (mean 0, std about 1) at patient-frame points (x, y, z
        float32 arrays, m), e.g. a coarse field (a large ``texel_m``) for organ texture."""
        x, y, z = points
        acc = None
        h = self.texel_m
        for (u, v), (ou, ov) in zip(_PLANES, _OFFSETS, strict=True):
            mu = (
                (x * np.float32(u[0] / h) + y * np.float32(u[1] / h) + z * np.float32(u[2] / h))
                + np.float32(ou)
            ) % PERIOD
            mv = (
                (x * np.float32(v[0] / h) + y * np.float32(v[1] / h) + z * np.float32(v[2] / h))
                + np.float32(ov)
            ) % PERIOD
            s = cv2.remap(
                self._tex,
                mu.reshape(1, -1),
                mv.reshape(1, -1),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )[0, :, 0].astype(np.float32)
            acc = s if acc is None else acc + s
        return (acc - 3 * 128.0) * np.float32(1.0 / (math.sqrt(3.0) * _STD))

    def envelope(
        self,
        origin: NDArray[np.float64],
        ex: NDArray[np.float64],
        ey: NDArray[np.float64],
        width: int,
        height: int,
        lateral_blur_px: float = 0.0,
    ) -> NDArray[np.float32]:
        """(height, width) float32 speckle at the pixels ``origin + col * ex + row * ey``
        (patient frame, m; ``ex``, ``ey``: the step per column and per row), its I and Q
        blurred along the rows by a Gaussian of ``lateral_blur_px`` (the beam's width; the
        blur lowers the mean, which the caller scales back)."""
        h = self.texel_m
        quad = np.array([[0, width, 0, width], [0, 0, height, height]], dtype=float)
        acc = None
        for (u, v), (ou, ov) in zip(_PLANES, _OFFSETS, strict=True):
            a = np.array(
                [
                    [u @ ex / h, u @ ey / h, u @ origin / h + ou],
                    [v @ ex / h, v @ ey / h, v @ origin / h + ov],
                ]
            )
            # Shift by whole periods so the image's corners fall on the tiled texture.
            corners = a[:, :2] @ quad + a[:, 2:]
            a[:, 2] -= np.floor(corners.min(axis=1) / PERIOD) * PERIOD
            s = cv2.warpAffine(
                self._tex,
                a.astype(np.float32),
                (width, height),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_REPLICATE,
            )
            acc = s if acc is None else cv2.add(acc, s, dtype=cv2.CV_16S)
        i, q, _, _ = cv2.split(acc)
        i = cv2.subtract(i, 3 * 128, dtype=cv2.CV_32F)
        q = cv2.subtract(q, 3 * 128, dtype=cv2.CV_32F)
        if lateral_blur_px > 0.0:  # the beam's width: speckle longer across the beam
            i = cv2.GaussianBlur(i, (0, 0), sigmaX=lateral_blur_px, sigmaY=0.01)
            q = cv2.GaussianBlur(q, (0, 0), sigmaX=lateral_blur_px, sigmaY=0.01)
        env = cv2.magnitude(i, q)
        env *= self._norm
        return env
