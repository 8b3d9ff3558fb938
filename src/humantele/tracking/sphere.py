"""The image of a marker sphere in a time-of-flight IR/depth camera, and its centre's range.

A sphere of radius R whose centre lies at range s along the ray of its IR centroid images as
a disc of radius ``r = f R / s`` px (an ellipse off-axis: ``r / cos(a)`` across and
``r / cos(a)^2`` along the radial direction, ``a`` the off-axis angle). The optics and the
pixel's own footprint blur it: a Gaussian of ``sigma^2 = psf^2 + 1/12`` px^2. For a pixel at
``rho`` px from the centre (in disc-normalised distance times r) this gives

- ``C(rho; r)``: the share of the pixel covered by the sphere (0..1);
- ``G(rho; r)``: the coverage-weighted mean depth of the sphere's near surface in front of
  its centre, in units of R (1 at the middle of a sharp disc, smaller off it and when blurred).

Each pixel's ToF range ``m`` is the amplitude-weighted mean of what it sees: the sphere
(brightness ``B C``, surface range ``s - R G``) and the background (brightness ``b (1 - C)``,
range ``r_bg``), which holds while the two ranges differ by much less than the wrap length.
So every pixel predicts the centre's range

    s_i = (m_i (B C_i + b_i) - b_i r_bg) / (B C_i) + R G_i + s theta_i^2 / 2,    b_i = b (1 - C_i)

(the last term turns range along the pixel's ray into range along the centroid's ray).
:func:`fit_sphere_ranges` estimates ``b`` and ``r_bg`` from the ring around the blob and ``B``
from unsaturated pixels, checks that the IR image looks like the model (a sphere half hidden
by a finger or merged with a glint does not) and takes a robust weighted mean of the ``s_i``.
Everything runs batched over all blobs of a frame. Units: m, px, IR counts.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SphereTables:
    """``C`` and ``G`` sampled on a grid of disc radii ``r`` (px) and pixel distances ``rho``
    (``cg[:, 0]`` is C, ``cg[:, 1]`` is G; shape (nr, 2, nrho))."""

    sigma_px: float
    r_grid: NDArray[np.float64]  # (nr,) uniform
    rho_step: float
    cg: NDArray[np.float64]

    def lookup(
        self, r: NDArray[np.float64], rho: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``C, G`` (N, ...) for disc radii ``r`` (N,) px (nearest in the grid) at distances
        ``rho`` (N, ...) px (linear)."""
        r0, dr = self.r_grid[0], self.r_grid[1] - self.r_grid[0]
        n, nq = len(r), self.cg.shape[2]
        jr = np.minimum(np.maximum(np.rint((r - r0) / dr), 0), len(self.r_grid) - 1)
        flat = self.cg.take(jr.astype(np.intp), axis=0).ravel()  # (N, 2, nrho): C then G
        fq = np.minimum(rho.reshape(n, -1) * (1.0 / self.rho_step), nq - 1.001)
        jq = fq.astype(np.intp)
        aq = fq - jq
        jq += (np.arange(n) * (2 * nq))[:, None]
        c0, g0 = flat.take(jq), flat.take(jq + nq)
        c = c0 + (flat.take(jq + 1) - c0) * aq
        g = g0 + (flat.take(jq + (nq + 1)) - g0) * aq
        return c.reshape(rho.shape), g.reshape(rho.shape)


CACHE_DIR_ENV = "HUMANTELE_CACHE_DIR"


def cache_dir() -> Path | None:
    """Where computed tables are kept between processes: ``$HUMANTELE_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/humantele`` (``~/.cache/humantele``); None (not kept) without a home."""
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path("~/.cache").expanduser())
    return base / "humantele" if base.is_absolute() else None


