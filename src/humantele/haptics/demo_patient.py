"""The demo's patient: the simulated torso the demo, the benchmarks and the tests render."""

from __future__ import annotations

from humantele.haptics.ellipsoid import Ellipsoid

# Demo patient (the servo's patient frame, m, y up): a torso 0.30 m wide whose xiphoid is
# 0.22 m above the bed.
DEMO_LANDMARKS = {
    "xiphoid": (0.0, 0.97, 0.0),
    "left": (0.0, 0.86, -0.15),
    "right": (0.0, 0.86, 0.15),
    "bed": (0.3, 0.75, 0.2),
}


def demo_model() -> Ellipsoid:
    """The ellipsoid of :data:`DEMO_LANDMARKS` (the demo's and the benchmark's patient)."""
    return Ellipsoid.from_landmarks(**{k: v for k, v in DEMO_LANDMARKS.items()})
