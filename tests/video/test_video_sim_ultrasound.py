"""Sim ultrasound known answers: the target where the geometry puts it, its image quality,
no contact is dark, the rib's shadow, speckle fixed in the tissue, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from video_helpers import (
    KIDNEY,
    SAGITTAL,
    P,
    correlation,
    grey,
    highpass,
    on_kidney,
    snap,
    window_mean,
)

from humantele.geometry import Pose
from humantele.video.phantom import Material, PhantomConfig, Tube
from humantele.video.scene import SceneSnapshot, probe_on_skin
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

# The kidney's semi-axes (m) along patient x, y, z; its largest section is the x-z plane.
KX, KY, KZ = 0.05, 0.022, 0.028


@pytest.fixture(scope="module")
def us() -> SimUltrasound:
    src = SimUltrasound()
    src.open()
    return src


def pixel_of(src: SimUltrasound, tip: Pose, point_patient) -> tuple[float, float]:
    """(row, col) where a patient-frame point in the image plane appears, by hand."""
    p_tip = (P.T_world_patient.inverse() @ tip).inverse().apply(np.asarray(point_patient))
    assert abs(p_tip[1]) < 1e-6  # in the image plane
    return src.geometry.tip_to_pixel(p_tip[0], p_tip[2])


def test_quality_on_target_is_the_section_ratio(us):
    """Sagittal through the kidney's centre: the section is the x-y ellipse (KX, KY), the
    largest is the x-z one (KX, KZ): Q = KY / KZ = 0.786, to the grid's accuracy."""
    q = us.render(snap(on_kidney())).meta["quality"]
    assert q == pytest.approx(KY / KZ, abs=0.02)
    # Transverse through the centre: the y-z ellipse, Q = KX KY ... = (KY KZ) / (KX KZ).
    tr = probe_on_skin(P, (KIDNEY[0], 0.0, KIDNEY[2]))
    assert us.render(snap(tr)).meta["quality"] == pytest.approx(KY / KX, abs=0.02)


def test_target_is_in_the_image_where_the_geometry_puts_it(us):
    """The bright renal sinus at the kidney centre's pixel, the darker cortex either side of
    it along the kidney (inside the kidney, outside the sinus)."""
    tip = on_kidney()
    img = grey(us.render(snap(tip)))
    row, col = pixel_of(us, tip, KIDNEY)
    half = int(round(0.002 / us.geometry.spacing_m))
    sinus = window_mean(img, row, col, half)
    for dx in (-0.04, 0.04):  # along the body: cortex (sinus semi-axis 0.03, kidney 0.05)
        r, c = pixel_of(us, tip, (KIDNEY[0] + dx, KIDNEY[1], KIDNEY[2]))
        assert sinus > window_mean(img, r, c, half) + 40


def test_target_appears_only_with_the_kidney_in_the_phantom():
    """The image with and without the kidney (its materials made plain tissue) differ where the
    kidney is: the centroid of the difference is the kidney centre's pixel (within 5 mm)."""
    phantom = PhantomConfig()
    plain = phantom.model_copy(deep=True)
    for organ in plain.organs:
        if organ.name in ("kidney", "renal sinus"):
            organ.echo, organ.boundary = phantom.tissue.echo, phantom.tissue.boundary
            organ.attenuation_db_cm_mhz = phantom.tissue.attenuation_db_cm_mhz
            organ.texture = phantom.tissue.texture
    tip = on_kidney()
    with_k = SimUltrasound(SimUltrasoundConfig(phantom=phantom))
    without = SimUltrasound(SimUltrasoundConfig(phantom=plain))
    diff = np.abs(grey(with_k.render(snap(tip))) - grey(without.render(snap(tip))))
    rows, cols = np.nonzero(diff > 25)
    row, col = pixel_of(with_k, tip, KIDNEY)
    mm = with_k.geometry.spacing_m * 1e3
    assert abs(rows.mean() - row) * mm < 5 and abs(cols.mean() - col) * mm < 5
    # ... and the quality does not depend on how the target looks, only where it is.
    q = without.render(snap(tip)).meta["quality"]
    assert q == pytest.approx(with_k.render(snap(tip)).meta["quality"])


def test_off_target_quality_zero_and_image_differs(us):
    on = us.render(snap(on_kidney()))
    off_tip = probe_on_skin(P, (KIDNEY[0], 0.0, -KIDNEY[2]), rotate_rad=SAGITTAL)
    off = us.render(snap(off_tip))
    assert on.meta["quality"] > 0.7
    assert off.meta["quality"] == 0.0
    mask = us.geometry.fov_mask
    assert np.mean(np.abs(grey(on) - grey(off))[mask]) > 10


