"""The follower daemon's configuration (``[follower]`` of configs/follower.toml): every field
has a default that runs the demo on the simulated clinic."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from humantele.config import ConfigModel
from humantele.daemons.session import SessionConfig
from humantele.follower.calibration import CalibrationConfig
from humantele.follower.clinic import ClinicConfig, SimClinicConfig
from humantele.follower.feed import FeedConfig
from humantele.follower.registration import RegistrationConfig
from humantele.interop.igtl import IgtlConfig
from humantele.media.config import FollowerVideoConfig
from humantele.recording import RecorderConfig
from humantele.runtime.child import PRIORITY, Priority
from humantele.transport import LinkConfig

DEFAULT_STATE_DIR = "~/.local/state/humantele/follower"
SIM_SETTING = 'the simulated clinic is [follower.clinic] (backend = "sim"): '


class FollowerConfig(ConfigModel):
    """The follower daemon (``[follower]`` of configs/follower.toml)."""

    moved_fields = {
        "auto_calibrate": SIM_SETTING + "auto_calibrate",
        "sim_patient": SIM_SETTING + "[follower.clinic.patient]",
        "sim_human": SIM_SETTING + "[follower.clinic.novice]",
        "sim_head": SIM_SETTING + "[follower.clinic.head]",
    }

    rate_hz: float = Field(100.0, gt=1, le=1000, description="tick: probe, sensing, state")
    stale_after_s: float = Field(0.3, gt=0, le=10, description="virtual probe stale after")
    alignment_settle_s: float = Field(
        1.0, ge=0, le=30, description="alignment error counted this long after following starts"
    )
    state_dir: str = Field(DEFAULT_STATE_DIR, description="where the calibration is saved")
    probe_source: Literal["pipeline", "truth"] = Field(
        "pipeline", description="measure through the sensing pipeline ([sensing]), or the truth"
    )
    sensing_rate_hz: float = Field(45.0, gt=1, le=1000, description="tracker frames per second")
    sensing_worker: Literal["process", "thread"] = Field(
        "process",
        description="where frames are measured while the daemon runs: a child process (its "
        "GIL apart from the loop's) or a thread",
    )
    sensing_realtime_priority: int = Field(
        PRIORITY["sensing"].fifo, ge=0, lt=PRIORITY["loop"].fifo,
        description="the sensing process's SCHED_FIFO priority: below the daemons' loops, "
        "above every normal process (the video, a browser); 0: normal policy at sensing_nice",
    )  # fmt: skip
    sensing_nice: int = Field(
        PRIORITY["sensing"].nice, ge=0, le=18,
        description="the sensing process's nice where it runs at the normal policy; below "
        "[follower.video] process_nice (the tracker before the video)",
    )  # fmt: skip
    tool: str = Field(
        "probe_default", description="the probe's tool definition: tracked, drawn, tip (one)"
    )
    link: LinkConfig = LinkConfig()
    feed: FeedConfig = FeedConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    clinic: ClinicConfig = Field(default_factory=SimClinicConfig)
    video: FollowerVideoConfig = FollowerVideoConfig()
    session: SessionConfig = SessionConfig()
    recording: RecorderConfig = RecorderConfig()
    igtl: IgtlConfig = IgtlConfig()
    registration: RegistrationConfig = RegistrationConfig()

    @property
    def sensing_priority(self) -> Priority:
        """The sensing process's scheduling (:func:`humantele.runtime.child.set_priority`):
        always below the loop's (the pose stream first), so none when the loop runs at the
        normal policy (``[follower.link] realtime_priority = 0``)."""
        loop = self.link.realtime_priority
        fifo = min(self.sensing_realtime_priority, loop - 1) if loop > 0 else 0
        return Priority(fifo=fifo, nice=self.sensing_nice)

    @model_validator(mode="after")
    def _tracker_before_video(self) -> FollowerConfig:
        """The video gives way first (issue 19 §2): the sensing process (tracker, force) must
        run at a lower nice than the video process."""
        if self.sensing_worker == "process" and self.sensing_nice >= self.video.process_nice:
            raise ValueError(
                f"sensing_nice = {self.sensing_nice} must be below [follower.video] "
                f"process_nice = {self.video.process_nice}: the tracker comes before the video"
            )
        return self

    @model_validator(mode="after")
    def _sim_needs_the_sim_clinic(self) -> FollowerConfig:
        if isinstance(self.clinic, SimClinicConfig):
            return self
        if self.probe_source == "truth":
            raise ValueError(
                'probe_source = "truth" is the simulated clinic\'s ideal sensor: '
                'use "pipeline" with [follower.clinic] backend = "devices"'
            )
        if self.video.enabled:
            for name in ("us", "pov"):
                if getattr(self.video, name).backend == "sim":
                    raise ValueError(
                        f'video.{name}: a "sim" source needs the simulated clinic; with '
                        'backend = "devices" give it a real one (e.g. "opencv")'
                    )
        return self
