"""The settings of the simulated video sources (ultrasound machine and phantom, headset
camera): apart from the renderers (:mod:`humantele.video.sim_ultrasound`,
:mod:`humantele.video.sim_pov`, :mod:`humantele.video.phantom`) so that choosing a backend
never imports the simulator."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from humantele.config import ConfigModel
from humantele.video.counter import patch_size

BGR = tuple[int, int, int]
MAX_SHAPES = 250  # organs and tubes of a phantom
Placement = tuple[float, float, float]  # (along the body, depth below the skin, lateral), m


class Material(ConfigModel):
    """How a region echoes: mean amplitude, specular boundary amplitude, attenuation."""

    echo: float = Field(1.0, ge=0.0, le=20.0)
    boundary: float = Field(0.0, ge=0.0, le=1000.0)
    attenuation_db_cm_mhz: float = Field(0.6, ge=0.0, le=50.0)
    texture: float = Field(0.0, ge=0.0, le=2.0, description="std of ln(echo) over the blobs")


class Organ(Material):
    """An ellipsoid, axis-aligned in the patient frame. ``center``: (x m, y / b, z / a)."""

    name: str = Field(min_length=1)
    center: Placement
    semi_axes_m: tuple[float, float, float]

    @field_validator("semi_axes_m")
    @classmethod
    def _positive(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(0.001 <= s <= 0.5 for s in v):
            raise ValueError(f"each semi-axis must be in [0.001, 0.5] m, got {list(v)}")
        return v


class Tube(Material):
    """A straight cylinder through ``point`` (x m, y / b, z / a) along ``direction`` (patient
    frame), ``radius_m`` thick, ``half_length_m`` either side of the point."""

    name: str = Field(min_length=1)
    point: Placement
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    radius_m: float = Field(0.01, ge=0.001, le=0.1)
    half_length_m: float = Field(0.3, gt=0.0, le=2.0)

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        n = float(np.linalg.norm(v))
        if not np.isfinite(n) or n < 1e-6:
            raise ValueError(f"direction must be a non-zero vector, got {list(v)}")
        return v


def _default_organs() -> list[Organ]:
    return [
        Organ(
            name="liver",
            center=(0.02, 0.25, 0.42),
            semi_axes_m=(0.085, 0.06, 0.095),
            echo=0.95,
            boundary=2.5,
            attenuation_db_cm_mhz=0.55,
        ),
        Organ(
            name="kidney",
            center=(0.12, -0.2, 0.45),
            semi_axes_m=(0.05, 0.022, 0.028),
            echo=0.45,
            boundary=3.5,
            attenuation_db_cm_mhz=0.8,
        ),
        Organ(
            name="renal sinus",
            center=(0.12, -0.2, 0.45),
            semi_axes_m=(0.03, 0.009, 0.012),
            echo=2.6,
            boundary=0.0,
            attenuation_db_cm_mhz=0.7,
            texture=0.6,
        ),
    ]


def _default_tubes() -> list[Tube]:
    return [
        Tube(
            name="aorta",
            point=(0.1, -0.12, -0.1),
            direction=(1.0, 0.0, 0.0),
            radius_m=0.011,
            half_length_m=0.25,
            echo=0.0,
            boundary=5.0,
            attenuation_db_cm_mhz=0.18,
        ),
        Tube(
            name="spine",
            point=(0.1, -0.62, 0.0),
            direction=(1.0, 0.0, 0.0),
            radius_m=0.022,
            half_length_m=0.3,
            echo=0.0,
            boundary=100.0,
            attenuation_db_cm_mhz=25.0,
        ),
        Tube(
            name="rib",
            point=(0.0, 0.62, 0.5),
            direction=(0.35, -0.3, 1.0),
            radius_m=0.006,
            half_length_m=0.07,
            echo=0.0,
            boundary=100.0,
            attenuation_db_cm_mhz=25.0,
        ),
    ]


class PhantomConfig(ConfigModel):
    """The anatomy (see the module docstring). Layer thicknesses in m."""

    skin_m: float = Field(0.002, gt=0.0, le=0.01)
    fat_m: float = Field(0.014, ge=0.0, le=0.1)
    muscle_m: float = Field(0.01, ge=0.0, le=0.05)
    skin: Material = Material(echo=2.0, boundary=0.0, attenuation_db_cm_mhz=0.6)
    fat: Material = Material(echo=0.4, boundary=0.0, attenuation_db_cm_mhz=0.6)
    muscle: Material = Material(echo=0.6, boundary=3.0, attenuation_db_cm_mhz=0.9)
    tissue: Material = Material(echo=0.9, boundary=1.5, attenuation_db_cm_mhz=0.6, texture=0.5)
    texture_m: float = Field(0.004, ge=0.0005, le=0.05, description="grain of the blobs")
    organs: list[Organ] = Field(default_factory=_default_organs)
    tubes: list[Tube] = Field(default_factory=_default_tubes)

    @model_validator(mode="after")
    def _unique_names(self) -> PhantomConfig:
        names = [o.name for o in self.organs] + [t.name for t in self.tubes]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"organs and tubes need distinct names; repeated: {dup}")
        if len(names) > MAX_SHAPES:  # the renderer's labels are uint8, with 5 for the layers
            raise ValueError(f"at most {MAX_SHAPES} organs and tubes, got {len(names)}")
        return self

    def names(self) -> list[str]:
        return [o.name for o in self.organs] + [t.name for t in self.tubes]


class SimSourceConfig(ConfigModel):
    """What every sim source's config has: the frame rate, the size (px), the counter."""

    backend: Literal["sim"] = "sim"
    fps: float = Field(20.0, gt=0.0, le=120.0)
    width: int = Field(640, ge=96, le=4096)
    height: int = Field(480, ge=64, le=4096)
    counter: bool = Field(True, description="draw the frame counter in the top-left corner")

    @model_validator(mode="after")
    def _counter_fits(self) -> SimSourceConfig:
        w, h = patch_size()
        if self.counter and (self.width < w or self.height < h):
            raise ValueError(f"the frame counter needs at least {w}x{h} px (or counter = false)")
        return self


