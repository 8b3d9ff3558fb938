"""The follower's calibration as a session: the saved calibration reused at start, or the four
landmark presses (:class:`~humantele.follower.calibration.Calibrator`) while calibrating,
each one said to the expert (``CalibrationProgress``), the headset page (``calibration``
objects) and the recording; the fit saved under ``state_dir`` for the next start."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from numpy.typing import ArrayLike

from humantele.follower.calibration import (
    CALIBRATION_FILE,
    LANDMARKS,
    Calibration,
    CalibrationConfig,
    CalibrationEvent,
    Calibrator,
)
from humantele.follower.records import calibration_event_samples
from humantele.wire import CalibrationProgress, ControlMessage

log = logging.getLogger(__name__)


class CalibrationSession:
    """``send(msg)``: a control message to the expert; ``publish(kind, fields)``: to the
    headset page; ``record(topic, t, payload)``; ``on_fitted(t)``: a new calibration is in
    :attr:`calibration` (the daemon sends and draws the model)."""

    def __init__(
        self,
        config: CalibrationConfig,
        state_dir: Path,
        send: Callable[[ControlMessage], Any],
        publish: Callable[[str, dict], None],
        record: Callable[[str, float | None, dict], None],
        on_fitted: Callable[[float | None], None],
    ) -> None:
        self.path = state_dir / CALIBRATION_FILE
        self.calibration: Calibration | None = Calibration.load(self.path)
        self.reused = self.calibration is not None
        self.calibrator = Calibrator(config)
        self.calibrating = False
        self.save_error = ""  # why the last calibration could not be saved
        self.last_event: CalibrationEvent | None = None
        self.send, self.publish_fn, self.record = send, publish, record
        self.on_fitted = on_fitted
        self._model_recorded: Calibration | None = None

    def record_model(self, t: float | None = None) -> None:
        """The fitted model (world frame, as ``Ellipsoid.to_dict``), once per calibration."""
        if self.calibration is None or self._model_recorded is self.calibration:
            return
        self._model_recorded = self.calibration
        self.record("/follower/ellipsoid", t, self.calibration.ellipsoid.to_dict())

    @property
    def landmark(self) -> str | None:
        """The landmark asked for (None when not calibrating)."""
        return self.calibrator.step if self.calibrating else None

    def start(self) -> None:
        self.calibrating = True
        self.calibrator.reset()
        self.record("/follower/calibration", time.monotonic(), {"event": "reset"})
        self.send(CalibrationProgress(event="start"))
        self.publish()

    def forget(self) -> None:
        """Ignore a saved calibration (``--recalibrate``)."""
        self.calibration, self.reused = None, False

    def update(self, t: float, tip: ArrayLike | None, force_n: float) -> None:
        """One measurement while calibrating (an untracked press still counts for the
        hysteresis)."""
        ev = self.calibrator.update(tip, force_n)
        if ev is not None:
            self.on_event(ev, t)

    def save(self) -> bool:
        """Save the calibration for the next start; a failure (read-only or full state dir) is
        reported (log, stats ``calibration_save_error``) and the session goes on without it."""
        try:
            self.calibration.save(self.path)
        except OSError as exc:
            self.save_error = f"{exc.strerror or exc}: {exc.filename or ''}".strip()
            log.error(
                "follower: calibration not saved (%s); it is used now but will be asked for "
                "again at the next start", self.save_error,
            )  # fmt: skip
            return False
        self.save_error = ""
        return True

    def on_event(self, ev: CalibrationEvent, t: float | None = None) -> None:
        self.last_event = ev
        log.info("calibration: %s", ev.message)
        index = LANDMARKS.index(ev.landmark)
        point = tuple(float(v) for v in ev.point)
        for payload in calibration_event_samples(ev):
            self.record("/follower/calibration", t, payload)
        if ev.kind == "refused":
            detail = ev.message[:200]
            self.send(CalibrationProgress(event="error", index=index, point=point, detail=detail))
        else:
            self.send(CalibrationProgress(event="point", index=index, point=point))
        if ev.kind == "done" and self.calibrator.result is not None:
            self.calibration = self.calibrator.result
            self.save()  # best-effort: the model goes to the expert regardless
            self.calibrating = False
            self.send(CalibrationProgress(event="done"))
            self.on_fitted(t)
        self.publish(ev)

    def publish(self, event: CalibrationEvent | None = None) -> None:
        """The state to the headset page (and the event, if one)."""
        self.publish_fn(
            "calibration",
            {
                "calibrated": self.calibration is not None,
                "calibrating": self.calibrating,
                "step": self.landmark,
                "prompt": self.calibrator.prompt() if self.calibrating else "",
                "event": None if event is None else event.kind,
                "landmark": None if event is None else event.landmark,
                "message": "" if event is None else event.message,
            },
        )

    def stats(self) -> dict[str, Any]:
        return {
            "calibrated": self.calibration is not None,
            "calibration_reused": self.reused,
            "calibration_save_error": self.save_error,
            "calibration_refusals": self.calibrator.refusals,
            "calibration_step": self.landmark,
        }
