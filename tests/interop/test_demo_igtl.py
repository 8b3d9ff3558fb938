"""``humantele demo --igtl-port PORT``, as the README points to for 3D Slicer: the demo's
follower serves OpenIGTLink there, the demo prints the address, and a pyigtl client gets the
probe (issue 20 item 6)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time

import pyigtl
import pytest

from humantele.cli import build_parser


def test_demo_takes_igtl_port():
    argv = ["demo", "--igtl-port", "18944"]
    assert build_parser(argv).parse_args(argv).igtl_port == 18944
    argv = ["demo", "--igtl-port", "70000"]
    with pytest.raises(SystemExit):
        build_parser(argv).parse_args(argv)


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.whole_session  # one at a time across the lanes (tests/session_slot.py)
def test_demo_serves_openigtlink_on_the_port_given(tmp_path):
    env = dict(os.environ)
    env.pop("HUMANTELE_TOKEN", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "humantele", "demo", "--duration", "60", "--igtl-port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, start_new_session=True,
        cwd=tmp_path, text=True,
    )  # fmt: skip
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    client = None
    try:
        port = None
        t_end = time.monotonic() + 120  # a bound for a loaded machine; it ends at the address
        while port is None and proc.poll() is None and time.monotonic() < t_end:
            for line in list(lines):
                m = re.match(r"OpenIGTLink \(follower, 3D Slicer\): 127\.0\.0\.1:(\d+)", line)
                if m:
                    port = int(m.group(1))
            time.sleep(0.2)
        assert port, f"no OpenIGTLink address printed:\n{''.join(lines)}\n{proc.stderr.read()}"
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        msg = client.wait_for_message("ProbeToWorld", timeout=60)
        assert msg is not None and msg.matrix.shape == (4, 4)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in its terminal
        assert proc.wait(60) == 0, proc.stderr.read()
    finally:
        if client is not None:
            client.stop()
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
