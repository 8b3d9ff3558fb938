"""Frame source configuration and factory: one config union, one function."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from humantele.tracking.frames import FrameSource
from humantele.tracking.hl2ss_source import Hl2ssFrameConfig, Hl2ssFrameSource
from humantele.tracking.opencv_source import OpenCVFrameConfig, OpenCVFrameSource
from humantele.tracking.sim import SimFrameConfig, SimFrameSource

AnyFrameConfig = SimFrameConfig | OpenCVFrameConfig | Hl2ssFrameConfig
FrameSourceConfig = Annotated[AnyFrameConfig, Field(discriminator="backend")]


def make_frame_source(config: AnyFrameConfig) -> FrameSource:
    """The frame source a configuration asks for (``backend`` = "sim", "opencv" or "hl2ss",
    the HoloLens 2 AHAT stream)."""
    if isinstance(config, SimFrameConfig):
        return SimFrameSource(config)
    if isinstance(config, Hl2ssFrameConfig):
        return Hl2ssFrameSource(config)
    return OpenCVFrameSource(config)
