"""The four-landmark calibration of the paper: xiphoid, extreme left, extreme right, bed.

The technician presses the probe on each landmark in turn. A landmark is taken at the probe
tip (world frame, m) when the measured force magnitude rises above ``force_on_n``; the next one
can only be taken after the force has fallen below ``force_off_n`` (hysteresis: one press gives
one landmark). Each landmark is checked as it is taken; an implausible one is refused with a
message the technician can act on ("press again on the right side: ...") and the same landmark
is asked again.

Frames. The world frame is the headset's, y up. From the landmarks we build the patient frame
of the paper: y up (world y), z lateral from the patient's left to right (the horizontal
direction from the left landmark to the right one), x = y cross z (head to feet). Its origin
is on the bed, under the xiphoid. The ellipsoid is fitted in this frame (eqs. 1-5 of the
paper), so ``T_world_patient`` places it in the room and the expert works in patient frame.

The result is saved as a small JSON file so a restart or a reconnect reuses it.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator

from humantele.config import ConfigModel
from humantele.geometry import Pose, matrix_to_quat

LANDMARKS: tuple[str, ...] = ("xiphoid", "left", "right", "bed")

PROMPTS: dict[str, str] = {
    "xiphoid": "press the probe on the xiphoid, just below the sternum",
    "left": "press the probe on the patient's extreme left side, at its widest",
    "right": "press the probe on the patient's extreme right side, at its widest",
    "bed": "press the probe on the bed beside the patient",
}

CALIBRATION_FILE = "calibration.json"
FORMAT_VERSION = 1


class CalibrationConfig(ConfigModel):
    """Landmark detection and plausibility limits (N, m)."""

    force_on_n: float = Field(5.0, gt=0, le=40, description="landmark taken above this force")
    force_off_n: float = Field(2.0, ge=0, description="re-armed below this force")
    min_half_width_m: float = Field(0.06, gt=0, description="least plausible half width")
    max_half_width_m: float = Field(0.35, gt=0, description="largest plausible half width")
    min_height_m: float = Field(0.04, gt=0, description="least xiphoid height above the bed")
    max_height_m: float = Field(0.50, gt=0, description="largest xiphoid height above the bed")
    side_height_tolerance_m: float = Field(
        0.05, ge=0, description="how far a side landmark may be above the xiphoid or below the bed"
    )
    long_semi_axis_m: float = Field(
        2.0, gt=0, description="the paper's very large longitudinal semi-axis c"
    )

    @model_validator(mode="after")
    def _ordered(self) -> CalibrationConfig:
        if self.force_off_n >= self.force_on_n:
            raise ValueError("force_off_n must be below force_on_n (hysteresis)")
        if self.min_half_width_m >= self.max_half_width_m:
            raise ValueError("min_half_width_m must be below max_half_width_m")
        if self.min_height_m >= self.max_height_m:
            raise ValueError("min_height_m must be below max_height_m")
        return self


@dataclass(frozen=True)
class PatientModel:
    """The fitted ellipsoid in the patient frame: centre (m) and semi-axes (a, b, c) (m).

    ``a`` is lateral (z), ``b`` vertical (y), ``c`` longitudinal (x), as in the paper.
    """

    center: NDArray[np.float64]
    a: float
    b: float
    c: float

    def to_dict(self) -> dict[str, Any]:
        return {"center": [float(v) for v in self.center], "a": self.a, "b": self.b, "c": self.c}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PatientModel:
        center = np.asarray(d["center"], dtype=float).reshape(3)
        a, b, c = (float(d[k]) for k in ("a", "b", "c"))
        if not (np.all(np.isfinite(center)) and min(a, b, c) > 0 and max(a, b, c) < 100):
            raise ValueError("patient model needs a finite centre and positive semi-axes")
        return cls(center, a, b, c)


def patient_frame(landmarks_world: dict[str, ArrayLike]) -> Pose:
    """``T_world_patient`` from the landmarks: y up, z from left to right, origin on the bed
    under the xiphoid."""
    left = np.asarray(landmarks_world["left"], dtype=float)
    right = np.asarray(landmarks_world["right"], dtype=float)
    xiphoid = np.asarray(landmarks_world["xiphoid"], dtype=float)
    bed = np.asarray(landmarks_world["bed"], dtype=float)
    z = right - left
    z[1] = 0.0
    n = float(np.linalg.norm(z))
    if n < 1e-6:
        raise ValueError("left and right landmarks are at the same place")
    z /= n
    y = np.array([0.0, 1.0, 0.0])
    x = np.cross(y, z)
    R = np.column_stack([x, y, z])
    origin = np.array([xiphoid[0], bed[1], xiphoid[2]])
    return Pose(origin, matrix_to_quat(R))


def fit_patient_model(landmarks_patient: dict[str, ArrayLike], c: float) -> PatientModel:
    """Eqs. 1-5 of the paper, landmarks in the patient frame (x, y, z)."""
    x1, y1, _ = np.asarray(landmarks_patient["xiphoid"], dtype=float)
    z2 = float(np.asarray(landmarks_patient["left"], dtype=float)[2])
    z3 = float(np.asarray(landmarks_patient["right"], dtype=float)[2])
    y4 = float(np.asarray(landmarks_patient["bed"], dtype=float)[1])
    a = (z3 - z2) / 2.0
    b = (y1 - y4) / 2.0
    center = np.array([x1, (y1 + y4) / 2.0, (z3 + z2) / 2.0])
    return PatientModel(center, float(a), float(b), float(c))


@dataclass
class Calibration:
    """A finished calibration: landmarks (world, m), ``T_world_patient``, the model."""

    landmarks_world: dict[str, NDArray[np.float64]]
    T_world_patient: Pose
    model: PatientModel
    created_unix: float = field(default_factory=time.time)

    def landmarks_patient(self) -> dict[str, NDArray[np.float64]]:
        T_patient_world = self.T_world_patient.inverse()
        return {k: T_patient_world.apply(v) for k, v in self.landmarks_world.items()}

    def to_dict(self) -> dict[str, Any]:
        return {
            "version": FORMAT_VERSION,
            "created_unix": self.created_unix,
            "landmarks_world": {k: [float(x) for x in v] for k, v in self.landmarks_world.items()},
            "T_world_patient": {
                "position": [float(x) for x in self.T_world_patient.position],
                "quaternion": [float(x) for x in self.T_world_patient.quaternion],
            },
            "model": self.model.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        """Raises ValueError (with the reason) on anything malformed."""
        try:
            if d.get("version") != FORMAT_VERSION:
                raise ValueError(f"unknown calibration format version {d.get('version')!r}")
            lm = {k: np.asarray(d["landmarks_world"][k], dtype=float).reshape(3) for k in LANDMARKS}
            if not all(np.all(np.isfinite(v)) for v in lm.values()):
                raise ValueError("landmarks must be finite")
            T = d["T_world_patient"]
            pose = Pose(np.asarray(T["position"], dtype=float), np.asarray(T["quaternion"]))
            model = PatientModel.from_dict(d["model"])
            return cls(lm, pose, model, float(d.get("created_unix", 0.0)))
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"malformed calibration: {exc!r}") from exc

    def save(self, path: str | Path) -> Path:
        """Write atomically (temporary file then rename); returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1), encoding="utf-8")
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Calibration | None:
        """The saved calibration, or None if there is none or it cannot be used."""
        try:
            return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, ValueError):
            return None


