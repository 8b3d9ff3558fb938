"""The follower's simulated world: the patient on the bed, the person holding the probe, and
the person's head (the headset camera). One object the sim sensing backends read, so the
daemon sees the sensors, not the simulation behind them.

Frames: the headset's world frame (y up), m, N, s. Poses are of the transducer's tip frame
(:mod:`humantele.follower.sim_human`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from humantele.follower.sim_human import (
    CalibrationScript,
    SimHead,
    SimHeadConfig,
    SimHuman,
    SimHumanConfig,
    SimPatient,
    SimPatientConfig,
)
from humantele.geometry import Pose


@dataclass(frozen=True)
class WorldTruth:
    """What the sim tracker and force sensor measure at one tracker image (time ``t``, s):
    ``T_world_tip`` (None: the probe is not held), the force on the tip ``force_world`` (N)
    and the headset camera ``T_world_camera`` (None: not placed yet)."""

    t: float
    T_world_tip: Pose | None
    force_world: NDArray[np.float64]
    T_world_camera: Pose | None


class SimWorld:
    """The simulated patient, person and head, advanced by the follower's tick."""

    def __init__(
        self,
        patient: SimPatientConfig | None = None,
        human: SimHumanConfig | None = None,
        head: SimHeadConfig | None = None,
    ) -> None:
        self.patient = SimPatient(patient)
        self.human = SimHuman(human, self.patient)
        self.head = SimHead(head)
        self.T_world_tip: Pose | None = None
        self.force_world: NDArray[np.float64] = np.zeros(3)

    def calibration_script(self) -> CalibrationScript:
        """The scripted technician's presses on this patient's landmarks."""
        return CalibrationScript(self.patient)

    def step(self, t: float, target: Pose | None) -> None:
        """The person moves the probe toward ``target`` (tip, world; None: holds still)."""
        self.T_world_tip = self.human.step(t, target)
        tip = self.T_world_tip
        self.force_world = np.zeros(3) if tip is None else self.patient.force(tip.position)

    def truth(self, t: float) -> WorldTruth:
        """The world at a tracker image taken at ``t`` (the head follows the probe)."""
        tip = self.T_world_tip
        camera = self.head.step(t, None if tip is None else tip.position)
        return WorldTruth(t, tip, self.force_world, camera)
