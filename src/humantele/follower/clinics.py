"""The clinic a follower configuration asks for (:mod:`humantele.follower.clinic`), and the
sensing devices it provides: the sim clinic's (:mod:`humantele.follower.sim_clinic`, imported
only when asked for) or the configured real backends."""

from __future__ import annotations

from typing import Any

from humantele.follower.clinic import Clinic, DeviceClinic, DeviceClinicConfig, SimClinicConfig
from humantele.follower.sensing_devices import SensingConfig, SensingDevices, real_sensing_devices
from humantele.tracking.tool import ToolDefinition


def make_clinic(config: SimClinicConfig | DeviceClinicConfig, video: Any = None) -> Clinic:
    """The clinic a configuration asks for; ``video``: the video sender whose simulated
    sources render the sim clinic's scene (None: no video)."""
    if isinstance(config, SimClinicConfig):
        from humantele.follower.sim_clinic import SimClinic  # the simulator, only when asked

        return SimClinic(config, video)
    return DeviceClinic()


def make_sensing_devices(
    clinic: SimClinicConfig | DeviceClinicConfig,
    sensing: SensingConfig,
    tool: ToolDefinition,
) -> SensingDevices:
    """The tracker camera and force sensor (not yet opened) with the force calibration: the
    sim clinic's devices, or the configured real backends (a ``sim`` backend in a real
    clinic is refused: nothing would move it)."""
    if isinstance(clinic, SimClinicConfig):
        from humantele.follower.sim_clinic import sim_sensing_devices

        return sim_sensing_devices(sensing, tool)
    return real_sensing_devices(sensing, tool)
