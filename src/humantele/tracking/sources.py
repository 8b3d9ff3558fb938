"""Frame source configurations and the factory: one config union, one function.

Each backend's configuration has a ``backend`` field that picks it: ``sim`` (rendered AHAT-like
frames, :mod:`humantele.tracking.sim`) or ``opencv`` (a camera OpenCV can open,
:mod:`humantele.tracking.opencv_source`).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from humantele.tracking.frames import FrameSource
from humantele.tracking.hl2ss_source import Hl2ssFrameConfig, Hl2ssFrameSource
from humantele.tracking.opencv_source import OpenCVFrameConfig, OpenCVFrameSource
from humantele.tracking.sim_config import SimFrameConfig
from humantele.tracking.tool import ToolDefinition

FrameSourceConfig = Annotated[
    SimFrameConfig | OpenCVFrameConfig | Hl2ssFrameConfig, Field(discriminator="backend")
]
"""A tracking camera's configuration, picked by its ``backend`` field: "sim", "opencv" or
"hl2ss" (the HoloLens 2 AHAT stream)."""


def make_frame_source(
    config: SimFrameConfig | OpenCVFrameConfig | Hl2ssFrameConfig,
    tool: ToolDefinition | None = None,
) -> FrameSource:
    """The frame source a configuration asks for, not yet opened. ``tool`` is the marker tree
    the sim backend draws (None: the default probe); the others ignore it."""
    if isinstance(config, SimFrameConfig):
        from humantele.tracking.sim import SimFrameSource  # only when asked: the simulator

        return SimFrameSource(config, tool)
    if isinstance(config, OpenCVFrameConfig):
        return OpenCVFrameSource(config)
    if isinstance(config, Hl2ssFrameConfig):
        return Hl2ssFrameSource(config)
    raise TypeError(f"not a frame source configuration: {type(config).__name__}")
