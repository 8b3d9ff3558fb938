"""A missing capture device: the follower says which and stops at start (exit code 2)."""

import asyncio
import sys

import pytest


@pytest.mark.slow
@pytest.mark.parametrize("process", [True, False])
async def test_missing_capture_device_is_a_clear_error_and_exit_code_2(tmp_path, process):
    config = tmp_path / "follower.toml"
    config.write_text(
        f"""
[follower.link]
signaling_url = "ws://127.0.0.1:9/ws"
[follower.feed]
enabled = false
[follower.video]
enabled = true
process = {str(process).lower()}
[follower.video.us]
backend = "opencv"
device = "/dev/video97"
pixel_spacing_mm = [0.2, 0.2]
depth_origin_row = 30.0
"""
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "humantele", "follower", "--config", str(config),
        "--state-dir", str(tmp_path / "state"), "--duration", "60",
        stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        out, err = await asyncio.wait_for(proc.communicate(), 90)
    finally:
        if proc.returncode is None:  # it hung: leave nothing running behind the test
            proc.kill()
            await proc.wait()
    text = (out + err).decode()
    assert proc.returncode == 2, text
    assert "/dev/video97" in text and "Traceback" not in text


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_the_video_process_killed_or_signalled_never_hangs_the_follower_s_stop(sig):
    """SIGTERM reaches the whole process group (systemd's stop, Ctrl-C's SIGINT likewise): the
    video process ignores it and stops when the follower says so; killed outright, the
    follower's stop still returns (its stop flag waits on nobody; an mp.Event did, forever)."""
    import os
    import signal
    import threading

    from media_helpers import small_video_config

    from humantele.media.sender import VideoSender
    from humantele.video.scene import DEFAULT_PATIENT

    sender = VideoSender(small_video_config(process=True), None, None, DEFAULT_PATIENT)
    sender.open()
    proc = sender.process.shared.process
    os.kill(proc.pid, getattr(signal, sig))
    proc.join(timeout=1.0 if sig == "SIGKILL" else 0.5)
    assert proc.is_alive() == (sig == "SIGTERM")  # SIGTERM is ignored; stopped by close()
    closer = threading.Thread(target=sender.close, daemon=True)
    closer.start()
    closer.join(timeout=30.0)
    assert not closer.is_alive(), "the follower's stop hung on its video process"
    assert not proc.is_alive()
