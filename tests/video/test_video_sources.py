"""Configs (bad values name the field), the factory, and the sim sources' read(): pacing,
a failing scene counted, bad snapshots dark and counted."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from pydantic import TypeAdapter
from video_helpers import grey, on_kidney, snap

from humantele.config import ConfigError, validate_config
from humantele.geometry import Pose
from humantele.video import (
    DemoScene,
    OpenCVVideoConfig,
    OpenCVVideoSource,
    PovSourceConfig,
    SimPov,
    SimPovConfig,
    SimUltrasound,
    SimUltrasoundConfig,
    UltrasoundSourceConfig,
    VideoSource,
    VideoSourceError,
    make_video_source,
)
from humantele.video.counter import read_counter
from humantele.video.scene import DEFAULT_PATIENT, SceneSnapshot


@pytest.mark.parametrize(
    ("model", "data", "field"),
    [
        (SimUltrasoundConfig, {"depth_m": -0.1}, "depth_m"),
        (SimUltrasoundConfig, {"fps": 0}, "fps"),
        (SimUltrasoundConfig, {"probe": "phased"}, "probe"),
        (SimUltrasoundConfig, {"width": 10}, "width"),
        (SimUltrasoundConfig, {"target": "spleen"}, "spleen"),
        (SimUltrasoundConfig, {"min_force_n": 5.0, "full_force_n": 4.0}, "full_force_n"),
        (SimUltrasoundConfig, {"phantom": {"organs": [{"name": "x"}]}}, "phantom.organs.0"),
        (
            SimUltrasoundConfig,
            {"phantom": {"tubes": [{"name": "t", "point": [0, 0, 0], "direction": [0, 0, 0]}]}},
            "direction",
        ),
        (SimUltrasoundConfig, {"colour": 1}, "colour"),
        (SimPovConfig, {"hfov_deg": 200}, "hfov_deg"),
        (SimPovConfig, {"skin": [1, 2]}, "skin"),
        (OpenCVVideoConfig, {"device": ""}, "device"),
        (OpenCVVideoConfig, {"pixel_spacing_mm": [0.3, -1]}, "pixel_spacing_mm"),
        (OpenCVVideoConfig, {"stall_reads": 0}, "stall_reads"),
    ],
)
def test_bad_config_names_the_field(model, data, field):
    with pytest.raises(ConfigError) as err:
        validate_config(model, data, "video.toml")
    assert field in str(err.value) and "video.toml" in str(err.value)


def test_repeated_phantom_names_are_refused():
    organ = {"name": "liver", "center": [0, 0, 0], "semi_axes_m": [0.05, 0.05, 0.05]}
    with pytest.raises(ConfigError, match="repeated"):
        validate_config(SimUltrasoundConfig, {"phantom": {"organs": [organ, organ]}})


def test_unions_pick_the_backend():
    us = TypeAdapter(UltrasoundSourceConfig)
    pov = TypeAdapter(PovSourceConfig)
    assert isinstance(us.validate_python({"backend": "sim"}), SimUltrasoundConfig)
    assert isinstance(us.validate_python({"backend": "opencv", "device": "1"}), OpenCVVideoConfig)
    assert isinstance(pov.validate_python({"backend": "sim"}), SimPovConfig)
    with pytest.raises(ValueError, match="backend"):
        us.validate_python({"backend": "hololens"})


def test_factory_makes_each_backend():
    assert isinstance(make_video_source(SimUltrasoundConfig()), SimUltrasound)
    assert isinstance(make_video_source(SimPovConfig()), SimPov)
    assert isinstance(make_video_source(OpenCVVideoConfig()), OpenCVVideoSource)
    for src in (SimUltrasound(), SimPov()):
        assert isinstance(src, VideoSource)
    with pytest.raises(TypeError):
        make_video_source(object())  # type: ignore[arg-type]


def test_sim_read_paces_like_a_camera_and_stamps_the_counter():
    """At 50 fps the k-th frame comes no sooner than k ticks of 20 ms after the first (a late
    reader gets its frame at once, without a burst), with seq 1, 2, ... drawn in the frame."""
    src = make_video_source(SimUltrasoundConfig(fps=50.0, width=160, height=120))
    with src:
        frames = [src.read() for _ in range(4)]
    assert [f.seq for f in frames] == [1, 2, 3, 4]
    assert [read_counter(f.image) for f in frames] == [1, 2, 3, 4]
    t = np.array([f.t_capture for f in frames])
    assert np.all(np.diff(t) >= 0.0)
    assert np.all(t[1:] - t[0] >= 0.02 * np.arange(1, 4) - 1e-4)
    assert src.counters.frames == 4 and src.counters.invalid == 0


def test_sim_read_before_open_is_an_error():
    with pytest.raises(VideoSourceError, match="before open"):
        SimPov().read()


def test_a_failing_scene_gives_dark_frames_counted():
    calls = {"n": 0}

    def scene():
        calls["n"] += 1
        raise RuntimeError("world crashed")

    src = SimUltrasound(SimUltrasoundConfig(fps=120.0), scene=scene)
    with src:
        frames = [src.read() for _ in range(3)]
    assert calls["n"] == 3 and src.counters.invalid == 3
    assert all(not f.meta["valid"] and f.meta["quality"] == 0.0 for f in frames)
    assert all(grey(f)[src.geometry.fov_mask].max() < 40 for f in frames)


def test_demo_scene_drives_both_sources_from_one_clock():
    t = {"now": 0.0}
    scene = DemoScene(clock=lambda: t["now"])
    us = SimUltrasound(scene=scene)
    pov = SimPov(scene=scene)
    with us, pov:
        a, pa = us.read(), pov.read()
        t["now"] = 2.0  # a quarter period: the probe has moved 3 cm across the body
        b, pb = us.read(), pov.read()
    assert a.meta["quality"] > 0.5 and b.meta["quality"] != a.meta["quality"]
    assert np.mean(np.abs(grey(a) - grey(b))) > 5
    assert np.mean(np.abs(pa.image.astype(int) - pb.image.astype(int))) > 0.5


def test_sources_run_in_a_reader_thread():
    """read() blocks; a daemon runs it in a thread and keeps the latest frame."""
    src = SimUltrasound(SimUltrasoundConfig(fps=100.0, width=160, height=120))
    latest = []
    done = threading.Event()

    def reader():
        with src:
            while len(latest) < 5:
                latest.append(src.read())
        done.set()

    threading.Thread(target=reader, daemon=True).start()
    assert done.wait(30.0)
    assert [f.seq for f in latest] == [1, 2, 3, 4, 5]


def test_non_finite_force_or_time_is_counted_and_dark():
    src = SimUltrasound()
    tip = on_kidney()
    for bad in (snap(tip, force=math.nan), snap(tip, force=math.inf)):
        frame = src.render(bad)
        assert not frame.meta["valid"]
    frame = src.render(SceneSnapshot(math.nan, DEFAULT_PATIENT, tip, 5.0, None))
    assert not frame.meta["valid"] and src.counters.invalid == 3
    # A corrupted pose (built around Pose's own check) is counted too.
    broken = object.__new__(Pose)
    object.__setattr__(broken, "position", np.array([np.nan, 0.0, 0.0]))
    object.__setattr__(broken, "quaternion", np.array([0.0, 0.0, 0.0, 1.0]))
    frame = src.render(snap(broken))
    assert not frame.meta["valid"] and src.counters.invalid == 4
    assert grey(frame)[src.geometry.fov_mask].max() < 40
