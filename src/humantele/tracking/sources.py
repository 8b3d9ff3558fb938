"""Frame source configuration and factory: one config union, one function."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from humantele.tracking.frames import FrameSource
from humantele.tracking.opencv_source import OpenCVFrameConfig, OpenCVFrameSource
from humantele.tracking.sim import SimFrameConfig, SimFrameSource

FrameSourceConfig = Annotated[SimFrameConfig | OpenCVFrameConfig, Field(discriminator="backend")]


def make_frame_source(config: SimFrameConfig | OpenCVFrameConfig) -> FrameSource:
    """The frame source a configuration asks for (``backend`` = "sim" or "opencv")."""
    if isinstance(config, SimFrameConfig):
        return SimFrameSource(config)
    return OpenCVFrameSource(config)
