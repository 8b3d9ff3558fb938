"""Video: the ultrasound image and the follower's point of view, from real or sim sources.

One interface (:class:`VideoSource`, frames as :class:`VideoFrame`), backends picked by
configuration (:func:`make_video_source`): ``sim`` ultrasound, ``sim`` POV, ``opencv``. The
sim sources read the world through :class:`SceneSnapshot`. :mod:`humantele.video.counter`
stamps frames for glass-to-glass latency; :mod:`humantele.video.fidelity` compares a decoded
frame with its source.
"""

from humantele.video.base import (
    SourceCounters,
    VideoFrame,
    VideoSource,
    VideoSourceError,
    VideoSourceUnavailable,
)
from humantele.video.opencv_source import OpenCVVideoConfig, OpenCVVideoSource
from humantele.video.sim_config import SimPovConfig, SimUltrasoundConfig
from humantele.video.sources import PovSourceConfig, UltrasoundSourceConfig, make_video_source

_SIMULATOR = {  # imported when first asked for: a follower on real devices never loads them
    "DemoScene": "humantele.video.scene",
    "SceneSnapshot": "humantele.video.scene",
    "SimPov": "humantele.video.sim_pov",
    "SimUltrasound": "humantele.video.sim_ultrasound",
}


def __getattr__(name: str) -> object:
    if name in _SIMULATOR:
        import importlib

        return getattr(importlib.import_module(_SIMULATOR[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DemoScene",
    "OpenCVVideoConfig",
    "OpenCVVideoSource",
    "PovSourceConfig",
    "SceneSnapshot",
    "SimPov",
    "SimPovConfig",
    "SimUltrasound",
    "SimUltrasoundConfig",
    "SourceCounters",
    "UltrasoundSourceConfig",
    "VideoFrame",
    "VideoSource",
    "VideoSourceError",
    "VideoSourceUnavailable",
    "make_video_source",
]
