"""The link's budget spent in priority order (humantele.media.policy.split_budget and
DegradationPolicy.apply_link): the US first and never below its floor, the POV's level from
what is left (rate, size, bit rate, then off), the US rate only with the POV off; levels drop at
once and come back one step per recover_s; the encoders take their share without reopening."""

from __future__ import annotations

import pytest

from humantele.media.config import BitrateConfig, DegradeConfig
from humantele.media.encoders import make_encoder
from humantele.media.policy import (
    POV_OFF,
    US_RATES,
    DegradationPolicy,
    split_budget,
)

US_MIN, US_MAX, POV_MAX = 500.0, 2500.0, 2000.0


def split(link, pov_level=0, us_level=0):
    return split_budget(link, US_MIN, US_MAX, POV_MAX, pov_level, us_level)


@pytest.mark.parametrize("link", [150, 300, 450, 600, 900, 1500, 2500, 3000, 5000, 9000])
def test_the_us_always_gets_its_floor_and_never_less_than_the_pov(link):
    b = split(link)
    assert b.us_kbps >= b.us_floor_kbps == US_MIN * US_RATES[b.us_level]
    assert b.us_kbps <= US_MAX and b.pov_kbps <= POV_MAX
    assert b.us_kbps >= b.pov_kbps or b.us_kbps == US_MAX
    if US_MIN <= link <= US_MAX + POV_MAX:
        assert b.us_kbps + b.pov_kbps == pytest.approx(link)
        assert b.us_level == 0  # the US rate is untouched while the link carries its floor


def test_the_pov_gives_way_first_rate_then_size_then_bit_rate_then_off():
    levels = [split(link).pov_level for link in (4000, 2100, 1500, 900, 600, 500)]
    assert levels == [0, 0, 1, 2, 3, POV_OFF]  # non-decreasing as the link thins
    assert split(3000).pov_kbps > split(1500).pov_kbps > split(600).pov_kbps > 0


def test_the_us_rate_steps_down_only_with_the_pov_off():
    for link in (450, 300, 100):
        b = split(link)
        assert b.pov_level == POV_OFF and b.us_level > 0
    assert split(450).us_level == 1 and split(200).us_level == 2
    assert split(200).us_kbps == US_MIN * US_RATES[2]  # the US's floor, whatever the link
    assert split(450).us_kbps == 450 and split(450).pov_kbps == 0  # the POV off: all the US's


def test_a_level_comes_back_only_with_a_margin():
    assert split(700).pov_level == 3  # 700 * 1/3 = 233 kbit/s left for the POV: level 3
    assert split(1200, pov_level=3).pov_level == 2  # 400 left: enough for level 2 with margin
    assert split(800).pov_level == 2  # 267 left: level 2 from above
    assert split(800, pov_level=3).pov_level == 3  # but not enough to climb to it


def test_link_levels_drop_at_once_and_climb_one_step_per_recover_s():
    p = DegradationPolicy(DegradeConfig(recover_s=5.0))
    assert p.apply_link(0.0, split(400)) and p.pov_off and p.us_rate_level == 1
    assert p.pov_scale == 0.5 and p.us_rate_factor == 0.75
    assert not p.apply_link(1.0, split(5000))  # a good second is not enough
    assert p.apply_link(5.0, split(5000)) and p.us_rate_level == 0 and p.pov_off  # US first
    assert p.apply_link(10.0, split(5000)) and p.pov_level == POV_OFF - 1
    for t in (15.0, 20.0, 25.0, 30.0):
        p.apply_link(t, split(5000))
    assert p.pov_level == 0 and p.link_changes == 6


def test_the_stepped_level_and_the_links_the_lower_picture_wins():
    p = DegradationPolicy()
    p.level = 2  # CPU contention stepped the POV down
    p.apply_link(0.0, split(1500))  # the link alone allows level 1
    assert p.pov_level == 2 and p.pov_scale == 0.5


def test_an_estimate_that_has_not_grown_yet_lowers_nothing_but_lets_levels_climb():
    p = DegradationPolicy(DegradeConfig(recover_s=5.0))
    assert not p.apply_link(0.0, split(300), short=False)  # a session's first REMB
    assert p.pov_level == 0 and p.us_rate_level == 0
    p.apply_link(1.0, split(300))  # the link really is short
    assert p.pov_off
    assert p.apply_link(6.0, split(5000), short=False) and p.us_rate_level == 1  # one step


