"""The simulated ultrasound: a B-mode-like image of the phantom under the probe.

Per frame: the probe's image plane (tip x-z plane, see :mod:`humantele.video.scan`) is placed
in the patient frame from ``T_world_tip`` and the patient ellipsoid; along each beam the
phantom (:mod:`humantele.video.phantom`) gives each sample a region, hence a mean echo, a
specular boundary echo where the region changes, and an attenuation. The round-trip loss is
accumulated along the beam and compensated by a time-gain compensation (TGC) for
``tgc_db_cm_mhz``, so fluid shows enhancement beneath and bone a shadow. The beam grid is
scan-converted to the image, multiplied by speckle fixed in the tissue
(:mod:`humantele.video.speckle`), a little per-frame electronic noise is added and the result
is log-compressed over ``dynamic_range_db`` to 8 bit grey (soft tissue of echo 1 at mid grey).

Coupling (per beam, in [0, 1]): the force factor ``(F - min_force_n) / (full_force_n -
min_force_n)`` clipped to [0, 1], times the face contact of the beam: 1 where the beam's point
on the face is inside the skin or within ``conform_m_per_n * F`` (the skin wraps around a
pressed face, at most ``max_conform_m``) of it, falling to 0 over 2 mm more. No force below
``min_force_n``, or a probe off the skin: a dark image with faint noise only. Pressing lightly
with a curved face images the middle beams only, as on a real probe.

Image quality (``meta["quality"]``, the known answer used in place of human ratings):

    Q = (1 / A_max) * integral over the image plane of  [p in target] [p in the field of view]
        c(beam(p)) [not shadowed(p)]  dA

where ``A_max = pi * s1 * s2`` is the area of the target ellipsoid's largest cross-section
(``s1 >= s2`` its two largest semi-axes), ``c`` the coupling of the beam through p, and p is
shadowed when the round-trip loss to it exceeds the TGC's nominal loss by more than
``shadow_db`` (20 dB; a rib or the spine gives > 80 dB, soft-tissue differences < 10 dB).
Q is 0 without contact or off the target and about 1 with the probe pressed on the target,
its longest section in the plane and no bone over it; computed on the beam grid (each sample
weighs the area it stands for), so it is exact to the grid (< 2 % at the default grid).

Image: columns along tip +x (the probe's array; the image's left is tip -x, where a small dot
marks the orientation), rows along the beam (depth), ``pixel_spacing_mm`` square; depth ticks
every cm outside the field of view on the right; the frame counter in the top-left corner.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from humantele.geometry import quat_to_matrix
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.video.phantom import Phantom
from humantele.video.scan import ScanGeometry
from humantele.video.scene import SceneSnapshot, pose_is_finite
from humantele.video.sim_config import SimUltrasoundConfig  # noqa: F401 (their home before)
from humantele.video.simsource import Rendered, SimVideoSource
from humantele.video.speckle import SpeckleField

STEP = 2  # the image is computed at every STEP-th column, then stretched
PSF_SAMPLES, PSF_BEAMS = 1.1, 1.1  # point spread on the beam grid (samples, beams)
LATERAL_BLUR_PX = 2.0
SPECKLE_GAMMA = 0.6  # of the half-width image: the beam's width
NOISE_BANK = 4  # precomputed electronic-noise images, one picked at random per frame (never
# the last frame's: electronic noise is never the same twice)
SPECKLE_BANDS = 6  # the speckle is made in this many bands of rows, each as wide as the fan
CONTACT_RAMP_M = 0.002
MID_GREY = 95.0  # display level of soft tissue (echo 1, speckle mean)
DB_PER_NEPER = 20.0 / math.log(10.0)


class SimUltrasound(SimVideoSource):
    """B-mode-like frames of the phantom from the scene's probe pose and force; ``kind`` "us".

    ``geometry`` (:class:`ScanGeometry`) holds the field of view, its mask and the pixel
    spacing. ``meta`` of each frame: ``quality`` (see the module docstring), ``target``,
    ``coupling`` (mean over the beams), ``force_n``, ``valid`` (False: unusable input).
    """

    name = "sim ultrasound"
    kind = "us"

    def __init__(self, config: SimUltrasoundConfig | None = None, scene=None, **kw) -> None:
        c = config or SimUltrasoundConfig()
        super().__init__(c, scene, **kw)
        self.geometry = g = ScanGeometry(
            c.probe,
            c.width,
            c.height,
            c.depth_m,
            c.fov_deg,
            c.radius_m,
            c.aperture_m,
            c.beams,
            c.samples,
        )
        diag = math.hypot(c.width, c.height) * g.spacing_m
        self.speckle = SpeckleField(c.speckle_m, diag, c.seed)
        rng = np.random.default_rng(c.seed + 1)
        self._rng = np.random.default_rng(c.seed + 2)
        mask = g.fov_mask_at(STEP).astype(np.float32)
        self._bands = _bands(mask > 0, SPECKLE_BANDS, int(math.ceil(2.5 * LATERAL_BLUR_PX)) + 1)
        self._diffuse = np.zeros(mask.shape, dtype=np.float32)  # scan-converted in the bands
        self._specular = np.zeros(mask.shape, dtype=np.float32)
        self._noise = []
        for _ in range(NOISE_BANK):
            n = rng.standard_normal((*mask.shape, 2)).astype(np.float32)
            env = cv2.magnitude(n[..., 0], n[..., 1]) * (c.noise / math.sqrt(math.pi / 2.0))
            self._noise.append(env * mask)
        self._noise_k = 0  # the last frame's noise image
        # Display: pixel = a * ln(amp) + b, with amp 1 at MID_GREY (+ gain).
        self._a = 255.0 / c.dynamic_range_db * DB_PER_NEPER
        self._b = MID_GREY + 255.0 / c.dynamic_range_db * c.gain_db
        self._amp_floor = math.exp(-self._b / self._a)
        dr_cm = c.depth_m / c.samples * 100.0
        self._loss_per_atten = 2.0 * c.frequency_mhz * dr_cm  # dB per (dB/cm/MHz) per sample
        self._tgc_db = (2.0 * c.frequency_mhz * c.tgc_db_cm_mhz * g.range_m * 100.0).astype(
            np.float32
        )
        nb, ns = -(-g.beams // 2), -(-g.samples // 4)
        bi = np.minimum(np.arange(nb) * 2, g.beams - 1)
        si = np.minimum(np.arange(ns) * 4, g.samples - 1)
        self._blob_rows = (bi, si)
        self._blob_shape = (nb, ns)
        self._cell_area = g.cell_area_m2.reshape(g.beams, g.samples).astype(np.float64)
        self._phantom: Phantom | None = None
        self._phantom_key: bytes | None = None
        overlay = self._make_overlay()
        self._overlay_at = np.flatnonzero(overlay)
        self._overlay_val = overlay.reshape(-1)[self._overlay_at]

    def _spacing_mm(self) -> tuple[float, float]:
        return self.geometry.pixel_spacing_mm

    def _depth_origin_row(self) -> float:
        return self.geometry.depth_origin_row

    # ------------------------------------------------------------------ input
    def _usable(self, s: SceneSnapshot) -> bool:
        if not super()._usable(s):
            return False
        if s.T_world_tip is not None and not pose_is_finite(s.T_world_tip):
            return False
        return s.patient is None or isinstance(s.patient, Ellipsoid)

    def phantom_for(self, patient: Ellipsoid) -> Phantom:
        """The phantom placed in ``patient`` (cached while the patient stays the same)."""
        key = patient.as_array().tobytes()
        if self._phantom is None or key != self._phantom_key:
            self._phantom = phantom = Phantom(self.config.phantom, patient, self.config.seed)
            self._phantom_key = key
            # Per sample: dB of round-trip loss by label; the target's largest section (m^2).
            self._loss_table = phantom.attenuation * np.float32(self._loss_per_atten)
            _, axes = phantom.organ(self.config.target)
            self._a_max = math.pi * float(np.prod(np.sort(axes)[1:]))
        return self._phantom

    # ------------------------------------------------------------------ rendering
    def _render(self, s: SceneSnapshot) -> Rendered:
        c = self.config
        meta = {"quality": 0.0, "target": c.target, "coupling": 0.0, "force_n": float(s.force_n)}
        if s.patient is None or s.T_world_tip is None:
            image, _ = self._blank()
            return image, {**meta, "valid": True}
        phantom = self.phantom_for(s.patient)
        # T_patient_tip = T_world_patient^-1 @ T_world_tip, as matrices (the Pose algebra in
        # pure Python cost as much as the phantom's labels).
        R_wp, centre = s.patient.rotation, s.patient.center
        R = R_wp.T @ quat_to_matrix(s.T_world_tip.quaternion)
        t = (np.asarray(s.T_world_tip.position, dtype=float) - centre) @ R_wp
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("non-finite probe pose in the patient frame")
        coupling = self._coupling(phantom, R, t, float(s.force_n))
        if not np.any(coupling > 0.0):
            image, _ = self._blank()
            return image, {**meta, "valid": True}
        diffuse, specular, quality = self._beams(phantom, R, t, coupling)
        image = self._compose(diffuse, specular, R, t)
        meta.update(quality=quality, coupling=float(coupling.mean()), valid=True)
        return image, meta

    def _beams(
        self, phantom: Phantom, R: np.ndarray, t: np.ndarray, coupling: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """The echo along every beam: (diffuse, specular) (beams, samples) amplitude grids and
        the image quality (module docstring). ``R``, ``t``: ``T_patient_tip``."""
        c, g = self.config, self.geometry
        starts = g.face.astype(np.float64) @ R.T + t  # each beam's start and direction, patient
        dirs = g.direction.astype(np.float64) @ R.T
        labels, _, target = phantom.along_rays(starts, dirs, g.range_m, c.target)
        assert target is not None
        echo = np.take(phantom.echo, labels)
        self._texture(phantom, labels, echo, starts, dirs)
        # Specular echoes where a beam crosses from one region into another.
        bound = np.take(phantom.boundary, labels)
        spec = np.zeros_like(bound)
        np.maximum(bound[:, 1:], bound[:, :-1], out=spec[:, 1:])
        spec[:, 1:] *= labels[:, 1:] != labels[:, :-1]
        # Round-trip loss down to each sample (half of its own), less what the TGC restores.
        loss = np.take(self._loss_table, labels)
        excess = np.cumsum(loss, axis=1, dtype=np.float32)
        excess -= 0.5 * loss
        excess -= self._tgc_db
        gain = cv2.exp(np.clip(excess, -20.0, 120.0) * np.float32(-math.log(10.0) / 20.0))
        gain *= coupling[:, None]
        # The pulse's length and the beam's width: a point echo spreads over ~2 samples
        # along and across the beams (bone surfaces and capsules become lines, not dots).
        psf = {"ksize": (5, 5), "sigmaX": PSF_SAMPLES, "sigmaY": PSF_BEAMS}
        diffuse = cv2.GaussianBlur(echo * gain, **psf)
        specular = cv2.GaussianBlur(spec * gain, **psf)
        visible = excess < c.shadow_db
        visible &= target
        area = np.sum(self._cell_area, axis=1, where=visible)
        quality = float(np.clip(float(area @ coupling) / self._a_max, 0.0, 1.0))
        return diffuse, specular, quality

    def _texture(self, phantom: Phantom, labels, echo, starts, dirs) -> None:
        """Multiply ``echo`` (beams, samples) in place by the phantom's blob texture,
        evaluated on every 2nd beam and 4th sample (the blobs are coarse) and interpolated."""
        if not phantom.texture.any():
            return
        g = self.geometry
        bi, si = self._blob_rows
        pts = starts[bi, None, :] + g.range_m[si].astype(np.float64)[None, :, None] * dirs[bi, None]
        field = phantom.blobs(tuple(pts[..., k].astype(np.float32).reshape(-1) for k in range(3)))
        if field is None:
            return
        field = cv2.resize(
            field.reshape(self._blob_shape), (g.samples, g.beams), interpolation=cv2.INTER_LINEAR
        )
        field *= np.take(phantom.texture, labels)
        echo *= cv2.exp(field)

    def _coupling(self, phantom: Phantom, R: np.ndarray, t: np.ndarray, force: float) -> np.ndarray:
        c, g = self.config, self.geometry
        f = np.clip((force - c.min_force_n) / (c.full_force_n - c.min_force_n), 0.0, 1.0)
        if f <= 0.0:
            return np.zeros(g.beams, dtype=np.float32)
        face = g.face.astype(np.float64) @ R.T + t
        gap = -phantom.depth_below_skin(tuple(face.T))
        conform = min(c.conform_m_per_n * max(force, 0.0), c.max_conform_m)
        contact = np.clip(1.0 - (gap - conform) / CONTACT_RAMP_M, 0.0, 1.0)
        return (f * contact).astype(np.float32)

    def _compose(self, diffuse_grid, specular_grid, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Scan conversion, speckle, noise, log compression, at every other column (lateral
        resolution is coarser than axial), then stretched to the full width."""
        c, g = self.config, self.geometry
        diffuse = g.to_image(diffuse_grid, STEP, self._bands, self._diffuse)
        specular = g.to_image(specular_grid, STEP, self._bands, self._specular)
        ex, ey = R[:, 0] * g.spacing_m, R[:, 2] * g.spacing_m
        x0, z0 = g.origin_m
        origin = t + R[:, 0] * x0 + R[:, 2] * z0 + ex * (STEP - 1) / 2.0
        # Speckle contrast as a scanner shows it after its speckle reduction: env ** gamma.
        speckle = self.speckle.contrast(
            origin,
            STEP * ex,
            ey,
            diffuse.shape[1],
            c.height,
            LATERAL_BLUR_PX,
            SPECKLE_GAMMA,
            self._bands,
        )
        amp = cv2.multiply(diffuse, speckle, dst=speckle)
        amp += specular
        amp += self._next_noise()
        return self._display(amp)

    def _display(self, amp: np.ndarray) -> np.ndarray:
        """(H, W/STEP) amplitude to the (H, W, 3) BGR grey image with its overlay."""
        c = self.config
        np.maximum(amp, self._amp_floor, out=amp)
        cv2.log(amp, amp)
        gray = cv2.convertScaleAbs(amp, alpha=self._a, beta=self._b)
        gray = cv2.resize(gray, (c.width, c.height), interpolation=cv2.INTER_LINEAR)
        gray.reshape(-1)[self._overlay_at] = self._overlay_val
        return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)

    def _next_noise(self) -> np.ndarray:
        """A noise image at random, another than the last frame's."""
        self._noise_k = (self._noise_k + 1 + int(self._rng.integers(NOISE_BANK - 1))) % NOISE_BANK
        return self._noise[self._noise_k]

    def _blank(self) -> Rendered:
        amp = self._next_noise().copy()
        meta = {"quality": 0.0, "target": self.config.target, "coupling": 0.0, "force_n": 0.0}
        return self._display(amp), meta

    def _make_overlay(self) -> np.ndarray:
        """Grey levels drawn over the image outside the field of view (0 = none): depth ticks
        every 1 cm on the right (5 cm longer) and the orientation dot at the image's left."""
        c, g = self.config, self.geometry
        ov = np.zeros((c.height, c.width), dtype=np.uint8)
        for k in range(int(c.depth_m * 100) + 1):
            row = int(round(g.tip_to_pixel(0.0, k * 0.01)[0]))
            length = 10 if k % 5 == 0 else 5
            if 0 <= row < c.height:
                ov[max(row - 1, 0) : row + 1, c.width - 4 - length : c.width - 4] = 160
        row, col = g.tip_to_pixel(float(g.face[0, 0]) - 0.006, float(g.face[0, 2]) + 0.002)
        row, col = min(max(row, 4.0), c.height - 5.0), min(max(col, 4.0), c.width - 5.0)
        cv2.circle(ov, (int(round(col)), int(round(row))), 3, 200, -1)
        ov[g.fov_mask] = 0
        return ov


def _bands(mask: np.ndarray, n: int, margin: int) -> list[tuple[int, int, int, int]]:
    """``n`` bands of rows (row0, row1, col0, col1) covering the True pixels of ``mask`` and
    ``margin`` columns beside them."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return [(0, mask.shape[0], 0, mask.shape[1])]
    edges = np.linspace(rows[0], rows[-1] + 1, n + 1).round().astype(int)
    out = []
    for r0, r1 in zip(edges[:-1], edges[1:], strict=True):
        cols = np.flatnonzero(mask[r0:r1].any(axis=0))
        if r1 > r0 and cols.size:
            c0, c1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, mask.shape[1])
            out.append((int(r0), int(r1), c0, c1))
    return out