@lru_cache(maxsize=8)
def sphere_tables(psf_sigma_px: float, r_max: float = 16.0) -> SphereTables:
    """:func:`compute_sphere_tables`, kept in :func:`cache_dir` (0.65 MB a PSF): computing
    them (and importing scipy.special) took 0.4-0.6 CPU-s, half of a sensing process's start,
    paid again at each restart. The file is named by the arguments and the computing code
    (its bytecode and constants), so a changed formula is computed afresh; one that cannot be
    read or does not hold what the arguments give is computed again and replaced; a cache
    that cannot be written is only not kept (logged at debug)."""
    folder = cache_dir()
    if folder is None:
        return compute_sphere_tables(psf_sigma_px, r_max)
    code = compute_sphere_tables.__code__
    key = repr((float(psf_sigma_px), float(r_max), code.co_code, code.co_consts))
    path = folder / f"sphere-{hashlib.sha256(key.encode()).hexdigest()[:20]}.npz"
    tables = _load_tables(path, r_max)
    if tables is None:
        tables = compute_sphere_tables(psf_sigma_px, r_max)
        _save_tables(path, tables)
    return tables


def _load_tables(path: Path, r_max: float) -> SphereTables | None:
    try:
        with np.load(path, allow_pickle=False) as f:
            sigma, r_grid, rho_step, cg = (f["sigma_px"], f["r_grid"], f["rho_step"], f["cg"])
    except FileNotFoundError:
        return None
    except Exception as exc:  # truncated, not an npz, a field missing: computed again
        log.debug("sphere tables: %s unreadable (%s): computing them", path, exc)
        return None
    ok = (
        sigma.shape == () and rho_step.shape == () and r_grid.ndim == 1 and len(r_grid) > 1
        and cg.ndim == 3 and cg.shape[:2] == (len(r_grid), 2) and cg.shape[2] > 1
        and abs(r_grid[-1] - r_max) < 0.1 and np.isfinite(cg).all()
    )  # fmt: skip
    if not ok:
        log.debug("sphere tables: %s does not hold tables for r_max %s: computed", path, r_max)
        return None
    return SphereTables(float(sigma), r_grid.astype(np.float64), float(rho_step), cg)


