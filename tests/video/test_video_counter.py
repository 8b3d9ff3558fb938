"""The frame counter survives VP8 at a modest bit rate; PSNR and SSIM of decoded frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from video_helpers import head_over, on_kidney, snap

from humantele.geometry import Pose
from humantele.video.counter import (
    MODULUS,
    draw_counter,
    patch_size,
    read_counter,
    unwrap,
)
from humantele.video.fidelity import psnr, ssim
from humantele.video.roundtrip import codec_round_trip
from humantele.video.sim_pov import SimPov
from humantele.video.sim_ultrasound import SimUltrasound


@pytest.mark.parametrize("value", [0, 1, 255, 256, 123456, MODULUS - 1])
def test_draw_and_read_back(value):
    img = np.full((120, 160, 3), 90, dtype=np.uint8)
    draw_counter(img, value)
    assert read_counter(img) == value
    grey = np.full((40, 64), 30, dtype=np.uint8)
    draw_counter(grey, value)
    assert read_counter(grey) == value


def test_counter_wraps_and_unwraps():
    img = np.zeros((64, 64), dtype=np.uint8)
    draw_counter(img, MODULUS + 5)
    assert read_counter(img) == 5
    assert unwrap(5, MODULUS + 3) == MODULUS + 5
    assert unwrap(MODULUS - 2, MODULUS + 1) == MODULUS - 2


def test_no_counter_or_a_damaged_one_reads_none():
    rng = np.random.default_rng(0)
    assert read_counter(np.full((64, 64, 3), 128, np.uint8)) is None
    noisy = [read_counter(rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)) for _ in range(50)]
    assert noisy.count(None) == 50
    img = np.zeros((64, 64), dtype=np.uint8)
    draw_counter(img, 777)
    img[2:6, 2:6] = 255 - img[2:6, 2:6]  # flip one bit cell's middle: the check fails
    assert read_counter(img) is None
    assert read_counter(np.zeros((10, 10), np.uint8)) is None  # too small


def test_too_small_an_image_for_the_counter_is_an_error():
    w, h = patch_size()
    with pytest.raises(ValueError):
        draw_counter(np.zeros((h - 1, w, 3), np.uint8), 1)


def test_scaled_frame_reads_with_the_scaled_cell():
    img = np.full((240, 320, 3), 60, dtype=np.uint8)
    draw_counter(img, 4242)
    half = cv2.resize(img, (160, 120), interpolation=cv2.INTER_AREA)
    assert read_counter(half, cell=4) == 4242


def vp8_round_trip(images: list, bit_rate: int) -> list[np.ndarray]:
    return codec_round_trip(images, "vp8", bit_rate)[0]


def moving_frames(src, n: int, pov: bool = False) -> list:
    """``n`` frames of the probe sliding 1 mm per frame along its array (the image moves)."""
    tip0 = on_kidney()
    frames = []
    for i in range(n):
        tip = Pose(tip0.position + tip0.rotate([0.001 * i, 0.0, 0.0]), tip0.quaternion)
        frames.append(src.render(snap(tip, head=head_over(tip0) if pov else None)))
    return frames


@pytest.fixture(scope="module")
def us_frames() -> list:
    """40 frames of the sim ultrasound (:func:`moving_frames`), rendered once for the two
    tests that read them (0.4 CPU-s a 20): the PSNR test's 20 are their first 20, the frames
    a new source renders first."""
    return moving_frames(SimUltrasound(), 40)


@pytest.mark.parametrize("kind", ["us", "pov"])
def test_every_counter_reads_back_after_vp8_at_250_kbits(kind, us_frames):
    """aiortc sends VP8 between 250 kbit/s (its floor) and 1.5 Mbit/s: at the floor, every
    frame's counter reads back exactly, in order."""
    frames = us_frames if kind == "us" else moving_frames(SimPov(), 40, pov=True)
    decoded = vp8_round_trip([f.image for f in frames], 250_000)
    assert len(decoded) == len(frames)
    assert [read_counter(img) for img in decoded] == [f.seq for f in frames]


def test_psnr_and_ssim_of_decoded_us_frames_rise_with_bit_rate(us_frames):
    frames = us_frames[:20]
    w, h = patch_size()
    region = (h, frames[0].height, 0, frames[0].width)  # leave out the counter's rows
    scores = {}
    for rate in (150_000, 1_500_000):
        decoded = vp8_round_trip([f.image for f in frames], rate)
        last = frames[-1].image, decoded[-1]
        scores[rate] = (psnr(*last, region=region), ssim(*last, region=region))
    (p_lo, s_lo), (p_hi, s_hi) = scores[150_000], scores[1_500_000]
    assert 20 < p_lo < p_hi < 60 and 0.3 < s_lo < s_hi < 1.0


def test_psnr_ssim_known_answers():
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), (5, 5), 2)
    assert psnr(img, img) == float("inf") and ssim(img, img) == pytest.approx(1.0)
    # Uniform noise of +-1 grey level in every pixel: MSE 2/3 -> PSNR 10 log10(255^2 / MSE).
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    step = rng.choice([-1, 0, 1], size=grey.shape).astype(np.int16)
    noisy_grey = np.clip(grey.astype(np.int16) + step, 0, 255).astype(np.uint8)
    mse = np.mean((noisy_grey.astype(float) - grey) ** 2)
    assert psnr(grey, noisy_grey) == pytest.approx(10 * np.log10(255**2 / mse), rel=1e-6)
    worse = np.clip(grey.astype(np.int16) + 8 * step, 0, 255).astype(np.uint8)
    assert psnr(grey, worse) < psnr(grey, noisy_grey)
    assert ssim(grey, worse) < ssim(grey, noisy_grey) < 1.0
    with pytest.raises(ValueError, match="size"):
        psnr(img, img[:-1])
