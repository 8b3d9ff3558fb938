"""The clinic the follower works in, behind one interface: real devices, or the simulated
clinic that provides all of them from one simulated world.

The daemon sees devices only. It gets tracker frames (each with the camera's pose in the
tracker's world, from the device), force readings, video frames and the headset's pose from
device objects, and never reads the simulated world's truth. What it gives the clinic is what
the headset page shows the person holding the probe (:class:`Guide`): the virtual probe and
whether it is live, and the landmark to press while calibrating.

- ``backend = "devices"``: the room is real. :class:`DeviceClinic` does nothing with the guide
  (the novice sees the page); the devices are the configured backends (``[sensing.camera]``
  ``hl2ss``/``opencv``, ``[sensing.force.sensor]`` ``hid``, ``[follower.video.*]``
  ``opencv``). No simulator module is imported in any of the follower's processes.
- ``backend = "sim"`` (the demo's): :mod:`humantele.follower.sim_clinic` holds the patient,
  the novice, their head and the probe in one simulated world; its devices (tracker, force
  board, ultrasound and POV video) observe that world. The sim is imported only then.

Frames: the tracker's world (y up), SI units. This module holds the clinic's settings and
interface and imports nothing of the simulator (nor of the sensing); the factories are
:mod:`humantele.follower.clinics`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal, Protocol

from pydantic import Field

from humantele.config import ConfigModel
from humantele.geometry import Pose
from humantele.runtime.simulator import SIMULATOR_MODULES, simulator_modules  # noqa: F401 (kept here)


class SimPatientConfig(ConfigModel):
    """The simulated patient on the bed (world frame, m, N/m)."""

    bed_height_m: float = Field(0.80, description="bed surface height (world y)")
    center_xz_m: tuple[float, float] = Field(
        (0.35, -0.15), description="abdomen centre, world x and z"
    )
    yaw_deg: float = Field(20.0, ge=-180, le=180, description="body axis about world y")
    half_width_m: float = Field(0.16, gt=0.03, le=0.4, description="lateral semi-axis a")
    half_height_m: float = Field(0.11, gt=0.02, le=0.3, description="vertical semi-axis b")
    half_length_m: float = Field(0.35, gt=0.05, le=1.0, description="longitudinal semi-axis")
    tissue_stiffness_n_per_m: float = Field(600.0, gt=0, le=1e5)
    bed_stiffness_n_per_m: float = Field(5000.0, gt=0, le=1e6)


class SimHumanConfig(ConfigModel):
    """The simulated novice, as simple as the published figures need (Black et al., IJCARS
    2023 and C&G 2024, Table 3; docs/references.md; the known-answer test is
    tests/follower/test_sim_follower_figures.py, the table of which parameter comes from which
    figure docs/study.md):

    - lag 0.35 s: ``reaction_delay_s`` + ``tracking_time_constant_s`` (a dead time, then a
      first-order follow: for motion slower than 1/tau their lags add);
    - RMS error 6.24 mm / 5.93 deg, read as the error once the lag is removed (the figures
      give lag and error apart): ``offset_mm`` / ``offset_rotation_deg`` (how this person holds
      the probe, most of it) with the tremor and the follow's smoothing on top;
    - tremor: physiological hand tremor, 8-12 Hz and under 1 mm (no study figure; small).
    """

    reaction_delay_s: float = Field(0.20, ge=0, le=2.0)
    tracking_time_constant_s: float = Field(0.15, gt=0, le=2.0)
    offset_mm: tuple[float, float, float] = Field((3.6, -2.4, 4.2), description="world frame")
    offset_rotation_deg: tuple[float, float, float] = Field(
        (3.75, -2.5, 3.75), description="rotation vector (deg) applied in the tip frame"
    )
    tremor_mm_rms: float = Field(0.8, ge=0, le=20, description="per axis")
    tremor_deg_rms: float = Field(0.6, ge=0, le=20, description="per axis")
    tremor_hz: float = Field(9.0, gt=1, le=30)
    rate_hz: float = Field(100.0, gt=10, le=1000, description="nominal step rate of the model")
    max_push_n: float = Field(30.0, gt=0, le=100, description="a person pushes no harder")
    seed: int = 0


class SimHeadConfig(ConfigModel):
    """The follower's head (the headset camera): above the work, looking down, following the
    probe loosely (people keep their hands in view)."""

    height_m: float = Field(0.42, gt=0.1, le=1.0, description="camera above the probe tip")
    follow_time_constant_s: float = Field(0.6, gt=0, le=10)


class SimClinicConfig(ConfigModel):
    """The simulated clinic (``[follower.clinic]``, ``backend = "sim"``): a patient on a bed,
    the novice holding the probe (a model of the study's people: docs/references.md), their
    head wearing the headset; ``auto_calibrate``: the simulated technician presses the four
    landmarks when asked."""

    backend: Literal["sim"] = "sim"
    auto_calibrate: bool = Field(True, description="the simulated technician presses landmarks")
    patient: SimPatientConfig = Field(default_factory=SimPatientConfig)
    novice: SimHumanConfig = Field(default_factory=SimHumanConfig)
    head: SimHeadConfig = Field(default_factory=SimHeadConfig)


class DeviceClinicConfig(ConfigModel):
    """A real clinic (``backend = "devices"``): every device is a configured backend."""

    backend: Literal["devices"] = "devices"


ClinicConfig = Annotated[SimClinicConfig | DeviceClinicConfig, Field(discriminator="backend")]


@dataclass(frozen=True)
class Guide:
    """What the headset page shows the person holding the probe at time ``t`` (s): the
    virtual probe's tip (world; None before a pose and a calibration), whether it is live
    (fresh, link up, no clutch: follow it) and, while calibrating, the landmark asked for
    (None otherwise). ``measuring``: the follower's sensing measures (a press before it
    does is not seen)."""

    t: float
    virtual: Pose | None
    live: bool
    landmark: str | None
    measuring: bool = True


class Clinic(Protocol):
    """The room, as the daemon sees it."""

    def step(self, guide: Guide) -> None:
        """The person sees ``guide`` (each tick)."""

    def world_at_frame(self, t: float) -> Any:
        """What simulated devices observe at a tracker frame taken at ``t`` (passed to the
        sensing as it is, never read by the daemon); None with real devices."""

    def scene(self) -> Any:
        """The latest scene for simulated video sources (None with real devices)."""


class DeviceClinic:
    """A real clinic: the novice sees the headset page; nothing to simulate."""

    def step(self, guide: Guide) -> None:
        pass

    def world_at_frame(self, t: float) -> None:
        return None

    def scene(self) -> None:
        return None
