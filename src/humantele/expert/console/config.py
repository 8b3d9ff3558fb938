"""The console's configuration (``[expert.console]``; docs/console.md, "Configuration")."""

from __future__ import annotations

import math

from pydantic import Field, field_validator

from humantele.config import ConfigModel, DirectoryField, Port
from humantele.web.loopback import is_loopback

# How a page may get the received video (docs/console.md, "The video path"): the first is
# the default. Sim video (no encoded frames) is always JPEG.
TRANSPORTS = ("webcodecs", "jpeg")


class ConsoleConfig(ConfigModel):
    """The console page (``[expert.console]``): where it is served and what it keeps."""

    enabled: bool = True
    host: str = Field("127.0.0.1", description="loopback only (an SSH tunnel for elsewhere)")
    port: Port = Field(8767, description="0 picks a free one")
    video: str = Field(
        "auto",
        pattern=r"^(auto|received|sim|none)$",
        description="'received': the follower's tracks; 'sim': sim sources here (a stand-in); "
        "'auto': received when the daemon has a receiver, else sim; 'none'",
    )
    us_pixel_spacing_mm: tuple[float, float] | None = Field(
        None,
        description="(row, col) mm per pixel of the received ultrasound frames; None: no "
        "calipers (a sim or local source gives its own)",
    )
    us_depth_origin_row: float | None = Field(
        None,
        ge=-10000.0,
        le=10000.0,
        description="row (px) of depth 0 (the skin under the probe's face) in the received "
        "ultrasound frames: with the pixel spacing, the depth scale's cm labels; None: none",
    )
    transport: str = Field(
        "webcodecs",
        pattern=r"^(webcodecs|jpeg)$",
        description="how the page gets received video: 'webcodecs' (the encoded frames, "
        "decoded by the page), 'jpeg' (a JPEG per frame, latest wins); sim video is always "
        "JPEG (docs/console.md: why WebCodecs, and why not WebRTC)",
    )
    jpeg_quality: int = Field(88, ge=30, le=100, description="JPEG frames and captures")
    state_rate_hz: float = Field(20.0, gt=0, le=100)
    stale_after_s: float = Field(1.0, gt=0, le=60, description="older video or pose: stale")
    cine_seconds: float = Field(10.0, gt=0, le=60)
    captures_dir: DirectoryField = Field(
        "~/.local/state/humantele/captures", description="captured frames and their poses"
    )
    max_clients: int = Field(1, ge=1, le=8, description="consoles at once; more are refused")
    page_rate_hz: float = Field(80.0, gt=0, le=1000, description="page messages a second")
    header_timeout_s: float = Field(
        10.0, gt=0, le=120, description="accept to a request's complete headers (then closed)"
    )
    max_connections: int = Field(
        64, ge=8, le=4096, description="open at once, besides the console's own page"
    )
    max_connections_per_address: int = Field(64, ge=2, le=4096)
    captures_per_minute: float = Field(
        30.0, gt=0, le=600, description="captures a minute on average (bursts of 10); more: refused"
    )
    captures_max_mb: float = Field(
        1000.0, gt=0, le=1e6, description="disk budget of captures_dir (MB); beyond: refused"
    )
    clip_seconds: float = Field(
        5.0, ge=0, le=60, description="Capture also keeps the cine's last seconds as an MP4 "
        "beside the still (0: stills only); in the same rate cap and disk budget",
    )  # fmt: skip

    @field_validator("us_pixel_spacing_mm")
    @classmethod
    def _spacing(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(math.isfinite(x) and 0.001 <= x <= 10.0 for x in v):
            raise ValueError(f"pixel spacing {v} mm: each must be within 0.001-10 mm")
        return v

    @field_validator("host")
    @classmethod
    def _loopback(cls, v: str) -> str:
        if not is_loopback(v):
            raise ValueError(
                f"the console is served on loopback only, not {v!r} (it drives the session; "
                "reach it from another machine through an SSH tunnel)"
            )
        return v
