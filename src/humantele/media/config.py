"""Video settings of the two daemons (``[follower.video]``, ``[expert.video]``).

Defaults were chosen by measurement on the 2-core machine (docs/benchmarks.md, "Video over
the link"): VP8 (libvpx real time, ~4 ms/frame at 960x540 on one core, against 8-13 ms for
H.264 with libx264 ultrafast), US 640x480 at 20 fps, POV 960x540 at 25 fps.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from humantele.config import ConfigModel
from humantele.runtime.child import POV_EXTRA_NICE, PRIORITY
from humantele.video.sim_config import SimPovConfig, SimUltrasoundConfig
from humantele.video.sources import PovSourceConfig, UltrasoundSourceConfig

TRACKS = ("us", "pov")
MIN_KBPS, MAX_KBPS = 50, 20_000  # the bit rates a track's encoder may be set to
Codec = Literal["vp8", "h264"]


def _kbps(default: int, what: str) -> Any:
    return Field(default, ge=MIN_KBPS, le=MAX_KBPS, description=what)


class BitrateConfig(ConfigModel):
    """One track's encoder bit rate (kbit/s): it starts at ``start_kbps``; the expert's
    congestion feedback (REMB) then moves it, but never below ``min_kbps`` nor above
    ``max_kbps``. ``min_kbps = max_kbps`` fixes it (REMB ignored)."""

    start_kbps: int = _kbps(1000, "target at start")
    min_kbps: int = _kbps(250, "REMB never goes below")
    max_kbps: int = _kbps(2500, "REMB never goes above")

    @model_validator(mode="after")
    def _ordered(self) -> BitrateConfig:
        if not self.min_kbps <= self.start_kbps <= self.max_kbps:
            raise ValueError(
                f"min_kbps ({self.min_kbps}) <= start_kbps ({self.start_kbps}) <= max_kbps "
                f"({self.max_kbps}) does not hold"
            )
        return self


class UsBitrateConfig(BitrateConfig):
    """The US track's: its floor is the higher one. Below ~500 kbit/s the 640x480 US image's
    SSIM falls under 0.83 (bench video quality), and REMB also reads a loaded CPU as
    congestion; the POV gives way first."""

    min_kbps: int = _kbps(500, "REMB never goes below")


class PovBitrateConfig(BitrateConfig):
    """The POV track's (the published system's POV: 1-2 Mbit/s H.264). It starts at 300 kbit/s
    (WebRTC's own start rate) and climbs as the expert's estimate allows: until that estimate
    is trusted each encoder runs at its start rate, and the US's 1000 with the POV's 300 fit a
    1500 kbit/s link, where 1000 + 800 filled its queue (docs/video.md, "Thin, lossy links")."""

    start_kbps: int = _kbps(300, "target at start")
    max_kbps: int = _kbps(2000, "REMB never goes above")


class DegradeConfig(ConfigModel):
    """When CPU or bandwidth runs short the POV degrades; the US frame rate only for the tracker.

    Once a second the follower looks at the last window: the share of US frames the encoder
    took (of those captured), the loss the expert reports (RTCP) on either track, and the
    follower's late ticks, and the tracker's frames measured against its rate. If any is
    bad, the POV drops one level; when the POV is at its lowest and the tracker is still
    short, the US rate drops one level (x0.75, x0.5); after ``recover_s`` with all good, one
    level climbs back, the US's first. POV levels: 0 full size and rate; 1 full size, half
    rate; 2 half size (each side), half rate; 3 half size, quarter rate.
    """

    enabled: bool = True
    min_us_delivery: float = Field(
        0.85, ge=0.0, le=1.0, description="US frames encoded / captured below this: degrade"
    )
    max_loss: float = Field(0.03, ge=0.0, le=1.0, description="RTCP fraction lost above: degrade")
    max_late_ticks_per_s: float = Field(5.0, ge=0.0, description="follower ticks late per second")
    recover_s: float = Field(5.0, gt=0.0, le=300.0, description="all good this long: climb back")
    max_level: int = Field(3, ge=0, le=3)
    min_tracker_ratio: float = Field(
        0.9, ge=0.0, le=1.0,
        description="tracker frames measured / due below this: the video gives way (POV, "
        "then the US rate)",
    )  # fmt: skip
    max_us_level: int = Field(
        2, ge=0, le=2, description="how far the US rate may fall for the tracker: 0.75, 0.5"
    )
    follow_link: bool = Field(
        True,
        description="split the link's budget (the expert's REMB of both tracks) in priority "
        "order: the US first, the POV's level and bit rate from what is left (off at the "
        "least), the US rate only with the POV off (humantele.media.policy.split_budget)",
    )


class FollowerVideoConfig(ConfigModel):
    """The follower's video (``[follower.video]``): the two sources, the counter, recording."""

    enabled: bool = Field(
        False, description="send the us and pov tracks (configs/follower.toml turns it on)"
    )
    us: UltrasoundSourceConfig = SimUltrasoundConfig()
    pov: PovSourceConfig = SimPovConfig()
    stamp_counter: bool | None = Field(
        None,
        description="draw the frame counter (64x32 px, top left) into every frame sent; "
        "unset: into the sim sources' only (a real picture is sent as it came; its latency "
        "comes from the frame records and the RTP timestamps)",
    )

    @model_validator(mode="after")
    def _scanner_geometry(self) -> FollowerVideoConfig:
        """A real scanner's picture says its scale: calipers, the depth scale and the
        OpenIGTLink image need them (the sim's come from its probe model)."""
        us = self.us
        # (a replay gives the recorded scale unless it is set)
        if self.enabled and getattr(us, "backend", "") not in ("sim", "replay"):
            missing = [n for n in ("pixel_spacing_mm", "depth_origin_row")
                       if getattr(us, n, None) is None]  # fmt: skip
            if missing:
                raise ValueError(
                    f"us: a real ultrasound source needs {' and '.join(missing)} (read them "
                    "off the scanner's image at its depth setting: mm per pixel, and the row "
                    "of the skin line)"
                )
        return self

    def stamps(self, track: str) -> bool:
        """Whether ``track``'s frames carry the drawn counter."""
        if self.stamp_counter is not None:
            return self.stamp_counter
        return getattr(getattr(self, track), "backend", "") == "sim"

    degrade: DegradeConfig = DegradeConfig()
    duplicate_repairs: bool = Field(
        False,
        description="on a lossy link (2 % or more of the packets asked for again, or reported "
        "lost), send each retransmission twice, 5 ms apart (humantele.media.pacer): a lost "
        "repair is a freeze; off until a quiet machine shows it pays (docs/video.md, "
        "issue 31's fifth pass)",
    )  # fmt: skip
    fec: bool = Field(
        True,
        description="after each US frame send one parity packet (an XOR of its packets, on "
        "its own SSRC and an unnegotiated payload type: humantele.media.fec) from which the "
        "expert rebuilds one lost packet with no round trip, paid from the US's share of the "
        "link; an expert without it drops them (docs/video.md, issue 31's sixth pass)",
    )
    fec_pov: bool = Field(False, description="with fec: the POV's frames get a parity too")
    fec_group: int = Field(
        8, ge=1, le=48, description="with fec: a parity per this many packets of a frame"
    )
    us_bitrate: UsBitrateConfig = UsBitrateConfig()
    pov_bitrate: PovBitrateConfig = PovBitrateConfig()
    process: bool = Field(
        True, description="render/capture in a separate, lower-priority process (not threads)"
    )
    process_nice: int = Field(
        PRIORITY["video_us"].nice, ge=1, le=19,
        description="the video process's nice increment (its POV thread "
        f"{POV_EXTRA_NICE} more); above [follower] sensing_nice: the video gives way first",
    )  # fmt: skip
    record_us_hz: float = Field(
        3.0, ge=0.0, le=120.0, description="US frames recorded as JPEG per second (0: none)"
    )
    record_pov_hz: float = Field(
        0.5, ge=0.0, le=120.0, description="POV frames recorded as JPEG per second (0: none)"
    )
    jpeg_quality: int = Field(80, ge=10, le=100)


class ExpertVideoConfig(ConfigModel):
    """The expert's video (``[expert.video]``): receive the tracks, with which codec.

    The expert makes the offer, so its codec is the one used (the follower encodes with it).
    Off unless configured (configs/expert.toml turns it on): with video the pose stream's
    budget is not yet shown to hold on a loaded 2-core machine (docs/video.md).
    """

    enabled: bool = Field(
        False, description="receive the us and pov tracks (configs/expert.toml turns it on)"
    )
    codec: Codec = Field("vp8", description="vp8 (default, cheapest on 2 cores) or h264")
    loss_wait_ms: float = Field(
        100.0, ge=0.0, le=2000.0,
        description="a lost packet is waited for this long (its retransmission) before the "
        "frames up to the next keyframe are dropped and a keyframe asked for",
    )  # fmt: skip
    repeat_nacks: bool = Field(
        False,
        description="send each NACK (a request for lost packets) twice, 5 ms apart: a lost "
        "NACK is a repair asked for a round trip late (humantele.media.aiortc_hooks); off "
        "until a quiet machine shows it pays (docs/video.md, issue 31's fifth pass)",
    )
    fec: bool = Field(
        True,
        description="rebuild a lost packet from the follower's parity packets, if it sends "
        "any (humantele.media.fec), and hold a NACK briefly for a packet whose parity may "
        "still come; costs nothing when none come",
    )
    record_frames: bool = Field(True, description="record every received frame's timestamps")
    record_encoded: bool = Field(
        True,
        description="record every received frame, encoded as it arrived (/expert/us_video, "
        "/expert/pov_video; for humantele export), when recording",
    )
