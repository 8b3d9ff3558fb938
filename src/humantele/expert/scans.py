"""The expert's scans: numbered, started and stopped by the expert (by hand or by the
``[expert.scans]`` script), each announced to the follower with a ``Scan`` control message
and written to the recording (``/expert/scan``). Times are the daemon's clock (s)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from pydantic import Field

from humantele.config import ConfigModel
from humantele.wire import Scan

if TYPE_CHECKING:
    from humantele.recording import Recorder

log = logging.getLogger(__name__)


class ScanScriptConfig(ConfigModel):
    """Scripted scans (``[expert.scans]``): scan 1 starts ``start_after_model_s`` after the
    first patient model arrives and lasts ``length_s`` (None: until the daemon stops); then,
    with ``repeat``, the next one starts ``gap_s`` later. ``enabled = false``: scans only by
    hand (:meth:`ScanScript.start`)."""

    enabled: bool = Field(True, description="script the scans (the demo's)")
    start_after_model_s: float = Field(2.0, ge=0, le=3600, description="first scan after, s")
    length_s: float | None = Field(None, gt=0, le=36000, description="None: until the stop")
    repeat: bool = Field(False, description="start the next scan gap_s after one ends")
    gap_s: float = Field(2.0, ge=0, le=3600, description="between scripted scans, s")


class ScanScript:
    """The scan in progress and the script that starts and stops them. ``announce`` sends a
    :class:`~humantele.wire.Scan` to the follower; ``recorder()`` is the recording of the
    moment (None: not recording); both are looked up at each call (the daemon's link and
    recording may be replaced)."""

    def __init__(
        self,
        config: ScanScriptConfig,
        announce: Callable[[Scan], object],
        recorder: Callable[[], Recorder | None],
    ) -> None:
        self.config = config
        self.announce = announce
        self.recorder = recorder
        self.scan: int | None = None  # the scan in progress
        self.started = 0  # scans started so far
        self.changed_t = -math.inf  # when the last scan started or stopped (s)

    def start(self, t: float) -> int:
        """Start the next scan (a running one is stopped first); returns its number."""
        if self.scan is not None:
            self.stop(t)
        self.started += 1
        self.scan = self.started
        self.changed_t = t
        rec = self.recorder()
        if rec is not None:
            rec.scan_start(t, self.scan)
        self.announce(Scan(action="start", scan_id=str(self.scan)))
        log.info("expert: scan %d started", self.scan)
        return self.scan

    def stop(self, t: float) -> None:
        """Stop the scan in progress (nothing if none)."""
        if self.scan is None:
            return
        rec = self.recorder()
        if rec is not None:
            rec.scan_stop(t, self.scan)
        self.announce(Scan(action="stop", scan_id=str(self.scan)))
        log.info("expert: scan %d stopped", self.scan)
        self.scan = None
        self.changed_t = t

    def tick(self, t: float, model_t: float | None) -> None:
        """The scripted scans at ``t``; ``model_t``: when the first patient model arrived
        (None: not yet, so no scan)."""
        cfg = self.config
        if not cfg.enabled or model_t is None:
            return
        if self.scan is None:
            first = self.started == 0
            if first and t - model_t >= cfg.start_after_model_s:
                self.start(t)
            elif not first and cfg.repeat and t - self.changed_t >= cfg.gap_s:
                self.start(t)
        elif cfg.length_s is not None and t - self.changed_t >= cfg.length_s:
            self.stop(t)
