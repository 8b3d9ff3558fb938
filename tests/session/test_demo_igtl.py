"""``humantele demo --igtl-port PORT``, as the README points to for 3D Slicer: the demo's
follower serves OpenIGTLink there, the demo prints the address, and a pyigtl client gets the
probe (issue 20 item 6). The demo is the shared run (session_helpers.demo_run, started with
``--igtl-port 0``; its client: session_helpers.IgtlClient)."""

from __future__ import annotations

import pytest

from humantele.cli import build_parser


def test_demo_takes_igtl_port():
    argv = ["demo", "--igtl-port", "18944"]
    assert build_parser(argv).parse_args(argv).igtl_port == 18944
    argv = ["demo", "--igtl-port", "70000"]
    with pytest.raises(SystemExit):
        build_parser(argv).parse_args(argv)


@pytest.mark.slow
def test_demo_serves_openigtlink_on_the_port_given(demo_run):
    igtl = demo_run.igtl
    assert igtl["port"], f"no OpenIGTLink address printed:\n{demo_run.err[-3000:]}"
    assert igtl["error"] is None, igtl["error"]
    assert igtl["shape"] == (4, 4), igtl  # the probe's ProbeToWorld transform came
    assert demo_run.returncode == 0, demo_run.err[-3000:]  # Ctrl-C in its terminal
