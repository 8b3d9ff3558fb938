"""libvpx through ctypes (humantele.media.vpx): the library PyAV ships loads with its layout
checked, a running encoder changes its bit rate without a keyframe and refuses what libvpx
refuses; a library whose layout does not match is not used."""

from __future__ import annotations

import numpy as np
import pytest

from humantele.media import vpx


@pytest.fixture
def lib():
    found = vpx.load()
    if found is None:
        pytest.fail("libvpx did not load: PyAV's wheel ships it (av.libs/libvpx*)")
    return found


def grey_noise(rng, w, h):
    y = rng.integers(100, 140, (h, w), dtype=np.uint8)  # compressible within qmax
    return np.concatenate([y, np.full((h // 2, w), 128, np.uint8)])


def test_the_bit_rate_of_a_running_encoder_changes_without_a_keyframe(lib):
    rng = np.random.default_rng(3)
    enc = vpx.LiveVp8(lib, 320, 240, 1500, 1, {})
    sizes, keys = [], []
    for i in range(80):
        if i == 40:
            enc.set_bitrate(200)
        data, key = enc.encode(grey_noise(rng, 320, 240), i * 4500, 4500)
        sizes.append(len(data))
        keys.append(key)
    kbps = [np.mean(sizes[a:b]) * 8 * 20 / 1000 for a, b in ((10, 40), (55, 80))]
    assert keys == [True] + [False] * 79
    assert kbps[0] > 1000 and kbps[1] < 300
    enc.close()


def test_a_frame_larger_than_the_first_or_of_another_size_is_refused(lib):
    enc = vpx.LiveVp8(lib, 320, 240, 500, 1, {})
    assert enc.fits(160, 120) and not enc.fits(640, 480)
    with pytest.raises(ValueError, match="320x240"):
        enc.encode(np.zeros((180, 160), np.uint8), 0, 3000)
    enc.set_size(160, 120)
    assert enc.encode(np.zeros((180, 160), np.uint8), 0, 3000)[1]  # a keyframe at the new size
    with pytest.raises(RuntimeError, match="libvpx"):
        enc.set_size(640, 480)  # libvpx's own refusal (vp8e_set_config)
    enc.close()


def test_a_library_whose_config_layout_differs_is_not_used(monkeypatch):
    monkeypatch.setattr(vpx, "_LOADED", [])
    monkeypatch.setitem(vpx.DEFAULTS, "rc_buf_sz", 1234)  # as if a field had moved
    assert vpx.load() is None
