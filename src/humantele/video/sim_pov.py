"""The simulated point of view (POV): what the headset's camera sees of the scene.

Drawn with numpy and OpenCV, no 3D engine, from the scene's ``T_world_head`` (the POV camera,
OpenCV axes: x right, y down, z forward) through a pinhole of ``hfov_deg`` horizontal field of
view: a wall and the floor (world y = 0), the bed (a box under the patient), the patient (the
ellipsoid, cut to ``body_half_length_m`` along the body, ray cast at ``shade_scale`` of the
resolution and shaded by a head light and a ceiling light), the tracked real probe (opaque) and
the virtual probe (translucent, another colour) as boxes in their tip frames. Polygons are cut
at the near plane; faces turned away are not drawn; the probes are drawn over the patient (the
mixed-reality capture draws holograms over the world the same way).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.video.scene import SceneSnapshot, pose_is_finite
from humantele.video.sim_config import SimPovConfig  # noqa: F401 (their home before)
from humantele.video.simsource import Rendered, SimVideoSource

NEAR_M = 0.02
BGR = tuple[int, int, int]
# Transducer as two boxes in its tip frame (m): the head (array along x) and the handle.
PROBE_BOXES = (
    ((-0.030, -0.012, -0.035), (0.030, 0.012, 0.0)),
    ((-0.016, -0.011, -0.140), (0.016, 0.011, -0.035)),
)
# Box faces as corner indices (corner i has x, y, z from bit 0, 1, 2: 0 = min, 1 = max).
_FACES = ((0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5))
_BITS = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], dtype=float)


def _clip_near(poly: NDArray[np.float64]) -> NDArray[np.float64]:
    """The part of a camera-frame polygon (N, 3) with z >= NEAR_M (Sutherland-Hodgman)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= NEAR_M, b[2] >= NEAR_M
        if ina:
            out.append(a)
        if ina != inb:
            s = (NEAR_M - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


class SimPov(SimVideoSource):
    """POV frames of the scene from its ``T_world_head``; ``kind`` "pov".

    A snapshot without a head pose, or with a non-finite pose or force, gives a blank (wall
    colour) frame, counted in ``counters.invalid`` when the input was bad.
    """

    name = "sim pov"
    kind = "pov"

    def __init__(self, config: SimPovConfig | None = None, scene=None, **kw) -> None:
        c = config or SimPovConfig()
        super().__init__(c, scene, **kw)
        w, h = c.width, c.height
        self.fx = (w / 2.0) / math.tan(math.radians(c.hfov_deg) / 2.0)
        self.cx, self.cy = (w - 1) / 2.0, (h - 1) / 2.0
        sw, sh = max(int(round(w * c.shade_scale)), 8), max(int(round(h * c.shade_scale)), 8)
        self._shade_size = (sw, sh)
        u = (np.arange(sw) + 0.5) * (w / sw) - 0.5
        v = (np.arange(sh) + 0.5) * (h / sh) - 0.5
        uu, vv = np.meshgrid(u, v)
        # Camera-frame ray (x, y, 1) of each shading pixel.
        self._ray_x = ((uu - self.cx) / self.fx).astype(np.float32)
        self._ray_y = ((vv - self.cy) / self.fx).astype(np.float32)
        self._background = np.empty((h, w, 3), dtype=np.uint8)
        self._background[:] = c.wall

    # ------------------------------------------------------------------ geometry
    def project(self, T_world_head: Pose, points_world: NDArray) -> NDArray[np.float64]:
        """Pixel (u, v) = (column, row) of world points (..., 3) seen from ``T_world_head``;
        NaN for points behind the near plane."""
        p = T_world_head.inverse().apply(np.asarray(points_world, dtype=float))
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack(
                [self.fx * p[..., 0] / z + self.cx, self.fx * p[..., 1] / z + self.cy], -1
            )
        uv[z < NEAR_M] = np.nan
        return uv

    def _usable(self, s: SceneSnapshot) -> bool:
        if not super()._usable(s):
            return False
        poses = (s.T_world_head, s.T_world_tip, s.T_world_virtual_tip)
        if any(p is not None and not pose_is_finite(p) for p in poses):
            return False
        return s.patient is None or isinstance(s.patient, Ellipsoid)

    # ------------------------------------------------------------------ drawing
    def _render(self, s: SceneSnapshot) -> Rendered:
        if s.T_world_head is None:
            return self._blank()
        c = self.config
        T_cam_world = s.T_world_head.inverse()
        img = self._background.copy()
        floor = np.array([[-3.0, 0.0, -3.0], [3.0, 0.0, -3.0], [3.0, 0.0, 3.0], [-3.0, 0.0, 3.0]])
        centre = s.patient.center if s.patient is not None else s.T_world_head.position
        floor[:, [0, 2]] += np.asarray(centre)[[0, 2]]
        self._polygon(img, T_cam_world.apply(floor), c.floor)
        if s.patient is not None:
            self._bed(img, s.patient, T_cam_world)
            self._patient(img, s.patient, T_cam_world)
        if s.T_world_tip is not None:
            self._probe(img, T_cam_world @ s.T_world_tip, c.real_probe, 1.0)
        if s.T_world_virtual_tip is not None:
            self._probe(img, T_cam_world @ s.T_world_virtual_tip, c.virtual_probe, c.virtual_alpha)
        return img, {"valid": True}

    def _blank(self) -> Rendered:
        return self._background.copy(), {"valid": True}

    def _polygon(
        self,
        img: NDArray[np.uint8],
        poly_cam: NDArray,
        color: BGR,
        outward: NDArray | None = None,
        origin: tuple[int, int] = (0, 0),
    ) -> None:
        """Fill a camera-frame polygon (N, 3) into ``img``, whose pixel (0, 0) is the full
        image's ``origin`` (col, row). With an ``outward`` normal (camera frame) it is drawn
        only when it faces the camera, flat shaded by the angle it is seen at."""
        if outward is not None:
            centre = poly_cam.mean(axis=0)
            facing = float(outward @ centre)
            if facing >= 0.0:
                return
            k = 0.45 + 0.55 * -facing / (np.linalg.norm(outward) * np.linalg.norm(centre) + 1e-12)
            color = tuple(int(min(255, ch * k)) for ch in color)
        poly = _clip_near(poly_cam)
        if len(poly) < 3:
            return
        uv = np.stack(
            [
                self.fx * poly[:, 0] / poly[:, 2] + self.cx,
                self.fx * poly[:, 1] / poly[:, 2] + self.cy,
            ],
            -1,
        )
        if not np.all(np.isfinite(uv)):
            return
        lim = 8.0 * max(self.config.width, self.config.height)
        uv = np.clip(uv, -lim, lim) - np.asarray(origin, dtype=float)
        pts = np.rint(uv * 16.0).astype(np.int32)
        cv2.fillPoly(img, [pts], color, lineType=cv2.LINE_AA, shift=4)

    def _box(self, img, T_cam_box: Pose, lo, hi, color: BGR, origin=(0, 0)) -> None:
        lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        cam = (lo + _BITS * (hi - lo)) @ T_cam_box.rotation_matrix.T + T_cam_box.position
        centre = cam.mean(axis=0)
        for f in _FACES:
            face = cam[list(f)]
            self._polygon(img, face, color, face.mean(axis=0) - centre, origin)

    def _bed(self, img, patient: Ellipsoid, T_cam_world: Pose) -> None:
        c = self.config
        _, b, _ = patient.semi_axes
        top, bottom = -float(b), -float(patient.center[1])  # patient y of bed top and floor
        lo = (-c.bed_length_m / 2 + 0.3, bottom, -c.bed_width_m / 2)
        hi = (c.bed_length_m / 2 + 0.3, top, c.bed_width_m / 2)
        if hi[1] > lo[1]:
            self._box(img, T_cam_world @ patient.T_world_patient, lo, hi, c.bed)

    def _bbox(self, points_cam: NDArray, margin: int = 2) -> tuple[int, int, int, int] | None:
        """(row0, row1, col0, col1) of the full image holding the projection of camera-frame
        points (whole image if some lie behind the near plane); None if it is off-image."""
        c = self.config
        if np.any(points_cam[:, 2] < NEAR_M):
            return (0, c.height, 0, c.width)
        u = self.fx * points_cam[:, 0] / points_cam[:, 2] + self.cx
        v = self.fx * points_cam[:, 1] / points_cam[:, 2] + self.cy
        c0, c1 = max(int(u.min()) - margin, 0), min(int(u.max()) + margin + 1, c.width)
        r0, r1 = max(int(v.min()) - margin, 0), min(int(v.max()) + margin + 1, c.height)
        return None if c0 >= c1 or r0 >= r1 else (r0, r1, c0, c1)

    def _patient(self, img: NDArray[np.uint8], patient: Ellipsoid, T_cam_world: Pose) -> None:
        """Ray cast the ellipsoid (cut at +-body_half_length_m) at the shading resolution,
        over the projection of its bounding box only."""
        c = self.config
        semi = np.array(patient.semi_axes, dtype=float)
        L = min(c.body_half_length_m, semi[0])
        T_cam_patient = T_cam_world @ patient.T_world_patient
        ext = np.array([L, semi[1], semi[2]])
        box = self._bbox(T_cam_patient.apply((_BITS * 2 - 1) * ext))
        if box is None:
            return
        sw, sh = self._shade_size
        fy, fx = sh / c.height, sw / c.width
        r0, r1 = int(box[0] * fy), min(int(np.ceil(box[1] * fy)) + 1, sh)
        c0, c1 = int(box[2] * fx), min(int(np.ceil(box[3] * fx)) + 1, sw)
        rx, ry = self._ray_x[r0:r1, c0:c1], self._ray_y[r0:r1, c0:c1]
        T_patient_cam = T_cam_patient.inverse()
        R = T_patient_cam.rotation_matrix
        o = T_patient_cam.position
        inv = 1.0 / semi
        o2 = o * inv
        C = float(o2 @ o2) - 1.0
        if C <= 0.0:  # the camera is inside the patient: nothing sensible to draw
            return
        # Ray directions in the patient frame, one array per axis (float32).
        d = [
            rx * np.float32(R[i, 0]) + ry * np.float32(R[i, 1]) + np.float32(R[i, 2])
            for i in range(3)
        ]
        d2 = [d[i] * np.float32(inv[i]) for i in range(3)]
        A = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
        B = d2[0] * np.float32(o2[0]) + d2[1] * np.float32(o2[1]) + d2[2] * np.float32(o2[2])
        disc = B * B - A * np.float32(C)
        hit = disc > 0.0
        t1 = (-B - np.sqrt(np.maximum(disc, 0.0))) / A
        px = np.float32(o[0]) + t1 * d[0]
        hit &= (t1 > NEAR_M) & (np.abs(px) <= L)
        if not hit.any():
            return
        # Lambert shading at the hits: a head light (along the ray) and a ceiling light.
        idx = np.flatnonzero(hit)
        th = t1.reshape(-1)[idx]
        dh = [di.reshape(-1)[idx] for di in d]
        n = [(np.float32(o[i]) + th * dh[i]) * np.float32(inv[i] ** 2) for i in range(3)]
        n_len = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) + np.float32(1e-12)
        d_len = np.sqrt(dh[0] * dh[0] + dh[1] * dh[1] + dh[2] * dh[2])
        head = -(n[0] * dh[0] + n[1] * dh[1] + n[2] * dh[2]) / (n_len * d_len)
        ceiling = n[1] / n_len  # patient y is world up
        k = np.zeros(hit.shape, dtype=np.float32)
        k.reshape(-1)[idx] = 0.3 + 0.45 * np.clip(head, 0.0, 1.0) + 0.3 * np.clip(ceiling, 0.0, 1.0)
        R0, R1 = int(round(r0 / fy)), min(int(round(r1 / fy)), c.height)
        C0, C1 = int(round(c0 / fx)), min(int(round(c1 / fx)), c.width)
        size = (C1 - C0, R1 - R0)
        if size[0] <= 0 or size[1] <= 0:
            return
        shade = cv2.merge([cv2.convertScaleAbs(k, alpha=float(ch)) for ch in c.skin])
        shade = cv2.resize(shade, size)
        # The silhouette: where a smooth "inside" measure, stretched bilinearly, is > 0: the
        # ray's discriminant (its sign) and the distance inside the cut ends.
        inside = np.minimum(disc / (A * A), (L - np.abs(px)) * np.float32(1.0 / L))
        inside[t1 <= NEAR_M] = -1.0
        mask = cv2.resize(inside, size) > 0.0
        cv2.copyTo(shade, mask.view(np.uint8), img[R0:R1, C0:C1])

    def _probe(self, img: NDArray[np.uint8], T_cam_tip: Pose, color: BGR, alpha: float) -> None:
        """The transducer's boxes; translucent when ``alpha`` < 1 (drawn over a copy of the
        region it covers, then blended back)."""
        corners = np.array([p for box in PROBE_BOXES for p in box])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        box = self._bbox(T_cam_tip.apply(lo + _BITS * (hi - lo)))
        if box is None:
            return
        boxes = sorted(PROBE_BOXES, key=lambda lh: -T_cam_tip.apply(np.add(*lh) / 2.0)[2])
        if alpha >= 1.0:
            for lo_, hi_ in boxes:  # far box first
                self._box(img, T_cam_tip, lo_, hi_, color)
            return
        r0, r1, c0, c1 = box
        roi = img[r0:r1, c0:c1]
        layer = roi.copy()
        for lo_, hi_ in boxes:
            self._box(layer, T_cam_tip, lo_, hi_, color, origin=(c0, r0))
        cv2.addWeighted(layer, alpha, roi, 1.0 - alpha, 0.0, dst=roi)