class SimUltrasoundConfig(SimSourceConfig):
    """The simulated ultrasound machine and probe (m, N; MHz and dB at this edge). Defaults:
    an abdominal curvilinear probe (C5-2 like: 50 mm radius, 70 deg, 16 cm, 3.5 MHz)."""

    fps: float = Field(20.0, gt=0.0, le=120.0)
    width: int = Field(640, ge=96, le=2048)
    height: int = Field(480, ge=64, le=2048)
    probe: Literal["curvilinear", "linear"] = "curvilinear"
    depth_m: float = Field(0.16, ge=0.02, le=0.3)
    fov_deg: float = Field(70.0, ge=10.0, le=120.0, description="curvilinear sector angle")
    radius_m: float = Field(0.05, ge=0.005, le=0.2, description="curvilinear face radius")
    aperture_m: float = Field(0.04, ge=0.01, le=0.1, description="linear array length")
    frequency_mhz: float = Field(3.5, ge=1.0, le=20.0)
    beams: int = Field(128, ge=16, le=1024)
    samples: int = Field(256, ge=32, le=2048)
    tgc_db_cm_mhz: float = Field(0.6, ge=0.0, le=5.0, description="attenuation TGC undoes")
    gain_db: float = Field(0.0, ge=-40.0, le=40.0)
    dynamic_range_db: float = Field(55.0, ge=20.0, le=120.0)
    noise: float = Field(0.02, ge=0.0, le=1.0, description="electronic noise, echo units")
    speckle_m: float = Field(0.00035, ge=0.00005, le=0.005, description="texel of the speckle")
    min_force_n: float = Field(1.0, ge=0.0, le=50.0)
    full_force_n: float = Field(4.0, gt=0.0, le=100.0)
    conform_m_per_n: float = Field(0.002, ge=0.0, le=0.05)
    max_conform_m: float = Field(0.015, ge=0.0, le=0.05)
    shadow_db: float = Field(20.0, gt=0.0, le=200.0)
    phantom: PhantomConfig = Field(default_factory=PhantomConfig)
    target: str = "kidney"
    seed: int = 0

    @model_validator(mode="after")
    def _check(self) -> SimUltrasoundConfig:
        if self.full_force_n <= self.min_force_n:
            raise ValueError(
                f"full_force_n ({self.full_force_n}) must be above min_force_n ({self.min_force_n})"
            )
        organs = [o.name for o in self.phantom.organs]
        if self.target not in organs:
            raise ValueError(f"target {self.target!r} is not an organ of the phantom: {organs}")
        return self


class SimPovConfig(SimSourceConfig):
    """The simulated headset camera and what it draws. Colours are BGR."""

    fps: float = Field(25.0, gt=0.0, le=120.0)
    width: int = Field(960, ge=96, le=4096)
    height: int = Field(540, ge=64, le=4096)
    hfov_deg: float = Field(64.7, ge=10.0, le=150.0, description="HoloLens 2 PV camera")
    shade_scale: float = Field(0.4, ge=0.1, le=1.0, description="resolution of the patient")
    body_half_length_m: float = Field(0.45, gt=0.05, le=2.0)
    bed_length_m: float = Field(2.0, gt=0.2, le=4.0)
    bed_width_m: float = Field(0.9, gt=0.2, le=3.0)
    skin: BGR = (150, 175, 215)
    bed: BGR = (170, 150, 120)
    floor: BGR = (95, 100, 105)
    wall: BGR = (60, 55, 50)
    real_probe: BGR = (225, 225, 230)
    virtual_probe: BGR = (255, 200, 40)
    virtual_alpha: float = Field(0.55, ge=0.0, le=1.0)
