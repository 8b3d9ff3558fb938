"""The simulated clinic: one simulated world (:mod:`humantele.follower.sim_world`: patient,
novice, head, probe, bed) and the devices that observe it, behind the clinic interface
(:mod:`humantele.follower.clinic`).

- :class:`SimClinic` lives in the daemon's process: each tick the novice sees the guide (the
  virtual probe while it is live; the landmark asked for while calibrating, pressed by the
  scripted technician when ``auto_calibrate``) and moves the probe; at each tracker frame it
  hands the sensing the world as its devices observe it (:meth:`SimClinic.world_at_frame`,
  opaque to the daemon), and it publishes the scene the sim video sources render.
- :func:`sim_sensing_devices` builds, in the sensing process, the headset's tracker camera
  and the probe's force board as devices: frames with the camera's pose in the world (the
  simulated head; the rig is the camera here), readings of the force the patient puts on
  the probe.
- :class:`IdealSensing` (``probe_source = "truth"``): a perfect tracker and force sensor of
  the same world, for tests that do not need the pipeline's noise.

Frames: the tracker's world (y up), SI units; poses are of the transducer's tip frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from humantele.follower.clinic import Guide, SimClinicConfig
from humantele.follower.sensing_devices import (
    ProbeMeasurement,
    SensingConfig,
    SensingDevices,
    tip_transform,
)
from humantele.follower.sim_human import CalibrationScript
from humantele.follower.sim_world import SimWorld, WorldTruth
from humantele.forcesense.calibration import ForceCalibration, calibrate_sim
from humantele.forcesense.sensors import calibration_path
from humantele.forcesense.sim import SimForceConfig, SimForceSensor
from humantele.geometry import Pose
from humantele.tracking.frames import TrackingFrame
from humantele.tracking.sim import SimFrameConfig, SimFrameSource
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import ToolDefinition
from humantele.video.scene import SceneSnapshot

OUT_OF_VIEW = Pose([0.0, 0.0, -1.0], [0.0, 0.0, 0.0, 1.0])  # behind the camera: not drawn
# The scripted technician keeps a press on until the headset page says the landmark was taken
# (it asks for the next one), as a person reading the page does, at most this long past the
# script's hold (s): then lifts and presses again (a press the sensing never saw, or refused).
CONFIRM_WAIT_S = 4.0
LIFTED_M = 0.03  # the probe this near the script's lifted pose: lifted, off to the next one


class SimClinic:
    """The simulated room, advanced by the follower's tick. ``on_scene``: where the scene
    goes for the sim video sources (the video sender's ``publish_scene``; None: no video)."""

    def __init__(self, config: SimClinicConfig, on_scene: Callable[[Any], None] | None = None):
        self.config = config
        self.world = SimWorld(config.patient, config.novice, config.head)
        self.patient = self.world.patient.ellipsoid()  # what the sim video renders
        self.on_scene = on_scene
        self.script: CalibrationScript | None = None
        self.script_t0 = 0.0
        self.pressing: str | None = None  # the landmark the technician's press is for
        self.waiting_since: float | None = None  # held past the script, for the page's word
        self._head: Pose | None = None
        self._scene: SceneSnapshot | None = None

    def step(self, guide: Guide) -> None:
        """The novice moves the probe: toward the live virtual probe, or (the scripted
        technician) onto the landmark asked for, again if refused; still otherwise."""
        t, target = guide.t, None
        if guide.landmark is not None and self.config.auto_calibrate:
            target = self._press(guide)
        else:
            self.script = self.pressing = None
            target = guide.virtual if guide.live else None
        self.world.step(t, target)
        self._publish_scene(t, guide.virtual)

    def _press(self, guide: Guide) -> Pose:
        """The scripted technician's target: the press of the landmark asked for, held until
        the page asks for another one (taken) or ``CONFIRM_WAIT_S`` past the script's hold;
        then lifted clear, and the landmark asked for then is pressed from the top. Driven by what
        the page says, not by the clock alone: a loaded machine that measures a few frames a
        second still sees every press."""
        t = guide.t
        if self.script is None or self.pressing is None:
            self.script, self.script_t0 = self.world.calibration_script(), t
            self.pressing, self.waiting_since = guide.landmark, None
        script = self.script
        if not guide.measuring:  # a press before the sensing measures is not seen
            self.script_t0, self.pressing, self.waiting_since = t, guide.landmark, None
        elapsed = t - self.script_t0
        if self.pressing == guide.landmark and elapsed >= script.hold_end_s:
            if self.waiting_since is None:
                self.waiting_since = t
            if t - self.waiting_since < CONFIRM_WAIT_S:  # not taken yet: keep pressing
                self.script_t0, elapsed = t - script.hold_end_s, script.hold_end_s
        target = script.target(self.pressing, elapsed)
        if target is None:  # lifted clear (the hand lags the script) before moving on
            high = script.target(self.pressing, script.segment_s)
            tip = self.world.T_world_tip
            if tip is not None and np.linalg.norm(tip.position - high.position) > LIFTED_M:
                return high
        if target is None:  # this press is over: the landmark asked for now, from the top
            self.script_t0, self.pressing, self.waiting_since = t, guide.landmark, None
            target = script.target(self.pressing, 0.0)
        return target

    def world_at_frame(self, t: float) -> WorldTruth:
        """The world as the devices observe it at a tracker frame (the head follows)."""
        truth = self.world.truth(t)
        self._head = truth.T_world_camera
        return truth

    def scene(self) -> SceneSnapshot:
        """The latest scene (called from the video threads)."""
        s = self._scene
        return s if s is not None else SceneSnapshot(0.0, self.patient, None, 0.0, None)

    def _publish_scene(self, t: float, virtual: Pose | None) -> None:
        tip, force = self.world.T_world_tip, self.world.force_world
        force_n = 0.0
        if tip is not None:
            force_n = max(0.0, -float(np.dot(force, tip.rotate((0.0, 0.0, 1.0)))))
        self._scene = SceneSnapshot(t, self.patient, tip, force_n, self._head, virtual)
        if self.on_scene is not None:
            self.on_scene(self._scene)


class _View:
    """The world the sim devices observe at the current frame (shared by both)."""

    def __init__(self) -> None:
        self.world: WorldTruth | None = None

    def observe(self, world: WorldTruth) -> None:
        self.world = world


class SimHeadsetCamera(SimFrameSource):
    """The headset's AHAT-like camera in the sim clinic: frames of the probe where the world
    has it, each with the camera's pose (the simulated head: rig and camera are one here);
    none before the head is placed."""

    name = "sim headset camera"

    def __init__(self, config: SimFrameConfig, tool: ToolDefinition, view: _View) -> None:
        super().__init__(config, tool)
        self.view = view
        self.T_tip_probe = tip_transform(tool).inverse()
        self.no_pose = 0

    def read(self, t: float | None = None) -> TrackingFrame | None:
        w = self.view.world
        if w is None or w.T_world_camera is None:
            self.no_pose += 1
            return None
        T_camera_world = w.T_world_camera.inverse()
        held = w.T_world_tip is not None
        frame = self.render(
            T_camera_world @ w.T_world_tip @ self.T_tip_probe if held else OUT_OF_VIEW, t
        )
        frame.T_world_camera = frame.T_world_rig = w.T_world_camera
        return frame


class SimProbeForceSensor(SimForceSensor):
    """The probe's force board in the sim clinic: loaded with the force the patient puts on
    the probe where the world has it (probe frame)."""

    def __init__(self, config: SimForceConfig, tool: ToolDefinition, view: _View) -> None:
        super().__init__(config)
        self.view = view
        self.T_tip_probe = tip_transform(tool).inverse()

    def read(self, t: float | None = None):  # -> ForceReading
        w = self.view.world
        if w is not None:
            if w.T_world_tip is None:
                self.set_force(np.zeros(3))
            else:
                R = (w.T_world_tip @ self.T_tip_probe).rotation_matrix
                self.set_force(R.T @ np.asarray(w.force_world, dtype=float))
        return super().read(t)


def sim_sensing_devices(config: SensingConfig, tool: ToolDefinition) -> SensingDevices:
    """The sim clinic's tracker camera and force board (not opened), the board's calibration
    (its file, or a calibration of a twin of the board: same seed, the same board)."""
    if not isinstance(config.camera, SimFrameConfig):
        raise ValueError(
            f"the simulated clinic's tracker is the sim camera, not {config.camera.backend!r}: "
            '[sensing.camera] backend = "sim", or [follower.clinic] backend = "devices"'
        )
    force = config.force.sensor
    if not isinstance(force, SimForceConfig):
        raise ValueError(
            f"the simulated clinic's force board is the sim one, not {force.backend!r}: "
            '[sensing.force.sensor] backend = "sim", or [follower.clinic] backend = "devices"'
        )
    view = _View()
    path = calibration_path(config.force)
    calibration = (
        ForceCalibration.load(path) if path is not None else calibrate_sim(SimForceSensor(force))
    )
    return SensingDevices(
        SimHeadsetCamera(config.camera, tool, view),
        SimProbeForceSensor(force, tool, view),
        calibration,
        view.observe,
    )


class IdealSensing:
    """A perfect tracker and force sensor of the sim world (``probe_source = "truth"``):
    the probe where the world has it, in contact above ``contact_n`` (N)."""

    def __init__(self, T_probe_tip: Pose, contact_n: float) -> None:
        self.T_tip_probe = T_probe_tip.inverse()
        self.contact_n = contact_n

    def measure(self, t: float, world: WorldTruth | None) -> ProbeMeasurement:
        force = np.zeros(3) if world is None else np.asarray(world.force_world, dtype=float)
        if world is None or world.T_world_tip is None:
            return ProbeMeasurement(t, TrackingStatus.LOST, None, None, force, np.zeros(3),
                                    False, math.nan)  # fmt: skip
        probe = world.T_world_tip @ self.T_tip_probe
        return ProbeMeasurement(
            t,
            TrackingStatus.TRACKED,
            probe,
            world.T_world_tip.position,
            force,
            probe.rotation_matrix.T @ force,
            float(np.linalg.norm(force)) > self.contact_n,
            0.0,
            T_world_rig=world.T_world_camera,
        )

    def close(self) -> None:
        pass