def test_disabled_degradation_ignores_the_link():
    p = DegradationPolicy(DegradeConfig(enabled=False))
    assert not p.apply_link(0.0, split(100)) and p.pov_level == 0


def test_an_encoder_takes_its_share_and_floor_without_reopening():
    enc = make_encoder("video/VP8", BitrateConfig(start_kbps=1000, min_kbps=500, max_kbps=2500))
    enc.target_bitrate = 2_000_000  # REMB
    enc.set_budget(1_200_000)  # the link's share is less: the share
    assert enc.target_bitrate == 1_200_000 and enc.remb == 2_000_000
    enc.set_budget(100_000, floor=250_000)  # below the floor of a halved US rate: the floor
    assert enc.target_bitrate == 250_000
    enc.set_budget(None)  # no budget: REMB within the configured limits again
    assert enc.target_bitrate == 2_000_000
    enc.target_bitrate = 10  # REMB nonsense: never below the floor
    assert enc.target_bitrate == 500_000


class _Report:
    def __init__(self, **kw):
        self.__dict__.update({"type": "remote-inbound-rtp", **kw})


class _Sender:
    """An RTCRtpSender's getStats as aiortc gives it: the expert's receiver report."""

    def __init__(self, lost: int, rtt: float, jitter: int) -> None:
        self.report = {"r": _Report(fractionLost=lost, roundTripTime=rtt, jitter=jitter),
                       "o": _Report(type="outbound-rtp", bytesSent=0)}  # fmt: skip

    def send(self, kbps: float, seconds: float) -> None:
        self.report["o"].bytesSent += int(kbps * 1000 / 8 * seconds)

    async def getStats(self):  # noqa: N802 - aiortc's name
        return self.report


def _video_sender(config, us: tuple[int, float, int], pov: tuple[int, float, int]):
    """A VideoSender (no encoder process) whose two tracks' senders give the receiver reports
    ``us`` and ``pov`` ((fraction lost /256, round trip s, jitter in RTP ticks)) and whose
    encoders are VP8 at the config's bit rates, as after a connection."""
    from humantele.media.sender import VideoSender
    from humantele.video.scene import DEFAULT_PATIENT

    sender = VideoSender(config, None, None, DEFAULT_PATIENT)
    sender._senders = {"us": _Sender(*us), "pov": _Sender(*pov)}
    sender._encoders = {"us": make_encoder("video/VP8", config.us_bitrate),
                        "pov": make_encoder("video/VP8", config.pov_bitrate)}  # fmt: skip
    return sender


async def test_the_senders_check_reads_the_link_and_spends_it():
    """What the follower does once a second: the REMB sum, the receiver reports' loss, round
    trip and jitter; the POV off and the US at its floor on a 450 kbit/s link; the encoders
    told their shares and the round trip; all in the stats."""
    from media_helpers import small_video_config

    sender = _video_sender(small_video_config(process=False), (5, 0.12, 900), (13, 0.15, 450))
    sender._encoders["us"].target_bitrate = 300_000  # the expert's REMB of each track
    assert (await sender.link_report())["link_kbps"] is None  # the POV's REMB not yet in
    sender._encoders["pov"].target_bitrate = 150_000
    report = await sender.link_report()
    assert report == {"loss": 13 / 256, "rtt_s": 0.15, "jitter_s": 0.01, "link_kbps": 450.0,
                      "bytes_sent": 0}  # fmt: skip
    await sender.check(9.0, 0.0, None)
    sender._senders["us"].send(500, 1.0)  # the tracks sent 800 kbit/s: the estimate is short
    sender._senders["pov"].send(300, 1.0)
    await sender.check(10.0, 0.0, None)
    p = sender.policy
    assert p.pov_off and p.us_rate_level == 1  # 450 < the US's 500 floor: the US rate too
    us, pov = sender._encoders["us"], sender._encoders["pov"]
    assert us.target_bitrate == 375_000  # REMB 300 is below its floor at x0.75: the floor
    us.target_bitrate = 420_000  # a REMB within its share (the whole link, the POV off)
    assert us.target_bitrate == 420_000
    us.target_bitrate = 900_000  # and one above it: the share
    assert us.target_bitrate == 450_000
    assert pov.target_bitrate == 50_000 and us.rtt_s == pov.rtt_s == 0.15
    assert sender.captures["pov"].max_fps == pytest.approx(0.2)
    assert sender.captures["us"].max_fps == pytest.approx(0.75 * sender.us_fps)
    st = sender.stats()
    assert st["pov_level"] == POV_OFF and st["us_level"] == 1 and st["link"]["link_kbps"] == 450


