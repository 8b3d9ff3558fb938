"""Which of the simulator's modules a process loaded: none in a real clinic's processes (the
follower daemon, its sensing and video processes each report theirs in the stats)."""

from __future__ import annotations

import sys

SIMULATOR_MODULES = frozenset({  # the simulated world and its devices' renderers
    "humantele.follower.sim_clinic", "humantele.follower.sim_world", "humantele.follower.sim_human",
    "humantele.tracking.sim", "humantele.forcesense.sim", "humantele.video.scene",
    "humantele.video.simsource", "humantele.video.sim_ultrasound", "humantele.video.sim_pov",
    "humantele.video.phantom", "humantele.video.speckle",
})  # fmt: skip


def simulator_modules() -> list[str]:
    """The simulator's modules loaded in this process (none in a real clinic's follower)."""
    return sorted(SIMULATOR_MODULES.intersection(sys.modules))
