"""The four-landmark calibration of the paper: xiphoid, extreme left, extreme right, bed.

The technician presses the probe on each landmark in turn. A landmark is taken at the probe
tip (world frame, m) when the measured force magnitude rises above ``force_on_n``; the next one
can only be taken after the force has fallen below ``force_off_n`` (hysteresis: one press gives
one landmark). Each landmark is checked as it is taken; an implausible one is refused with a
message the technician can act on ("press again on the right side: ...") and the same landmark
is asked again.

Frames. The world frame is the headset's, y up; landmarks are world points (m). The fit is
:meth:`humantele.haptics.ellipsoid.Ellipsoid.from_landmarks` (eqs. 1-5 of the paper plus the
heading of the body): its patient frame has y up, z from the patient's left to right, x head
to feet, origin at the ellipsoid centre. ``T_world_patient`` places that frame in the room; the
expert works in the patient frame only.

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
from humantele.geometry import Pose
from humantele.haptics.ellipsoid import (
    DEFAULT_LONGITUDINAL,
    MAX_LONGITUDINAL,
    MIN_BODY_SEMI_AXIS,
    Ellipsoid,
    LandmarkError,
)
from humantele.wire import LANDMARKS  # the landmarks' names and order: one list, on the wire

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
    min_height_m: float = Field(0.10, gt=0, description="least xiphoid height above the bed")
    max_height_m: float = Field(0.50, gt=0, description="largest xiphoid height above the bed")
    side_height_tolerance_m: float = Field(
        0.05, ge=0, description="how far a side landmark may be above the xiphoid or below the bed"
    )
    long_semi_axis_m: float = Field(
        DEFAULT_LONGITUDINAL,
        ge=MIN_BODY_SEMI_AXIS,
        le=MAX_LONGITUDINAL,
        description="the paper's very large longitudinal semi-axis c (m)",
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


@dataclass
class Calibration:
    """A finished calibration: the landmarks (world, m) and the ellipsoid fitted to them.

    ``ellipsoid`` is in the world frame; ``T_world_patient`` is its patient frame (origin at the
    centre); :meth:`model_patient` is the same ellipsoid expressed in the patient frame, which is
    what the expert renders (the wire's poses are in that frame).
    """

    landmarks_world: dict[str, NDArray[np.float64]]
    ellipsoid: Ellipsoid
    created_unix: float = field(default_factory=time.time)

    @property
    def T_world_patient(self) -> Pose:  # noqa: N802 (frame names keep their case)
        return self.ellipsoid.T_world_patient

    def model_patient(self) -> Ellipsoid:
        """The ellipsoid in its own patient frame: centre at the origin, heading 0."""
        return Ellipsoid((0.0, 0.0, 0.0), self.ellipsoid.semi_axes, 0.0)

    def landmarks_patient(self) -> dict[str, NDArray[np.float64]]:
        return {k: self.ellipsoid.to_patient(v) for k, v in self.landmarks_world.items()}

    def to_dict(self) -> dict[str, Any]:
        return {
            "version": FORMAT_VERSION,
            "created_unix": self.created_unix,
            "landmarks_world": {k: [float(x) for x in v] for k, v in self.landmarks_world.items()},
            "ellipsoid_world": self.ellipsoid.to_dict(),
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
            ellipsoid = Ellipsoid.from_dict(d["ellipsoid_world"])
            return cls(lm, ellipsoid, float(d.get("created_unix", 0.0)))
        except (KeyError, TypeError, IndexError, AttributeError) as exc:
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
    landmarks_world: dict[str, ArrayLike], config: CalibrationConfig | None = None
) -> Calibration:
    """Fit the ellipsoid (paper eqs. 1-5 plus heading) to four landmarks (world frame, m).

    Raises :class:`humantele.haptics.ellipsoid.LandmarkError` naming a landmark to retake."""
    config = config or CalibrationConfig()
    lm = {k: np.asarray(landmarks_world[k], dtype=float).reshape(3) for k in LANDMARKS}
    ellipsoid = Ellipsoid.from_landmarks(
        lm["xiphoid"], lm["left"], lm["right"], lm["bed"], config.long_semi_axis_m
    )
    return Calibration(lm, ellipsoid)


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
        except LandmarkError as exc:  # retake the landmark the fit blames
            bad = exc.landmark if exc.landmark in self.taken else name
            del self.taken[bad]
            self.refusals += 1
            place = {"left": "left side", "right": "right side"}.get(bad, bad)
            msg = f"press again on the {place}: {exc.reason}"
            return CalibrationEvent("refused", bad, self.taken.get(bad, tip), msg)
        return CalibrationEvent("done", name, tip, "calibration done")
