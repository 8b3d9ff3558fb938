"""The settings of the simulated AHAT-like camera (:mod:`humantele.tracking.sim`), apart from
its renderer so that choosing a backend never imports the simulator."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel
from humantele.tracking.camera import CameraIntrinsics


class SimFrameConfig(ConfigModel):
    """Simulated AHAT-like sensor. Counts are IR active-brightness units; distances m. The
    marker tree it draws is given to :class:`SimFrameSource` (the follower's ``tool``)."""

    moved_fields = {
        "tool": "the sim draws the follower's probe, set once in [follower] tool "
        "(SimFrameSource(config, tool) elsewhere)"
    }

    backend: Literal["sim"] = "sim"
    seed: int = 0
    intrinsics: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    frame_rate_hz: float = Field(45.0, gt=0, le=1000)
    noise_scale: float = Field(1.0, ge=0, le=20, description="multiplies every noise term")
    marker_brightness: float = Field(3000.0, gt=0, description="sphere counts at 0.5 m")
    saturation: int = Field(4095, ge=255, le=65535)
    psf_sigma_px: float = Field(0.7, ge=0, le=5)
    ir_read_noise: float = Field(6.0, ge=0)
    ir_shot_gain: float = Field(1.0, ge=0, description="shot noise variance per count")
    depth_noise_m: float = Field(0.002, ge=0, description="per-pixel range noise at 0.5 m")
    saturated_depth_noise_factor: float = Field(2.0, ge=1)
    saturated_invalid_fraction: float = Field(0.15, ge=0, le=1)
    depth_wrap_m: float = Field(1.055, gt=0.1, description="ranges wrap modulo this (AHAT)")
    range_mixing: Literal["linear", "phasor"] = Field(
        "phasor", description="a pixel seeing a marker's edge and the background: ranges "
        "mixed by brightness, or phasors summed as a time-of-flight pixel does")  # fmt: skip
    background_depth_m: float = Field(0.55, gt=0.05)
    background_brightness: float = Field(250.0, ge=0)
    clutter_patches: int = Field(2, ge=0, le=50)
    spurious_rate: float = Field(1.0, ge=0, le=50, description="mean glints per frame")
    partial_occlusion_prob: float = Field(0.0, ge=0, le=1, description="per marker, frame")
    occluded_markers: list[int] = Field(
        default_factory=list, description="hidden markers (a finger in front of each)"
    )
    finger_brightness: float = Field(
        400.0, ge=0, description="IR counts of skin at 0.5 m (fingers over markers)"
    )
    stray_spheres: int = Field(
        0, ge=0, le=20, description="sphere-shaped strays per frame near the probe"
    )
    stray_radius_mm: float | None = Field(
        None, gt=0.5, le=30, description="their radius; None: the tool's marker radius"
    )
    stray_spread_m: float = Field(
        0.07, gt=0, le=0.5, description="strays lie within this of the probe's origin, per axis"
    )
    second_tool: str | None = Field(
        None, description="another marker tool in view (a packaged tool name or a path)"
    )
    second_tool_distance_m: tuple[float, float] = Field(
        (0.07, 0.14), description="its origin's distance from the probe's, sideways, m"
    )
