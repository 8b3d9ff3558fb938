"""The servo's CPU wake-up latency request (runtime.cpu_latency): the value the kernel reads,
held while the process lives, and a refusal that is said, not raised."""

import logging
import os
import struct
import subprocess
import sys

import pytest

from humantele.runtime import cpu_latency


def test_the_request_is_written_as_the_kernel_reads_it_and_held(tmp_path):
    devs = [tmp_path / "a", tmp_path / "b"]
    for dev in devs:
        dev.write_bytes(b"")
    try:
        assert cpu_latency.hold_cpu_latency(0, devs[0]) is True
        assert cpu_latency.hold_cpu_latency(25, devs[1]) is True
        # a 32-bit int in the machine's order (PM QoS reads 4 bytes, or a hex string)
        assert [d.read_bytes() for d in devs] == [struct.pack("i", 0), struct.pack("i", 25)]
        held = list(cpu_latency._held)
        assert len(held) == 2 and all(os.fstat(fd) for fd in held)  # still open
    finally:
        cpu_latency.release_cpu_latency()
    assert cpu_latency._held == []


def test_a_refused_request_is_logged_and_the_servo_goes_on(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    assert cpu_latency.hold_cpu_latency(0, tmp_path / "absent" / "cpu_dma_latency") is False
    assert [r.levelname for r in caplog.records] == ["INFO"]  # no such device: said quietly
    denied = tmp_path / "root_only"
    denied.write_bytes(b"")
    denied.chmod(0o400)  # read-only: refused as a device only root may write
    if os.access(denied, os.W_OK):  # root writes anyway: a directory refuses it too
        denied = tmp_path
    assert cpu_latency.hold_cpu_latency(0, denied) is False
    assert caplog.records[-1].levelname == "WARNING"
    assert "CPU wake-up latency request refused" in caplog.text
    assert cpu_latency._held == []


@pytest.mark.e2e  # runs a Python process (the fast lane leaves it out)
def test_the_servo_asks_for_it_unless_told_not_to(tmp_path):
    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "from humantele.runtime import cpu_latency\n"
        "from humantele.haptics import servo_child\n"
        "from humantele.haptics.servo_config import ServoConfig\n"
        "asked = []\n"
        "servo_child.hold_cpu_latency = lambda us: asked.append(us) or True\n"
        "servo_child.try_realtime(ServoConfig(realtime_priority=0))\n"
        "servo_child.try_realtime(ServoConfig(realtime_priority=0, cpu_latency_us=None))\n"
        "servo_child.try_realtime(ServoConfig(realtime_priority=0, cpu_latency_us=50))\n"
        "print(asked)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[0, 50]"