def test_tilt_changes_image_and_quality(us):
    """Fanning 15 deg about the array moves the plane off the kidney's centre: a smaller
    section (quality drops) and another image; rocking in-plane keeps the section."""
    flat = us.render(snap(on_kidney()))
    fanned = us.render(snap(on_kidney(tilt_rad=math.radians(15))))
    rocked = us.render(snap(on_kidney(rock_rad=math.radians(10))))
    mask = us.geometry.fov_mask
    assert np.mean(np.abs(grey(flat) - grey(fanned))[mask]) > 10
    assert np.mean(np.abs(grey(flat) - grey(rocked))[mask]) > 10
    assert fanned.meta["quality"] < flat.meta["quality"] - 0.1
    # Rocked about the face (8 mm from the skin): the plane still holds the kidney's centre
    # line closely, so its section is nearly the same.
    assert rocked.meta["quality"] == pytest.approx(flat.meta["quality"], abs=0.05)


@pytest.mark.parametrize("force", [0.0, 0.5, -3.0])
def test_no_contact_is_dark(us, force):
    frame = us.render(snap(on_kidney(), force=force))
    img = grey(frame)[us.geometry.fov_mask]
    assert frame.meta["quality"] == 0.0 and frame.meta["coupling"] == 0.0
    assert img.mean() < 3.0 and img.max() < 40  # faint noise only


def test_probe_off_the_skin_is_dark_whatever_the_force(us):
    """5 N along the beam but the face 3 cm above the skin (not a contact force)."""
    tip = on_kidney(press_m=-0.03)
    frame = us.render(snap(tip, force=5.0))
    assert frame.meta["coupling"] == 0.0
    assert grey(frame)[us.geometry.fov_mask].mean() < 3.0


def test_partial_coupling_scales_quality_and_brightness(us):
    """Between min_force_n (1 N) and full_force_n (4 N) the coupling is linear: at 2.5 N the
    quality is half of the full one, and the image darker than at 5 N."""
    full = us.render(snap(on_kidney(), force=5.0))
    half = us.render(snap(on_kidney(), force=2.5))
    assert half.meta["quality"] == pytest.approx(0.5 * full.meta["quality"], rel=1e-3)
    mask = us.geometry.fov_mask
    assert grey(half)[mask].mean() < grey(full)[mask].mean() - 5


def test_rib_shadow_is_darker_beneath_than_beside(us):
    """Over the rib (default phantom: at the costal margin, x = 0, z = 0.5 a): a bright
    surface, and beneath it a shadow far darker than the tissue beside it at the same depth."""
    cfg = us.config.phantom
    rib = next(t for t in cfg.tubes if t.name == "rib")
    a, b = float(P.semi_axes[2]), float(P.semi_axes[1])
    centre = np.array([rib.point[0], rib.point[1] * b, rib.point[2] * a])
    tip = probe_on_skin(P, (centre[0], 0.0, centre[2]), rotate_rad=SAGITTAL)
    frame = us.render(snap(tip))
    img = grey(frame)
    # Where the rib crosses the image plane: the tube's axis meets the plane y_tip = 0.
    T_tip_patient = (P.T_world_patient.inverse() @ tip).inverse()
    c_tip = T_tip_patient.apply(centre)
    d = np.asarray(rib.direction, dtype=float)
    d_tip = T_tip_patient.rotate(d / np.linalg.norm(d))
    hit = c_tip - d_tip * (c_tip[1] / d_tip[1])
    row, col = us.geometry.tip_to_pixel(hit[0], hit[2])
    px = 1.0 / (us.geometry.spacing_m * 1e3)  # pixels per mm
    surface = img[int(row - 8 * px) : int(row), int(col - 2 * px) : int(col + 2 * px)]
    assert surface.max() > 200  # the bright bone surface
    rows = slice(int(row + 20 * px), int(row + 60 * px))
    beneath = img[rows, int(col - 2 * px) : int(col + 2 * px)].mean()
    beside = img[rows, int(col + 25 * px) : int(col + 30 * px)].mean()
    assert beside > 40 and beneath < 0.2 * beside


def test_speckle_moves_with_the_tissue(us):
    """Moving the probe 2 mm along its array shifts the speckle by 2 mm in the image: the
    high-passed images match at that shift (not at zero shift)."""
    t1 = on_kidney()
    t2 = Pose(t1.position + t1.rotate([0.002, 0.0, 0.0]), t1.quaternion)
    g1, g2 = highpass(grey(us.render(snap(t1)))), highpass(grey(us.render(snap(t2))))
    k = int(round(0.002 / us.geometry.spacing_m))
    r0, r1, c0, c1 = 150, 350, 250, 400
    matched = correlation(g1[r0:r1, c0 + k : c1 + k], g2[r0:r1, c0:c1])
    unshifted = correlation(g1[r0:r1, c0:c1], g2[r0:r1, c0:c1])
    assert matched > 0.9 and unshifted < 0.5


