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
