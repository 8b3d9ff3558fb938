"""What the headset page and the log are told of the follower's devices: the headset's stream
stalled or back, the force board stale (unplugged or silent) or back, each as it changes."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from humantele.follower.sensing import Measurement

log = logging.getLogger(__name__)

# each state's words in the log: (when it goes bad, when it is back)
WORDS = {
    "headset_stream_stalled": ("headset stream stalled", "headset stream back"),
    "force_stale": ("force board stale (unplugged or silent): no force sent", "force board back"),
}


class DeviceWatch:
    """The devices' state from each measurement (``camera_stalled``, ``force_stale``), given to
    ``publish`` (the headset page's feed) as it changes."""

    def __init__(self, publish: Callable[[dict[str, bool]], None]) -> None:
        self.publish = publish
        self.state = {"headset_stream_stalled": False, "force_stale": False}

    def update(self, m: Measurement) -> None:
        """A measurement: a changed state is logged (a warning when a device goes bad, info
        when it is back) and published; the same state, nothing."""
        now = {"headset_stream_stalled": bool(m.camera_stalled), "force_stale": bool(m.force_stale)}
        if now == self.state:
            return
        for key, (bad, good) in WORDS.items():
            if now[key] != self.state[key]:
                (log.warning if now[key] else log.info)("follower: %s", bad if now[key] else good)
        self.state = now
        self.publish(dict(now))
