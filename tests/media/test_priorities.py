"""Priorities by what matters (issue 19 §2): servo > pose stream > tracker > force > US video >
POV video, in every mechanism: the degradation policy's decisions under a simulated CPU
shortage, the configurations' order, and the nice values of the spawned children as the
system has them."""

import asyncio
import os
from pathlib import Path

import pytest

from humantele.follower.config import FollowerConfig
from humantele.haptics.servo_config import ServoConfig
from humantele.media.config import DegradeConfig, FollowerVideoConfig
from humantele.media.policy import DegradationPolicy, Health
from humantele.runtime.child import PRIORITY, child_priority
from humantele.transport import LinkConfig
from sched_privilege import fifo_allowed
from waits import until

GOOD = Health(us_delivery=1.0, loss=0.0, late_ticks_per_s=0.0, tracker_ratio=1.0)
CPU_SHORT = Health(us_delivery=1.0, loss=0.0, late_ticks_per_s=0.0, tracker_ratio=0.6)


def test_under_a_cpu_shortage_the_pov_gives_way_first_then_the_us_rate_never_the_tracker():
    p = DegradationPolicy(DegradeConfig(recover_s=5.0))
    seen = []
    for t in range(8):  # the tracker measures 60 % of its frames, check after check
        p.update(float(t), CPU_SHORT)
        seen.append((p.level, p.us_level))
    # The POV steps down to its lowest first; only then the US rate, down to its floor.
    assert seen == [(1, 0), (2, 0), (3, 0), (3, 1), (3, 2), (3, 2), (3, 2), (3, 2)]
    assert (p.pov_scale, p.pov_rate_factor, p.us_rate_factor) == (0.5, 0.25, 0.5)
    assert "tracker at 60 %" in p.reason
    # Recovery: the US comes back first, then the POV, one level per recover_s.
    back = []
    for t in range(8, 40):
        p.update(float(t), GOOD)
        if not back or back[-1] != (p.level, p.us_level):
            back.append((p.level, p.us_level))
    assert back == [(3, 2), (3, 1), (3, 0), (2, 0), (1, 0), (0, 0)]


def test_the_video_s_own_troubles_never_lower_the_us_rate():
    p = DegradationPolicy(DegradeConfig())
    for t in range(10):  # the US encoder behind, loss, a late loop: the POV alone gives way
        p.update(float(t), Health(0.2, 0.2, 50.0, tracker_ratio=1.0))
    assert p.level == 3 and p.us_level == 0 and p.us_rate_factor == 1.0
    # No tracker figure (the sensing process restarting measures nothing): not contention.
    assert Health(1.0, 0.0, 0.0, tracker_ratio=None).problems(DegradeConfig()) == []


def test_the_configured_order_servo_loop_sensing_video():
    servo, loop = ServoConfig().realtime_priority, LinkConfig().realtime_priority
    f = FollowerConfig()
    assert servo == PRIORITY["servo"].fifo > loop == PRIORITY["loop"].fifo > 0
    assert f.sensing_nice == PRIORITY["sensing"].nice
    # the tracker at SCHED_FIFO below the loops: above every normal process (the video, a
    # browser on the same machine), preempted by the pose stream and the servo
    assert loop > f.sensing_realtime_priority == PRIORITY["sensing"].fifo > 0
    assert f.sensing_priority == PRIORITY["sensing"]
    # never at or above the loop's: none with the loop at the normal policy, below a low one
    assert FollowerConfig(link=LinkConfig(realtime_priority=0)).sensing_priority.fifo == 0
    assert FollowerConfig(link=LinkConfig(realtime_priority=3)).sensing_priority.fifo == 2
    assert f.video.process_nice == PRIORITY["video_us"].nice
    assert 0 <= f.sensing_nice < f.video.process_nice < PRIORITY["video_pov"].nice


def test_a_sensing_process_below_the_video_is_refused_at_load_with_the_field_names():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="sensing_nice = 7 must be below"):
        FollowerConfig(sensing_nice=7, video=FollowerVideoConfig(process_nice=5))
    FollowerConfig(sensing_nice=7, sensing_worker="thread")  # no sensing process: no order
    with pytest.raises(ValidationError, match="sensing_realtime_priority"):
        FollowerConfig(sensing_realtime_priority=LinkConfig().realtime_priority)  # = the loops


def _thread_nices(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with_comm = (task / "stat").read_text().rsplit(")", 1)[1].split()
        out.append(int(with_comm[16]))  # field 19 of stat: nice
    return out


@pytest.mark.e2e
@pytest.mark.slow
async def test_the_spawned_children_run_in_that_order(tmp_path):
    """The sensing process and the video process as the follower spawns them, their
    scheduling read back from /proc: the sensing at SCHED_FIFO where the system allows it
    (else below the daemon at its nice), the video below the sensing at the normal policy,
    the video's POV thread below its US thread."""
    from media_helpers import small_video_config

    from humantele.follower.sensing_process import SensingProcess
    from humantele.media.sender import VideoSender
    from humantele.video.scene import DEFAULT_PATIENT

    base = os.getpriority(os.PRIO_PROCESS, 0)
    config = FollowerConfig(state_dir=str(tmp_path))
    sensing = SensingProcess(config, None, lambda *a: None, priority=config.sensing_priority)
    video = VideoSender(small_video_config(process=True), None, None, DEFAULT_PATIENT)
    try:
        sensing.start()
        await asyncio.to_thread(video.open)
        assert await sensing.wait_ready(180.0)
        video.start(asyncio.get_running_loop())
        vpid = video.process.pid
        nice_s = base + config.sensing_nice
        nice_us = base + video.config.process_nice
        fifo = fifo_allowed()
        want = ("fifo", base) if fifo else ("other", nice_s)
        await until(lambda: child_priority(sensing.pid) == want, 120.0)
        if fifo:
            param = os.sched_getparam(sensing.pid).sched_priority
            assert param == config.sensing_realtime_priority
        assert child_priority(vpid) == ("other", nice_us)
        await until(lambda: base + PRIORITY["video_pov"].nice in _thread_nices(vpid), 120.0)
        nices = set(_thread_nices(vpid))
        assert nice_us in nices  # the US capture thread (and the process's own)
        assert base < nice_s < nice_us < base + PRIORITY["video_pov"].nice
    finally:
        sensing.close()
        await asyncio.to_thread(video.close)


async def test_the_window_the_tracker_starts_measuring_in_is_not_contention():
    """The sender's once-a-second check gets the tracker's ratio only once the tracker has
    measured through a whole window: the window its sensing process came up in (half its
    frames, say) must not lower the POV."""
    from media_helpers import small_video_config

    from humantele.media.sender import VideoSender
    from humantele.video.scene import DEFAULT_PATIENT

    sender = VideoSender(small_video_config(process=False), None, None, DEFAULT_PATIENT)
    ratios = []

    async def check(t, late, ratio=None):
        ratios.append(ratio)
        return 0

    sender.check = check
    counts = [0, 0, 20, 65, 110, 130]  # measured so far, once a second at 45 Hz
    for t, n in enumerate(counts):
        sender.tick(float(t), 0, n, 45.0)
        await asyncio.sleep(0)
    # t=0 the first; t=1 nothing measured; t=2 it starts (20): no ratio; then full, then short
    assert ratios[:3] == [None, None, None]
    assert ratios[3] == pytest.approx(1.0) and ratios[5] == pytest.approx(20 / 45)