async def test_an_estimate_above_what_the_tracks_sent_is_not_a_short_link():
    """A starved capture sends less than its target and the expert's estimate follows what it
    receives: that is not the link (a session's start on a loaded machine)."""
    from media_helpers import small_video_config

    config = small_video_config(process=False).model_copy(
        update={"degrade": DegradeConfig(max_loss=0.5)}
    )
    sender = _video_sender(config, (0, 0.01, 90), (0, 0.01, 90))
    sender._encoders["us"].target_bitrate = 300_000
    sender._encoders["pov"].target_bitrate = 150_000
    for t in (1.0, 2.0, 3.0):
        sender._senders["us"].send(250, 1.0)  # 400 kbit/s sent, the estimate 450
        sender._senders["pov"].send(150, 1.0)
        await sender.check(t, 0.0, None)
    assert sender.policy.pov_level == 0 and sender.policy.us_rate_level == 0
    # 15 % random loss: 500 sent, 425 arrive, the estimate 450: not short either
    for name in ("us", "pov"):
        sender._senders[name].report["r"].fractionLost = 38  # /256
    sender._senders["us"].send(350, 1.0)
    sender._senders["pov"].send(150, 1.0)
    await sender.check(4.0, 0.0, None)
    assert sender.policy.link_level == 0 and sender.policy.link_us_level == 0


def test_a_stale_estimate_is_no_bound_until_it_catches_up_or_falls_with_what_got_through():
    from humantele.media.sender import link_estimate

    # aiortc's estimate started from a dark US (~40 kbit/s) and climbs 8 % a second, while
    # 600 kbit/s got through: stale, the link is what got through
    assert link_estimate(145.0, None, 600.0, False) == (600.0, True)
    assert link_estimate(400.0, 370.0, 600.0, True) == (600.0, True)  # still climbing
    assert link_estimate(580.0, 540.0, 600.0, True) == (580.0, False)  # caught up
    # a fresh overuse: it fell, to 0.85 of what it received: the link is short, trust it
    assert link_estimate(510.0, 900.0, 600.0, True) == (510.0, False)
    assert link_estimate(510.0, 480.0, 600.0, False) == (510.0, False)  # and stays trusted
    assert link_estimate(100.0, 900.0, 600.0, False) == (600.0, True)  # far below: stale
    assert link_estimate(450.0, None, None, True) == (450.0, False)  # nothing measured yet


async def test_an_estimate_that_started_from_a_dark_picture_does_not_turn_the_video_down():
    """Measured at 15 % loss (and at the rural link): the expert's REMB of the US started at
    ~40 kbit/s (the probe not yet on the patient) and climbed 8 % a second, the POV's at ~105,
    while 630 kbit/s got through: spent as the link it halved the US frame rate and turned
    the POV off for the whole scan. A real overuse later still lowers the levels."""
    from media_helpers import small_video_config

    sender = _video_sender(small_video_config(process=False), (7, 0.01, 900), (7, 0.01, 450))
    us, pov = sender._encoders["us"], sender._encoders["pov"]
    remb = {"us": 40.0, "pov": 105.0}
    for t in range(1, 16):  # the sum climbs from 145 to 425 kbit/s
        us.target_bitrate = int(remb["us"] * 1000)
        pov.target_bitrate = int(remb["pov"] * 1000)
        sender._senders["us"].send(500, 1.0)  # the US at its floor, the POV at its level's
        sender._senders["pov"].send(130, 1.0)
        await sender.check(float(t), 0.0, None)
        remb = {k: v * 1.08 for k, v in remb.items()}
    p = sender.policy
    assert p.us_rate_level == 0 and not p.pov_off and sender.remb_stale
    assert us.target_bitrate == 500_000 and sender.captures["us"].max_fps is None
    # a real overuse: the estimate falls to 0.85 of what it receives, well below the floors
    us.target_bitrate, pov.target_bitrate = 300_000, 100_000
    sender._senders["us"].send(500, 1.0)
    sender._senders["pov"].send(130, 1.0)
    await sender.check(16.0, 0.0, None)
    assert not sender.remb_stale and p.pov_off and p.us_rate_level == 1