def build_calibration(
    landmarks_world: dict[str, ArrayLike], config: CalibrationConfig
) -> Calibration:
    """Patient frame and fitted model from four landmarks (world frame, m)."""
    lm = {k: np.asarray(landmarks_world[k], dtype=float).reshape(3) for k in LANDMARKS}
    T_world_patient = patient_frame(lm)
    T_patient_world = T_world_patient.inverse()
    model = fit_patient_model(
        {k: T_patient_world.apply(v) for k, v in lm.items()}, config.long_semi_axis_m
    )
    return Calibration(lm, T_world_patient, model)


def _mm(v: float) -> str:
    return f"{v * 1000.0:.0f} mm"


def check_landmark(
    name: str,
    point: NDArray[np.float64],
    taken: dict[str, NDArray[np.float64]],
    cfg: CalibrationConfig,
) -> str | None:
    """None if ``point`` is a plausible ``name`` landmark given those ``taken`` before it, else
    the message to show the technician."""
    place = {"left": "left side", "right": "right side"}.get(name, name)
    again = f"press again on the {place}"
    if not np.all(np.isfinite(point)) or float(np.linalg.norm(point)) > 10.0:
        return f"{again}: the probe tip was not tracked properly"
    xi = taken.get("xiphoid")
    if name in ("left", "right") and xi is not None:
        d = point - xi
        horiz = math.hypot(d[0], d[2])
        if horiz < cfg.min_half_width_m:
            return f"{again}: it is only {_mm(horiz)} from the xiphoid, press at the widest point"
        if horiz > cfg.max_half_width_m * 1.5:
            return f"{again}: it is {_mm(horiz)} from the xiphoid, too far for the same patient"
        if d[1] > cfg.side_height_tolerance_m:
            return f"{again}: it is {_mm(d[1])} above the xiphoid, press lower on the side"
    if name == "right" and "left" in taken:
        left = taken["left"]
        width = math.hypot(point[0] - left[0], point[2] - left[2])
        if width < 2 * cfg.min_half_width_m:
            return f"{again}: it is only {_mm(width)} from the left landmark"
        if width > 2 * cfg.max_half_width_m:
            return f"{again}: it is {_mm(width)} from the left landmark, too wide"
        if xi is not None:
            dl, dr = left - xi, point - xi
            if dl[0] * dr[0] + dl[2] * dr[2] > 0:
                return f"{again}: it is on the same side as the left landmark"
    if name == "bed" and xi is not None:
        height = float(xi[1] - point[1])
        if height < cfg.min_height_m:
            return (
                f"{again}: it is only {_mm(height)} below the xiphoid, "
                "press on the bed itself, beside the patient"
            )
        if height > cfg.max_height_m:
            return f"{again}: it is {_mm(height)} below the xiphoid, press on the bed's surface"
        for side in ("left", "right"):
            if side in taken and taken[side][1] < point[1] - cfg.side_height_tolerance_m:
                return f"{again}: it is above the {side} landmark, press on the bed's surface"
    return None


