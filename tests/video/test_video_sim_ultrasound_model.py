"""Sim ultrasound, its model kept through issue 31's speed-ups: the picture of the renderer
before them (reference frames), the labels along the beams against the point test, speckle
fixed in the tissue that decorrelates out of the plane, Rayleigh speckle, depth attenuation
and its TGC."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from video_helpers import P, correlation, grey, highpass, on_kidney, snap

from humantele.geometry import Pose
from humantele.video.fidelity import ssim
from humantele.video.phantom import Material, Organ, PhantomConfig
from humantele.video.scene import probe_on_skin
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig
from humantele.video.speckle import SpeckleField

A = float(P.semi_axes[2])
# Made by the renderer as it was before the speed-ups (commit 7656bfe), each pose's frame from
# a new SimUltrasound() (seed 0): "<pose>_anatomy" the grey image blurred by 2 mm and shrunk to
# 160 x 120 (INTER_AREA), "<pose>_crop" its full-resolution pixels in rows 200-280, columns
# 280-360, "<pose>_quality" its meta["quality"].
REFERENCE = Path(__file__).parent / "data" / "sim_us_reference.npz"
POSES = {
    "kidney": lambda: on_kidney(),
    "fanned": lambda: on_kidney(tilt_rad=math.radians(15)),
    "rib": lambda: probe_on_skin(P, (0.0, 0.0, 0.5 * A), rotate_rad=math.pi / 2),
    "aorta": lambda: probe_on_skin(P, (0.1, 0.0, -0.1 * A)),
}


def anatomy(image: np.ndarray, src: SimUltrasound) -> np.ndarray:
    g = cv2.GaussianBlur(image[..., 0], (0, 0), 0.002 / src.geometry.spacing_m)
    return cv2.resize(g, (160, 120), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("pose", sorted(POSES))
def test_the_picture_is_the_one_before_the_speed_ups(pose):
    """The anatomy (structural similarity of the 2 mm-blurred images) and the speckle itself
    (SSIM of a full-resolution patch) as the old renderer drew them, the same quality."""
    ref = np.load(REFERENCE)
    src = SimUltrasound()
    frame = src.render(snap(POSES[pose]()))
    assert frame.meta["quality"] == pytest.approx(float(ref[f"{pose}_quality"]), abs=1e-3)
    assert ssim(ref[f"{pose}_anatomy"], anatomy(frame.image, src)) > 0.98
    crop = np.ascontiguousarray(frame.image[200:280, 280:360, 0])
    assert ssim(ref[f"{pose}_crop"], crop) > 0.95
    # ... and the test can tell: another pose's picture is far from this one's.
    other = "aorta" if pose != "aorta" else "kidney"
    assert ssim(ref[f"{other}_anatomy"], anatomy(frame.image, src)) < 0.9


@pytest.mark.parametrize(
    "tip",
    [on_kidney(), on_kidney(tilt_rad=0.3, rock_rad=-0.2), POSES["rib"](), POSES["aorta"]()],
)
def test_labels_along_the_beams_are_the_point_test(tip):
    """The labels from each beam's entry into and exit from each shape (and the skin's depth
    along the beam) are those of testing every sample point, to float rounding on surfaces;
    so is the target's mask."""
    src = SimUltrasound()
    g = src.geometry
    phantom = src.phantom_for(P)
    T = P.T_world_patient.inverse() @ tip
    R, t = T.rotation_matrix, T.position
    starts = g.face.astype(np.float64) @ R.T + t
    dirs = g.direction.astype(np.float64) @ R.T
    labels, depth, kidney = phantom.along_rays(starts, dirs, g.range_m, "kidney")
    pts = starts[:, None, :] + g.range_m.astype(np.float64)[None, :, None] * dirs[:, None, :]
    points = tuple(pts[..., k].astype(np.float32).reshape(-1) for k in range(3))
    want = phantom.labels(points).reshape(labels.shape)
    assert np.mean(labels != want) < 1e-3
    assert len(np.unique(want)) >= 4  # the pose crosses several regions
    np.testing.assert_allclose(depth.reshape(-1), phantom.depth_below_skin(points), atol=1e-5)
    inside = phantom.inside("kidney", points).reshape(labels.shape)
    assert np.mean(kidney != inside) < 1e-3
    assert np.array_equal(kidney, phantom.inside_along("kidney", starts, dirs, g.range_m))


