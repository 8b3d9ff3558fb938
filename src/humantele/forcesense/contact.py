"""Contact detector with hysteresis: one press of the probe on the patient -> one event.

Contact starts when the force magnitude rises above ``on_n`` and ends when it falls below
``off_n`` (< on_n), each only after holding for ``hold_s``, so noise near a threshold does not
chatter. Used by the landmark calibration: each press collects one point.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from pydantic import Field, model_validator

from humantele.config import ConfigModel

ContactEvent = Literal["press", "release"]


class ContactConfig(ConfigModel):
    """Thresholds on the force magnitude (N) and the hold time (s)."""

    on_n: float = Field(3.0, gt=0)
    off_n: float = Field(1.5, ge=0)
    hold_s: float = Field(0.03, ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> ContactConfig:
        if self.off_n >= self.on_n:
            raise ValueError(f"off_n ({self.off_n}) must be below on_n ({self.on_n})")
        return self


class ContactDetector:
    """``update(t, force)`` returns "press", "release" or None; ``in_contact`` is the state."""

    def __init__(self, config: ContactConfig | None = None):
        self.config = config or ContactConfig()
        self.in_contact = False
        self._since: float | None = None
        self.presses = 0

    def reset(self) -> None:
        """Forget the state (no contact, no hold under way): the force is unknown."""
        self.in_contact = False
        self._since = None

    def update(self, t: float, force: ArrayLike) -> ContactEvent | None:
        """Feed one force sample (N, any frame) at time t (s). Non-finite samples are ignored."""
        f = np.asarray(force, dtype=float)
        mag = float(np.linalg.norm(f))
        if not np.isfinite(mag):
            return None
        c = self.config
        crossing = mag < c.off_n if self.in_contact else mag > c.on_n
        if not crossing:
            self._since = None
            return None
        if self._since is None:
            self._since = t
        if t - self._since < c.hold_s:
            return None
        self._since = None
        self.in_contact = not self.in_contact
        if self.in_contact:
            self.presses += 1
            return "press"
        return "release"