@dataclass(frozen=True)
class CalibrationEvent:
    """What happened on one sample: a landmark taken, refused, or the calibration finished."""

    kind: str  # "taken" | "refused" | "done"
    landmark: str
    point: NDArray[np.float64]
    message: str


class Calibrator:
    """Turns a stream of (probe tip, force magnitude) samples into a calibration."""

    def __init__(self, config: CalibrationConfig | None = None) -> None:
        self.config = config or CalibrationConfig()
        self.reset()

    def reset(self) -> None:
        self.taken: dict[str, NDArray[np.float64]] = {}
        self.pressed = False  # force above force_on_n and not yet back below force_off_n
        self._press_used = False  # this press already gave a landmark (or a refusal)
        self.result: Calibration | None = None
        self.presses = 0
        self.refusals = 0

    @property
    def step(self) -> str | None:
        """The landmark asked for now, or None once done."""
        for name in LANDMARKS:
            if name not in self.taken:
                return name
        return None

    def prompt(self) -> str:
        s = self.step
        return PROMPTS[s] if s else "calibration done"

    def update(self, tip_world: ArrayLike | None, force_n: float) -> CalibrationEvent | None:
        """One sample: tip in world frame (m) or None when not tracked, force magnitude (N)."""
        if not math.isfinite(force_n):
            return None
        if self.pressed:
            if force_n < self.config.force_off_n:
                self.pressed = False
            elif not self._press_used and tip_world is not None:
                return self._take(np.asarray(tip_world, dtype=float))
            return None
        if force_n > self.config.force_on_n:
            self.pressed = True
            self._press_used = False
            self.presses += 1
            if tip_world is not None:
                return self._take(np.asarray(tip_world, dtype=float))
        return None

    def _take(self, tip: NDArray[np.float64]) -> CalibrationEvent | None:
        self._press_used = True
        name = self.step
        if name is None:
            return None
        problem = check_landmark(name, tip, self.taken, self.config)
        if problem is not None:
            self.refusals += 1
            return CalibrationEvent("refused", name, tip, problem)
        self.taken[name] = tip.copy()
        if self.step is not None:
            return CalibrationEvent("taken", name, tip, f"{name} taken; now {self.prompt()}")
        try:
            self.result = build_calibration(self.taken, self.config)
        except ValueError as exc:
            del self.taken[name]
            self.refusals += 1
            return CalibrationEvent("refused", name, tip, f"press again on the {name}: {exc}")
        return CalibrationEvent("done", name, tip, "calibration done")