async def test_an_overuse_while_the_tracks_send_little_lowers_nothing():
    """Measured at 15 % loss: with the US dark (~15 kbit/s sent of the 1000 asked) aiortc's
    estimator saw an overuse and set the US estimate to 10 kbit/s. What the tracks send far
    below what their encoders were asked for measures nothing of the link: no level falls,
    no encoder is capped; once they send, a real overuse does lower the levels."""
    from media_helpers import small_video_config

    sender = _video_sender(small_video_config(process=False), (0, 0.01, 900), (0, 0.01, 450))
    config = sender.config
    us, pov = sender._encoders["us"], sender._encoders["pov"]
    for t, remb in ((1.0, (20, 70)), (2.0, (22, 75)), (3.0, (10, 60)), (4.0, (11, 62))):
        us.target_bitrate, pov.target_bitrate = remb[0] * 1000, remb[1] * 1000
        sender._senders["us"].send(15, 1.0)  # dark: a few kbit/s, whatever it is asked
        sender._senders["pov"].send(70, 1.0)
        await sender.check(t, 0.0, None)
        assert not sender.link_trusted
    p = sender.policy
    assert p.pov_level == 0 and p.us_rate_level == 0
    assert us.target_bitrate == config.us_bitrate.min_kbps * 1000  # its floor, not 10
    pov.target_bitrate = 4_420_000  # and an estimate as wrong upwards (measured, 1.5 Mbit/s
    assert pov.target_bitrate == config.pov_bitrate.start_kbps * 1000  # link): its start
    pov.target_bitrate = 62_000
    for t in (5.0, 6.0):  # the picture comes: the tracks send what they are asked
        sender._senders["us"].send(us.target_bitrate / 1000, 1.0)
        sender._senders["pov"].send(pov.target_bitrate / 1000, 1.0)
        us.target_bitrate, pov.target_bitrate = 300_000, 80_000  # and the link is short
        await sender.check(t, 0.0, None)
    assert sender.link_trusted and p.pov_off and p.us_rate_level == 1


async def _us_share(parity, link_kbps: int) -> int:
    """The US encoder's target (bit/s) once the follower has spent a measured ``link_kbps``
    link (both tracks sending what they are allowed) with ``parity`` (a ParityEncoder or
    None) on its US."""
    from media_helpers import small_video_config

    sender = _video_sender(small_video_config(process=False), (0, 0.1, 90), (0, 0.1, 90))
    sender.parity = parity
    sender._encoders["us"].target_bitrate = link_kbps * 500  # each track's REMB: half
    sender._encoders["pov"].target_bitrate = link_kbps * 500
    for t in (9.0, 10.0):
        sender._senders["us"].send(link_kbps // 2, 1.0)  # the tracks send it all
        sender._senders["pov"].send(link_kbps // 2, 1.0)
        await sender.check(t, 0.0, None)
    assert sender.link_trusted
    sender._encoders["us"].target_bitrate = 10_000_000  # a REMB above its share: the share
    return sender._encoders["us"].target_bitrate


async def test_with_parity_the_us_share_leaves_room_for_it():
    """The parity (config fec) is not in the expert's estimate (of the media streams): the
    US's share pays for it, at the start share until enough is protected, then at the
    measured one; never below the US's floor."""
    from media_helpers import small_video_config

    from humantele.media.fec import ParityEncoder
    from humantele.media.sender import PARITY_SHARE_MIN_BYTES, PARITY_SHARE_START

    bare = await _us_share(None, 3000)
    parity = ParityEncoder(lambda ssrc: True)
    assert await _us_share(parity, 3000) == pytest.approx(bare / (1 + PARITY_SHARE_START), abs=2)
    parity.counters.protected_bytes = PARITY_SHARE_MIN_BYTES
    parity.counters.parity_bytes = PARITY_SHARE_MIN_BYTES // 10  # measured: a tenth
    assert await _us_share(parity, 3000) == pytest.approx(bare / 1.1, abs=2)
    # 400 kbit/s: the POV off, the US at x0.75 with all of it; with the parity, its floor
    assert await _us_share(None, 400) == 400_000
    floor = 0.75 * small_video_config(process=False).us_bitrate.min_kbps  # 375 > 400 / 1.1
    assert await _us_share(parity, 400) == 1000 * floor
