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
from humantele.video.scene import DemoScene, SceneSnapshot
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig
from humantele.video.sources import PovSourceConfig, UltrasoundSourceConfig, make_video_source

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