def _save_tables(path: Path, t: SphereTables) -> None:
    """Write ``t`` to ``path`` whole or not at all (a temporary file renamed over it)."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
            tmp = f.name
            np.savez(f, sigma_px=t.sigma_px, r_grid=t.r_grid, rho_step=t.rho_step, cg=t.cg)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        log.debug("sphere tables: not kept in %s (%s)", path.parent, exc)
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


def compute_sphere_tables(psf_sigma_px: float, r_max: float = 16.0) -> SphereTables:
    """Tables of ``C`` and ``G`` for a Gaussian PSF of ``psf_sigma_px`` (plus the pixel box).

    Exact radial integrals of the blurred disc: with ``a = r sin t`` over the disc,
    ``C = int (a / s^2) exp(-(a - rho)^2 / 2 s^2) i0e(a rho / s^2) da`` and the same with the
    surface depth ``sqrt(1 - a^2 / r^2)`` inside for ``C G`` (Gauss-Legendre, 64 nodes).
    """
    from scipy.special import i0e  # here: the follower daemon imports this module, not scipy

    s = math.hypot(psf_sigma_px, math.sqrt(1.0 / 12.0))
    r_grid = np.arange(0.75, r_max + 1e-9, 0.1)  # fine enough to take the nearest
    rho_step = 0.08
    rho = np.arange(0.0, r_max + 6.0 * s + 1.0, rho_step)  # beyond: C = 0
    x, wq = np.polynomial.legendre.leggauss(64)
    t = (x + 1.0) * (math.pi / 4.0)  # t in (0, pi/2)
    wt = wq * (math.pi / 4.0)
    r = r_grid[:, None, None]
    a = r * np.sin(t)[None, None, :]
    da = r * np.cos(t)[None, None, :] * wt[None, None, :]
    q = rho[None, :, None]
    kern = (a / s**2) * np.exp(-((a - q) ** 2) / (2 * s**2)) * i0e(a * q / s**2) * da
    c = kern.sum(axis=-1)
    cg = (kern * np.cos(t)[None, None, :]).sum(axis=-1)
    g = np.where(c > 1e-9, cg / np.maximum(c, 1e-12), 1.0)
    return SphereTables(float(s), r_grid, rho_step, np.stack([np.clip(c, 0.0, 1.0), g], axis=1))


@dataclass(frozen=True)
class SphereFitParams:
    """Settings of the range fit. ``psf_sigma_px``: the camera's blur (calibrate per device);
    ``saturation``: IR counts where pixels clip; ``min_coverage``: pixels the sphere covers
    less than this do not vote; ``shape_tolerance``: largest relative IR misfit of a pixel that
    votes; ``max_ir_misfit``: RMS IR misfit of the whole blob (fraction of the sphere's
    brightness) beyond which it is refused as not a whole sphere (partly hidden, merged). A
    whole sphere fits to ~0.02 with the right PSF, ~0.05-0.07 with the PSF 0.2-0.3 px off; a
    sphere cut enough to move its centroid by 0.3 px misfits by more than ~0.07."""

    psf_sigma_px: float = 0.7
    saturation: float = 4095.0
    min_coverage: float = 0.3
    shape_tolerance: float = 0.35
    max_ir_misfit: float = 0.06
    saturated_weight: float = 0.25  # ToF range of clipped pixels is noisier (x2 sd)
    phasor: bool = True  # a pixel's sphere and background returns sum as phasors (ToF)


@dataclass(frozen=True)
class SphereFit:
    """Per blob: ``range_m`` of the centre along its centroid ray (NaN if no fit),
    ``shape_ok`` (the IR image looks like a whole sphere), ``n_pixels`` that voted,
    ``ir_misfit`` the RMS misfit of the IR image to the model, as a fraction of its brightness."""

    range_m: NDArray[np.float64]
    shape_ok: NDArray[np.bool_]
    n_pixels: NDArray[np.int64]
    ir_misfit: NDArray[np.float64]


def _masked_median(x: NDArray, mask: NDArray, default: NDArray) -> NDArray[np.float64]:
    """Median over the last two axes of ``x`` (N, H, W) where ``mask``; ``default`` where none."""
    n = x.shape[0]
    v = np.sort(np.where(mask, x, np.inf).reshape(n, -1), axis=1).ravel()
    m = v.size // max(n, 1)
    cnt = np.count_nonzero(mask.reshape(n, -1), axis=1)
    base = np.arange(n) * m
    lo = v.take(base + np.maximum(cnt - 1, 0) // 2)
    hi = v.take(base + np.minimum(cnt // 2, m - 1))
    return np.where(cnt > 0, 0.5 * (lo + hi), default)


def fit_sphere_ranges(
    ir_w: NDArray,
    range_w: NDArray,
    dx: NDArray,
    dy: NDArray,
    bearing: NDArray,
    s0: NDArray,
    radius: float,
    focal_px: float,
    threshold: float,
    params: SphereFitParams,
    wrap_m: float | None = None,
) -> SphereFit:
    """Range (m) of each blob's sphere centre along its centroid ray.

    ``ir_w`` (N, H, W) IR counts of windows around the blobs (NaN outside the image);
    ``range_w`` (N, H, W) measured ranges, m, unwrapped near ``s0`` (NaN = invalid);
    ``dx`` (N, 1, W), ``dy`` (N, H, 1) pixel offsets from the centroid; ``bearing`` (N, 2)
    the centroid's normalised image coordinates (x/z, y/z); ``s0`` (N,) a rough range (m)
    that sets the disc size; ``threshold`` IR counts of blob pixels (kept out of the ring);
    ``wrap_m`` the range ambiguity: the background is then taken to lie behind the sphere.
    """
    p = params
    n = len(s0)
    tab = sphere_tables(float(p.psf_sigma_px))
    bx, by = bearing[:, 0, None, None], bearing[:, 1, None, None]
    sec2 = (1.0 + bearing[:, 0] ** 2 + bearing[:, 1] ** 2)[:, None, None]  # 1 / cos^2(a)
    r_t = (focal_px * radius / s0)[:, None, None] * np.sqrt(sec2)  # disc radius across, px
    proj = dx * bx + dy * by  # the radial direction is stretched by 1 / cos(a): undo it
    q2 = (dx * dx + dy * dy - proj * proj / sec2) / (r_t * r_t)  # (offset / disc radius)^2
    r = r_t * np.sqrt(np.sqrt(sec2))  # the ellipse's mean radius, px
    c, g = tab.lookup(r[:, 0, 0], r * np.sqrt(q2))
    theta2 = q2 * (radius / s0[:, None, None]) ** 2  # angle of a pixel's ray off the centre's

    ring = (c < 0.003) & (ir_w < threshold)  # NaN (off the image) compares False
    n_ring = ring.sum(axis=(1, 2))
    bg = (np.where(ring, ir_w, 0.0).sum(axis=(1, 2)) / np.maximum(n_ring, 1))[:, None, None]
    bg_w = range_w
    if wrap_m:
        bg_w = range_w + wrap_m * np.ceil((s0[:, None, None] - 0.01 - range_w) / wrap_m)
    bg_r = _masked_median(bg_w, ring & (bg_w > 0), s0)[:, None, None]

    sat = ir_w >= p.saturation - 0.5
    unsat = (c > 0.3) & (ir_w < p.saturation - 0.5)
    cu = np.where(unsat, c, 0.0)
    num = (cu * (ir_w - bg * (1.0 - c))).sum(axis=(1, 2), where=unsat)
    den = (cu * cu).sum(axis=(1, 2))
    b_lower = p.saturation / np.maximum(c.max(axis=(1, 2)), 1e-3)
    bright = np.where(den > 0, num / np.where(den > 0, den, 1.0), b_lower)
    bc = np.maximum(bright, 1.0)[:, None, None] * c
    bgi = bg * (1.0 - c)
    pred_ir = bc + bgi

    # does the IR image look like a whole sphere? (not cut by a finger, not merged with a glint)
    sat_level = p.saturation - 0.5
    res = np.where(sat, np.maximum(0.98 * sat_level - pred_ir, 0.0), ir_w - pred_ir)
    lit = c >= 0.05
    n_lit = lit.sum(axis=(1, 2))
    sq = np.where(lit, res * res, 0.0).sum(axis=(1, 2)) / np.maximum(n_lit, 1)
    ir_misfit = np.sqrt(sq) / np.maximum(bright, 1.0)
    shape_ok = (n_lit > 0) & (ir_misfit <= p.max_ir_misfit)
    with np.errstate(invalid="ignore"):
        bad_px = np.abs(res) > p.shape_tolerance * pred_ir + 3.0 * np.sqrt(pred_ir + 36.0)
    fits = np.where(sat, pred_ir >= 0.6 * p.saturation, ~bad_px)

    sel = fits & (c >= p.min_coverage) & (range_w > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        if p.phasor and wrap_m:  # the sphere's phasor: the pixel's less the background's
            k = 2.0 * np.pi / wrap_m
            amp = np.where(sat, pred_ir, ir_w)  # AB is the sum's amplitude (clipped: model)
            zs = amp * np.exp(1j * k * range_w) - bgi * np.exp(1j * k * bg_r)
            r_s = np.angle(zs) / k
            r_s = r_s + wrap_m * np.round((range_w - r_s) / wrap_m)  # near the measured
        else:  # ranges mixed by brightness
            r_s = (range_w * pred_ir - bgi * bg_r) / bc
        s_i = r_s + radius * g + 0.5 * s0[:, None, None] * theta2
        w = (bc / pred_ir) ** 2 * c * c
    if p.saturated_weight != 1.0:
        w = np.where(sat, w * p.saturated_weight, w)
    # robust: drop pixels far from the median vote (a glint, a finger edge, a wrong pixel)
    med = _masked_median(s_i, sel, s0)[:, None, None]
    dev = np.where(sel, np.abs(s_i - med), np.inf)
    mad = _masked_median(dev, sel, np.zeros(n))
    keep = dev <= np.maximum(4.0 * 1.4826 * mad, 0.002)[:, None, None]
    w = np.where(keep, w, 0.0)
    wsum = w.sum(axis=(1, 2))
    n_px = keep.sum(axis=(1, 2))
    s = (w * np.where(keep, s_i, 0.0)).sum(axis=(1, 2)) / np.where(wsum > 0, wsum, 1.0)
    s = np.where((n_px >= 2) & (wsum > 0), s, np.nan)
    return SphereFit(s, shape_ok, n_px.astype(np.int64), ir_misfit)
