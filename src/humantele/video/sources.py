"""Video source configurations and the factory: one union per track, one function.

The follower has two tracks: the ultrasound image (``UltrasoundSourceConfig``: ``sim`` or
``opencv``, e.g. a capture card on the US machine's video output) and the point of view
(``PovSourceConfig``: ``sim`` or ``opencv``, e.g. a webcam; the headset's PV camera will be
another backend here). Each is picked by its ``backend`` field.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from pydantic import Field

from humantele.video.base import VideoSource
from humantele.video.opencv_source import OpenCVVideoConfig, OpenCVVideoSource
from humantele.video.sim_config import SimPovConfig, SimUltrasoundConfig

if TYPE_CHECKING:
    from humantele.video.scene import Scene

UltrasoundSourceConfig = Annotated[
    SimUltrasoundConfig | OpenCVVideoConfig, Field(discriminator="backend")
]
PovSourceConfig = Annotated[SimPovConfig | OpenCVVideoConfig, Field(discriminator="backend")]
AnyVideoConfig = SimUltrasoundConfig | SimPovConfig | OpenCVVideoConfig


def make_video_source(config: AnyVideoConfig, scene: Scene | None = None) -> VideoSource:
    """The source a configuration asks for, not yet opened. ``scene`` feeds the sim backends
    (None: :class:`~humantele.video.scene.DemoScene`); the others ignore it."""
    if isinstance(config, SimUltrasoundConfig):  # the simulator only when asked for
        from humantele.video.sim_ultrasound import SimUltrasound

        return SimUltrasound(config, scene)
    if isinstance(config, SimPovConfig):
        from humantele.video.sim_pov import SimPov

        return SimPov(config, scene)
    if isinstance(config, OpenCVVideoConfig):
        return OpenCVVideoSource(config)
    raise TypeError(f"not a video source configuration: {type(config).__name__}")