def test_speckle_decorrelates_out_of_the_plane():
    """2 mm across the image plane (along the probe's elevation) the speckle is new while the
    anatomy is the same; in the plane it moves with the tissue (the other test file)."""
    src = SimUltrasound()
    t1 = on_kidney()
    t2 = Pose(t1.position + t1.rotate([0.0, 0.002, 0.0]), t1.quaternion)
    f1, f2 = grey(src.render(snap(t1))), grey(src.render(snap(t2)))
    r0, r1, c0, c1 = 150, 350, 250, 400
    assert correlation(highpass(f1)[r0:r1, c0:c1], highpass(f2)[r0:r1, c0:c1]) < 0.3
    blur = {"ksize": (0, 0), "sigmaX": 0.003 / src.geometry.spacing_m}
    b1, b2 = cv2.GaussianBlur(f1, **blur), cv2.GaussianBlur(f2, **blur)
    assert correlation(b1[r0:r1, c0:c1], b2[r0:r1, c0:c1]) > 0.9


def test_speckle_envelope_is_rayleigh():
    """The envelope |I + jQ| of the two Gaussian fields on a plane: Rayleigh, so std / mean
    = sqrt(4 / pi - 1) = 0.523; mean 1 (scaled on another plane)."""
    field = SpeckleField(0.00035, 0.3, seed=3)
    # (the origin, the steps per column and row, 400 x 300 pixels, no lateral blur)
    plane = (np.array([0.01, 0.02, -0.03]), np.array([3e-4, 1e-4, 0.0]),
             np.array([0.0, 1e-4, 3e-4]), 400, 300, 0.0)  # fmt: skip
    env = field.contrast(*plane, 1.0)  # gamma 1: the envelope itself
    assert env.shape == (300, 400) and env.dtype == np.float32
    assert env.mean() == pytest.approx(1.0, abs=0.06)
    assert env.std() / env.mean() == pytest.approx(math.sqrt(4.0 / math.pi - 1.0), abs=0.04)
    # Contrast below 1 for gamma < 1 (a scanner's speckle reduction), mean 1 again.
    soft = field.contrast(*plane, 0.6)
    assert soft.mean() == pytest.approx(1.0, abs=0.06)
    assert soft.std() < 0.75 * env.std()


def test_depth_attenuation_and_its_tgc():
    """Plain tissue (no texture) under the probe: with the TGC off (20 dB more gain, no
    electronic noise to fill the deep picture) it darkens with depth by the round trip's loss,
    2 f alpha d; with the TGC set to the tissue's attenuation, deep and shallow look alike."""
    tissue = Material(echo=0.9, boundary=1.5, attenuation_db_cm_mhz=0.6, texture=0.0)
    far = Organ(name="kidney", center=(-0.4, -0.2, 0.45), semi_axes_m=(0.01, 0.01, 0.01))
    phantom = PhantomConfig(tissue=tissue, organs=[far], tubes=[])
    tip = on_kidney()
    means = {}
    for tgc, gain in ((0.0, 20.0), (0.6, 0.0)):
        cfg = SimUltrasoundConfig(phantom=phantom, tgc_db_cm_mhz=tgc, gain_db=gain, noise=0.0)
        src = SimUltrasound(cfg)
        img = grey(src.render(snap(tip)))
        g = src.geometry
        col = int(round(g.tip_to_pixel(0.0, 0.0)[1]))
        rows = [int(round(g.tip_to_pixel(0.0, d)[0])) for d in (0.03, 0.06)]
        means[tgc] = [img[r - 10 : r + 10, col - 20 : col + 20].mean() for r in rows]
    shallow, deep = means[0.0]
    # 3 cm more of 0.6 dB/cm/MHz at 3.5 MHz, there and back: 12.6 dB; 255 / 55 grey per dB.
    assert shallow - deep == pytest.approx(12.6 * 255 / 55, rel=0.1)
    assert shallow < 240  # not clipped
    assert abs(means[0.6][0] - means[0.6][1]) < 12


def test_a_phantom_holds_at_most_250_shapes():
    """The renderer's labels are one byte (five layers, then the shapes): a config with more
    is refused when read, not counted as a bad frame at every render."""
    from pydantic import ValidationError

    from humantele.video.sim_config import MAX_SHAPES, Tube

    tubes = [Tube(name=f"vessel {i}", point=(0.0, 0.0, 0.0)) for i in range(MAX_SHAPES)]
    with pytest.raises(ValidationError, match="at most 250 organs and tubes"):
        PhantomConfig(tubes=tubes)  # 250 tubes and the 3 default organs
    assert len(PhantomConfig(organs=[], tubes=tubes).tubes) == MAX_SHAPES
