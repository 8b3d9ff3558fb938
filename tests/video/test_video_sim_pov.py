"""Sim POV: the probes and the patient are drawn where they project."""

from __future__ import annotations

import numpy as np
import pytest
from video_helpers import P, head_over, on_kidney, snap

from humantele.geometry import Pose
from humantele.video.scene import SceneSnapshot, look_at
from humantele.video.sim_pov import SimPov, SimPovConfig


@pytest.fixture(scope="module")
def pov() -> SimPov:
    return SimPov(SimPovConfig(counter=False))


def handle_point(tip: Pose) -> np.ndarray:
    """A point on the transducer's handle (tip frame 8 cm up the handle), world."""
    return tip.apply((0.0, 0.0, -0.08))


def test_real_probe_drawn_where_it_projects(pov):
    tip = on_kidney()
    head = head_over(tip)
    with_probe = pov.render(snap(tip, head=head)).image
    without = pov.render(snap(None, head=head)).image
    u, v = pov.project(head, handle_point(tip))
    assert 0 <= u < pov.config.width and 0 <= v < pov.config.height
    px, bg = with_probe[int(v), int(u)].astype(int), without[int(v), int(u)].astype(int)
    assert np.abs(px - bg).sum() > 60
    # The real probe's colour, shaded: channels in its proportions, not the skin's.
    ref = np.array(pov.config.real_probe, dtype=float)
    k = px / ref
    assert 0.4 < k.min() and k.max() - k.min() < 0.1
    # Far from the probe the two images agree.
    assert np.array_equal(with_probe[:40, -40:], without[:40, -40:])


def test_virtual_probe_is_translucent_and_another_colour(pov):
    tip = on_kidney()
    virtual = Pose(tip.position + np.array([0.0, 0.0, 0.08]), tip.quaternion)
    head = head_over(tip)
    base = pov.render(snap(None, head=head)).image
    img = pov.render(snap(None, head=head, virtual=virtual)).image
    u, v = pov.project(head, handle_point(virtual))
    px, bg = img[int(v), int(u)].astype(float), base[int(v), int(u)].astype(float)
    a = pov.config.virtual_alpha
    col = np.array(pov.config.virtual_probe, dtype=float)
    # A blend of the background and the (shaded) hologram colour: neither of them alone.
    assert np.abs(px - bg).sum() > 40
    shaded = (px - (1 - a) * bg) / a  # the hologram's own colour at that pixel
    k = shaded / col
    assert 0.35 < k.min() and k.max() - k.min() < 0.15


def test_patient_drawn_where_it_projects(pov):
    tip = on_kidney()
    head = head_over(tip)
    c, b, _ = (float(v) for v in P.semi_axes)
    x = 0.25  # a point on the skin along the body's top line
    top = P.T_world_patient.apply((x, b * np.sqrt(1 - (x / c) ** 2) - 0.001, 0.0))
    img = pov.render(snap(None, head=head)).image
    u, v = pov.project(head, top)
    px = img[int(v), int(u)].astype(float)
    skin = np.array(pov.config.skin, dtype=float)
    k = px / skin
    assert 0.3 < k.min() and k.max() - k.min() < 0.08
    # With no patient in the scene the same pixel is not skin.
    empty = pov.render(SceneSnapshot(0.0, None, None, 0.0, head)).image
    assert np.abs(empty[int(v), int(u)].astype(float) - px).sum() > 30


def test_view_changes_with_the_head(pov):
    tip = on_kidney()
    a = pov.render(snap(tip, head=head_over(tip))).image
    eye = P.T_world_patient.apply((0.3, 0.5, -0.3))
    b = pov.render(snap(tip, head=look_at(eye, tip.position))).image
    assert np.mean(np.abs(a.astype(int) - b.astype(int))) > 10


def test_looking_away_shows_no_patient(pov):
    tip = on_kidney()
    eye = tip.position + np.array([0.0, 0.5, 0.0])
    head = look_at(eye, eye + np.array([0.0, 1.0, 0.01]))  # at the ceiling
    img = pov.render(snap(tip, head=head)).image
    assert np.all(img == np.array(pov.config.wall, dtype=np.uint8))


def test_no_head_pose_gives_the_blank_frame_uncounted(pov):
    before = pov.counters.invalid
    frame = pov.render(snap(on_kidney(), head=None))
    assert np.all(frame.image == np.array(pov.config.wall, dtype=np.uint8))
    assert pov.counters.invalid == before and frame.meta["valid"]


@pytest.mark.parametrize("size", [(320, 180), (1280, 720)])
def test_size_and_field_of_view_from_config(size):
    w, h = size
    src = SimPov(SimPovConfig(width=w, height=h, hfov_deg=90.0))
    tip = on_kidney()
    frame = src.render(snap(tip, head=head_over(tip)))
    assert frame.image.shape == (h, w, 3) and frame.image.dtype == np.uint8
    assert src.fx == pytest.approx(w / 2.0)  # tan(45 deg) = 1
    assert frame.pixel_spacing_mm is None