def test_same_seed_same_frames_other_seed_other_speckle():
    tip = on_kidney()
    a, b = SimUltrasound(), SimUltrasound()
    c = SimUltrasound(SimUltrasoundConfig(seed=1))
    fa, fb, fc = (s.render(snap(tip)) for s in (a, b, c))
    assert np.array_equal(fa.image, fb.image)
    assert fa.meta["quality"] == fc.meta["quality"]
    assert np.mean(np.abs(grey(fa) - grey(fc))[a.geometry.fov_mask]) > 5


def test_a_little_noise_changes_from_frame_to_frame(us):
    frames = [grey(us.render(snap(on_kidney()))) for _ in range(8)]
    for f1, f2 in zip(frames, frames[1:], strict=False):  # every frame, not only most
        d = np.abs(f1 - f2)[us.geometry.fov_mask]
        assert 0.0 < d.mean() < 3.0  # noise, not new speckle


@pytest.mark.parametrize("probe", ["curvilinear", "linear"])
def test_pixel_spacing_follows_depth_and_size(probe):
    """The field of view's depth along the central column is depth_m / spacing pixels, and
    the reported spacing is that pixel size in mm."""
    cfg = SimUltrasoundConfig(probe=probe, depth_m=0.08, width=400, height=400)
    src = SimUltrasound(cfg)
    frame = src.render(snap(on_kidney()))
    g = src.geometry
    assert frame.pixel_spacing_mm == pytest.approx((g.spacing_m * 1e3,) * 2)
    col = int(round(g.tip_to_pixel(0.0, 0.0)[1]))
    rows = np.flatnonzero(g.fov_mask[:, col])
    assert (rows[-1] - rows[0] + 1) * g.spacing_m == pytest.approx(0.08, abs=2 * g.spacing_m)
    if probe == "linear":
        cols = np.flatnonzero(g.fov_mask[rows[len(rows) // 2]])
        assert (cols[-1] - cols[0] + 1) * g.spacing_m == pytest.approx(0.04, abs=2 * g.spacing_m)
    assert frame.image.shape == (400, 400, 3)


def test_no_patient_or_no_probe_is_dark_not_invalid(us):
    before = us.counters.invalid
    for s in (snap(None), SceneSnapshot(0.0, None, on_kidney(), 5.0, None)):
        frame = us.render(s)
        assert frame.meta["valid"] and frame.meta["quality"] == 0.0
        assert grey(frame)[us.geometry.fov_mask].mean() < 3.0
    assert us.counters.invalid == before


def test_other_target_organ():
    """The quality follows the configured target: the liver from over it."""
    src = SimUltrasound(SimUltrasoundConfig(target="liver"))
    tip = probe_on_skin(P, (0.02, 0.0, 0.42 * float(P.semi_axes[2])))
    assert src.render(snap(tip)).meta["quality"] > 0.3
    assert src.render(snap(on_kidney(), force=0.0)).meta["quality"] == 0.0


def test_material_attenuation_brightens_below_fluid():
    """Posterior enhancement: below the aorta (0.18 dB/cm/MHz) the tissue is brighter than
    beside it at the same depth, because the TGC expects 0.6."""
    cfg = SimUltrasoundConfig(phantom=PhantomConfig(tissue=Material(echo=0.9, texture=0.0)))
    src = SimUltrasound(cfg)
    tube = next(t for t in cfg.phantom.tubes if t.name == "aorta")
    a, b = float(P.semi_axes[2]), float(P.semi_axes[1])
    centre = (0.1, tube.point[1] * b, tube.point[2] * a)
    tip = probe_on_skin(P, (centre[0], 0.0, centre[2]))
    img = grey(src.render(snap(tip)))
    row, col = pixel_of(src, tip, centre)
    px = 1.0 / (src.geometry.spacing_m * 1e3)
    rows = slice(int(row + 15 * px), int(row + 30 * px))
    below = img[rows, int(col - 4 * px) : int(col + 4 * px)].mean()
    beside = img[rows, int(col + 20 * px) : int(col + 28 * px)].mean()
    assert below > beside + 8


def test_shadowed_part_of_the_target_does_not_count():
    """A bone across the body above the kidney shadows a band of it: the quality drops by
    about that band's share of the section: a 12 mm bone 3 cm deep, its shadow fanning out to
    about 23 mm at the kidney (the sector's apex is 5 cm behind the face), of a 100 mm section."""
    base = PhantomConfig()
    bone = Tube(
        name="bone",
        point=(KIDNEY[0], 0.3, 0.45),
        direction=(0.0, 0.0, 1.0),
        radius_m=0.006,
        half_length_m=0.1,
        echo=0.0,
        boundary=100.0,
        attenuation_db_cm_mhz=25.0,
    )
    shadowed = base.model_copy(update={"tubes": [*base.tubes, bone]})
    q = SimUltrasound(SimUltrasoundConfig(phantom=base)).render(snap(on_kidney()))
    qs = SimUltrasound(SimUltrasoundConfig(phantom=shadowed)).render(snap(on_kidney()))
    drop = q.meta["quality"] - qs.meta["quality"]
    assert 0.15 < drop / q.meta["quality"] < 0.3
