"""Simulated AHAT-like IR + depth frames of the probe's marker spheres at a known pose.

What is modelled (each term scaled by ``noise_scale``):

- marker spheres by ray casting (4 x 4 supersampling per pixel) so their images have the right
  size and perspective elongation; brightness falling as 1/range^2, optical blur (Gaussian
  PSF), shot and read noise, saturation (clipped counts);
- depth as time-of-flight range along each ray: surface of the sphere, noise growing with
  range^2 and stronger on saturated pixels, some saturated pixels invalid (0), mixed pixels
  at blurred edges (range weighted by brightness), 1 mm quantisation, wrap-around beyond
  ``depth_wrap_m``;
- the scene: a tilted patient/bed plane with IR texture, static bright clutter (bed rails,
  cables), spurious reflections (gel glints, the probe's shell) near the probe and anywhere,
  partial occlusion of a sphere by a finger, markers fully hidden on request (a finger in
  front of them);
- retro-reflective strays shaped like the markers (a ring, a button, a loose sphere) and a
  second marker tool in view, drawn by the same sphere renderer: the scenes where two real
  markers and a stray can look like a three-marker fit.

Only small regions around each sphere and glint are rendered per frame; the background is
drawn once (a few noisy variants) and copied, so a frame costs well under a millisecond or
two. Deterministic by ``seed``. Every frame carries its ground truth.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.tracking.frames import FrameSource, TrackingFrame
from humantele.tracking.sim_config import SimFrameConfig
from humantele.tracking.tool import DEFAULT_TOOL, ToolDefinition, load_tool

_SS = 4  # supersampling per pixel side


def default_sim_pose() -> Pose:
    """Probe 0.42 m in front of the camera, handle towards the camera, tilted 20 deg."""
    q_flip = quat_from_axis_angle([1.0, 0.0, 0.0], math.pi)  # probe z -> camera -z
    q_tilt = quat_from_axis_angle([0.3, 1.0, 0.0], math.radians(20.0))
    return Pose([0.02, 0.03, 0.42], quat_multiply(q_tilt, q_flip))


class SimFrameSource(FrameSource):
    """Renders frames of ``tool`` (None: the default probe) at ``pose`` (``set_pose``, then
    ``read``) or at a given pose (``render``: what the follower's sensing does with the
    simulated probe's true pose)."""

    name = "sim frames"

    def __init__(self, config: SimFrameConfig | None = None, tool: ToolDefinition | None = None):
        self.config = config or SimFrameConfig()
        self.tool = tool or load_tool(DEFAULT_TOOL)
        self.intrinsics = self.config.intrinsics
        self.pose = default_sim_pose()
        self._rng = np.random.default_rng(self.config.seed)
        c = self.config
        self.second_tool = None if c.second_tool is None else load_tool(c.second_tool)
        self._stray_rng = np.random.default_rng(c.seed + 4241)  # strays do not shift the rest
        self._stray_radius = (
            self.tool.sphere_radius if c.stray_radius_mm is None else c.stray_radius_mm / 1000.0
        )
        self._seq = 0
        self._make_background()

    # -- background, drawn once ------------------------------------------------------------
    def _make_background(self) -> None:
        c, k = self.config, self.intrinsics
        rng = np.random.default_rng(self.config.seed + 7919)
        uu, vv = np.meshgrid(np.arange(k.width), np.arange(k.height))
        self._rays = k.rays(uu, vv).astype(np.float32)  # (H, W, 3)
        n = np.array([0.15, -0.25, 1.0])
        n /= np.linalg.norm(n)
        denom = np.maximum(self._rays @ n.astype(np.float32), 0.2)
        rng_true = (c.background_depth_m * n[2] / denom).astype(np.float32)
        tex = rng.uniform(0.5, 1.5, (12, 12)).astype(np.float32)
        tex = cv2.resize(tex, (k.width, k.height), interpolation=cv2.INTER_CUBIC)
        ir = c.background_brightness * tex * (c.background_depth_m / rng_true) ** 2
        for _ in range(c.clutter_patches):  # bright bars: bed rails, cables
            p0 = rng.uniform([0, 0], [k.width, k.height])
            p1 = p0 + rng.uniform(-120, 120, 2)
            cv2.line(
                ir,
                tuple(int(x) for x in p0),
                tuple(int(x) for x in p1),
                float(rng.uniform(2000, 5000)),
                int(rng.integers(2, 5)),
            )
        ir = cv2.GaussianBlur(ir, (0, 0), max(c.psf_sigma_px, 0.3))
        self._bg_ir_true = ir.astype(np.float32)
        self._bg_range_true = rng_true
        self._bg_ir, self._bg_depth = [], []
        for _ in range(4):  # a few noisy variants, picked per frame
            i, d = self._noisy(self._bg_ir_true, rng_true, rng)
            self._bg_ir.append(i)
            self._bg_depth.append(d)

    def _noisy(
        self, ir: NDArray, rng_m: NDArray, rng: np.random.Generator
    ) -> tuple[NDArray[np.uint16], NDArray[np.uint16]]:
        """Noise, saturation, invalid pixels, wrap and quantisation of (ir, range) arrays."""
        c = self.config
        s = c.noise_scale
        sd_ir = np.sqrt(c.ir_read_noise**2 + c.ir_shot_gain * np.maximum(ir, 0))
        ir_n = ir + s * sd_ir * rng.standard_normal(ir.shape, dtype=np.float32)
        sat = ir_n >= c.saturation
        sd_d = c.depth_noise_m * (rng_m / 0.5) ** 2
        sd_d = np.where(sat, sd_d * c.saturated_depth_noise_factor, sd_d)
        r = rng_m + s * sd_d * rng.standard_normal(rng_m.shape, dtype=np.float32)
        r = np.mod(r, c.depth_wrap_m)
        depth = np.rint(r * 1000.0)
        invalid = (ir_n < 20.0) | (sat & (rng.random(ir.shape) < c.saturated_invalid_fraction))
        depth[invalid] = 0
        ir_u = np.clip(ir_n, 0, c.saturation).astype(np.uint16)
        return ir_u, depth.astype(np.uint16)

    # -- per frame -------------------------------------------------------------------------
    def set_pose(self, T_camera_probe: Pose) -> None:
        """Pose of the probe in the camera frame used by :meth:`read`."""
        self.pose = T_camera_probe

    def read(self, t: float | None = None) -> TrackingFrame:
        """A frame at the current pose; ``t`` defaults to seq / frame rate."""
        return self.render(self.pose, t)

    def open(self) -> None:
        """Nothing to open: the scene was drawn when the source was made."""

    def close(self) -> None:
        pass

    def render(self, T_camera_probe: Pose, t: float | None = None) -> TrackingFrame:
        """A frame of the tool at ``T_camera_probe`` (with the truth attached)."""
        c, k, rng = self.config, self.intrinsics, self._rng
        j = int(rng.integers(len(self._bg_ir)))
        ir = self._bg_ir[j].copy()
        depth = self._bg_depth[j].copy()
        centres = T_camera_probe.apply(self.tool.markers)
        rad = self.tool.sphere_radius
        # every object (range, kind, data), drawn far first so nearer ones cover farther ones
        objects: list[tuple[float, str, object]] = []
        for i, ctr in enumerate(centres):
            if i in c.occluded_markers:
                finger = self._finger_in_front(ctr, rad)
                if finger is not None:
                    objects.append((float(np.linalg.norm(finger[0])), "finger", finger))
            else:
                objects.append((float(np.linalg.norm(ctr)), "marker", (i, ctr, rad)))
        for ctr, r in self._strays(T_camera_probe):
            objects.append((float(np.linalg.norm(ctr)), "stray", (-1, ctr, r)))
        vis = dict.fromkeys(range(len(centres)), False)
        for _d, kind, data in sorted(objects, key=lambda o: -o[0]):
            if kind == "finger":
                self._draw_finger(ir, depth, *data, rng)
            else:
                i, ctr, r = data
                shown = self._draw_sphere(ir, depth, ctr, rng, r)
                if i >= 0:
                    vis[i] = shown
        visible = tuple(bool(vis[i]) for i in range(len(centres)))
        n_glints = int(rng.poisson(c.spurious_rate))
        centre_px = k.project(T_camera_probe.position) if T_camera_probe.position[2] > 0 else None
        for g in range(n_glints):
            near = centre_px is not None and g % 2 == 0
            self._draw_glint(ir, depth, rng, centre_px if near else None)
        seq = self._seq
        self._seq += 1
        return TrackingFrame(
            t=seq / c.frame_rate_hz if t is None else t,
            ir=ir,
            depth_mm=depth,
            intrinsics=k,
            seq=seq,
            T_camera_probe_true=T_camera_probe,
            visible_true=visible,
        )

    def _roi(self, u: float, v: float, h: int) -> tuple[int, int, int, int] | None:
        k = self.intrinsics
        x0, y0 = max(int(round(u)) - h, 0), max(int(round(v)) - h, 0)
        x1, y1 = min(int(round(u)) + h + 1, k.width), min(int(round(v)) + h + 1, k.height)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None

    def _composite(
        self,
        ir: NDArray,
        depth: NDArray,
        box: tuple[int, int, int, int],
        i_m: NDArray,
        r_m: NDArray,
        cover: NDArray,
        rng: np.random.Generator,
    ) -> None:
        """Mix a bright object (intensity i_m, range r_m, blurred coverage) over the scene."""
        x0, y0, x1, y1 = box
        bg_i = self._bg_ir_true[y0:y1, x0:x1] * (1.0 - cover)
        bg_r = self._bg_range_true[y0:y1, x0:x1]
        tot = i_m + bg_i
        if self.config.range_mixing == "phasor":  # a ToF pixel sums the returns' phasors
            k = 2.0 * np.pi / self.config.depth_wrap_m
            z = i_m * np.exp(1j * k * r_m) + bg_i * np.exp(1j * k * bg_r)
            r = np.mod(np.angle(z), 2.0 * np.pi) / k
            tot = np.abs(z)  # active brightness: the amplitude of the sum
        else:
            r = (i_m * r_m + bg_i * bg_r) / np.maximum(tot, 1e-6)
        i_n, d_n = self._noisy(tot.astype(np.float32), r.astype(np.float32), rng)
        lit = i_m > 0.05 * np.maximum(bg_i, 1.0)
        ir[y0:y1, x0:x1][lit] = i_n[lit]
        depth[y0:y1, x0:x1][lit] = d_n[lit]

    def _strays(self, T_camera_probe: Pose) -> list[tuple[NDArray, float]]:
        """Sphere centres (camera frame, m) and radii of this frame's strays and second tool."""
        c, rng = self.config, self._stray_rng
        out = []
        markers = T_camera_probe.apply(self.tool.markers)
        gap = self.tool.sphere_radius + self._stray_radius + 0.001  # solid spheres never meet
        for _ in range(c.stray_spheres):
            for _try in range(20):
                p = T_camera_probe.position + rng.uniform(-1.0, 1.0, 3) * c.stray_spread_m
                if np.linalg.norm(markers - p, axis=1).min() > gap:
                    out.append((p, self._stray_radius))
                    break
        if self.second_tool is not None:
            a = rng.uniform(0.0, 2.0 * math.pi)
            d = rng.uniform(*c.second_tool_distance_m)
            pos = T_camera_probe.position + [
                d * math.cos(a),
                d * math.sin(a),
                rng.uniform(-0.03, 0.03),
            ]
            tilt = quat_from_axis_angle(rng.normal(size=3), math.radians(rng.uniform(0.0, 40.0)))
            pose = Pose(pos, quat_multiply(tilt, default_sim_pose().quaternion))
            for m in pose.apply(self.second_tool.markers):
                out.append((m, self.second_tool.sphere_radius))
        return [(p, r) for p, r in out if p[2] > 0.1]

    def _finger_in_front(self, centre: NDArray, rad: float) -> tuple[NDArray, float] | None:
        """A fingertip (centre m, radius m) 15-25 mm in front of a hidden sphere."""
        dist = float(np.linalg.norm(centre))
        if centre[2] < 0.1:
            return None
        gap = self._stray_rng.uniform(0.015, 0.025)
        return centre * (dist - rad - gap) / dist, 0.009

    def _draw_finger(
        self,
        ir: NDArray,
        depth: NDArray,
        centre: NDArray,
        radius: float,
        rng: np.random.Generator,
        cut: tuple[float, float, float] | None = None,
    ) -> None:
        """Skin (dim in IR, a valid range) as a blurred disc of ``radius`` (m) at ``centre``;
        with ``cut`` = (u, v, r_px) a disc in pixels instead."""
        c, k = self.config, self.intrinsics
        if cut is None:
            u0, v0 = k.project(centre)
            r_px = k.fx * radius / centre[2]
        else:
            u0, v0, r_px = cut
        box = self._roi(u0, v0, int(math.ceil(r_px + 3.0 * c.psf_sigma_px + 2.0)))
        if box is None:
            return
        x0, y0, x1, y1 = box
        xx, yy = np.meshgrid(np.arange(x0, x1) - u0, np.arange(y0, y1) - v0)
        cov = np.clip(r_px + 0.5 - np.hypot(xx, yy), 0.0, 1.0).astype(np.float32)
        if c.psf_sigma_px > 0:
            cov = cv2.GaussianBlur(cov, (0, 0), c.psf_sigma_px)
        dist = float(np.linalg.norm(centre))
        i_m = (c.finger_brightness * (0.5 / dist) ** 2 * cov).astype(np.float32)
        r_m = np.full(cov.shape, dist, dtype=np.float32)
        self._composite(ir, depth, box, i_m, r_m, cov, rng)

    def _draw_sphere(
        self,
        ir: NDArray,
        depth: NDArray,
        centre: NDArray,
        rng: np.random.Generator,
        rad: float,
    ) -> bool:
        c, k = self.config, self.intrinsics
        if centre[2] < 0.05:
            return False
        dist = float(np.linalg.norm(centre))
        u0, v0 = k.project(centre)
        r_px = k.fx * rad / centre[2]
        off = math.hypot((u0 - k.cx) / k.fx, (v0 - k.cy) / k.fy)
        h = int(math.ceil(r_px * (1.0 + off * off) + 3.0 * c.psf_sigma_px + 2.0))
        box = self._roi(u0, v0, h)
        if box is None:
            return False
        x0, y0, x1, y1 = box
        us = x0 + (np.arange((x1 - x0) * _SS) + 0.5) / _SS - 0.5
        vs = y0 + (np.arange((y1 - y0) * _SS) + 0.5) / _SS - 0.5
        xs, ys = (us - k.cx) / k.fx, (vs - k.cy) / k.fy
        inv_n = 1.0 / np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
        proj = (xs[None, :] * centre[0] + ys[:, None] * centre[1] + centre[2]) * inv_n
        rho2 = dist * dist - proj * proj
        hit = rho2 <= rad * rad
        finger = None
        if rng.random() < c.partial_occlusion_prob:  # a fingertip's edge across the sphere
            a = rng.uniform(0, 2 * math.pi)
            f_px = max(2.0 * r_px, k.fx * 0.009 / centre[2])  # fingertip radius, px
            off = rng.uniform(-0.3, 0.5) * r_px + f_px  # its edge cuts the disc at -0.3..0.5 r
            fu, fv = u0 + off * math.cos(a), v0 + off * math.sin(a)
            hit &= np.hypot(us[None, :] - fu, vs[:, None] - fv) > f_px
            finger = (fu, fv, f_px)
        if not hit.any():
            return False
        t_surf = np.where(hit, proj - np.sqrt(np.maximum(rad * rad - rho2, 0.0)), 0.0)
        hh, ww = y1 - y0, x1 - x0
        cov = hit.reshape(hh, _SS, ww, _SS).mean(axis=(1, 3)).astype(np.float32)
        tsum = t_surf.reshape(hh, _SS, ww, _SS).sum(axis=(1, 3)) / (_SS * _SS)
        bright = c.marker_brightness * (0.5 / dist) ** 2
        i_m = (bright * cov).astype(np.float32)
        ir_range = (bright * tsum).astype(np.float32)
        if c.psf_sigma_px > 0:
            i_m = cv2.GaussianBlur(i_m, (0, 0), c.psf_sigma_px)
            ir_range = cv2.GaussianBlur(ir_range, (0, 0), c.psf_sigma_px)
            cov = cv2.GaussianBlur(cov, (0, 0), c.psf_sigma_px)
        r_m = ir_range / np.maximum(i_m, 1e-6)
        if finger is not None:  # under the sphere's own light: it keeps its image intact
            d_f = dist - rad - 0.015
            self._draw_finger(ir, depth, centre * d_f / dist, 0.0, rng, finger)
        self._composite(ir, depth, box, i_m, r_m, cov, rng)
        return True

    def _draw_glint(
        self, ir: NDArray, depth: NDArray, rng: np.random.Generator, near: NDArray | None
    ) -> None:
        k = self.intrinsics
        if near is not None:
            u, v = near + rng.uniform(-60, 60, 2)
        else:
            u, v = rng.uniform(0, k.width), rng.uniform(0, k.height)
        sigma = rng.uniform(0.6, 1.5)
        box = self._roi(u, v, int(math.ceil(4 * sigma)))
        if box is None:
            return
        x0, y0, x1, y1 = box
        xx, yy = np.meshgrid(np.arange(x0, x1) - u, np.arange(y0, y1) - v)
        i_m = (rng.uniform(1500, 6000) * np.exp(-(xx**2 + yy**2) / (2 * sigma**2))).astype(
            np.float32
        )
        r_bg = self._bg_range_true[y0:y1, x0:x1]
        r_m = r_bg if near is None else r_bg * 0 + rng.uniform(0.25, 0.5)
        cover = np.clip(i_m / i_m.max(), 0, 1)
        self._composite(ir, depth, box, i_m, r_m.astype(np.float32), cover, rng)
