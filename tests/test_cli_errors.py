"""Errors a user sees: one clear line and a meaningful exit code, never a traceback (issue 9 §4)."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys

import pytest

from humantele.cli import main
from humantele.config import ConfigError
from humantele.demo_plan import recording_paths

CMD = [sys.executable, "-m", "humantele"]


def _env(**kw: str) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("HUMANTELE_TOKEN", None)
    env.update(kw)
    return env


def _one_clear_line(stderr: str) -> None:
    assert "Traceback" not in stderr, stderr


@pytest.mark.parametrize("command", ["demo", "expert", "follower"])
@pytest.mark.parametrize(
    "args, says",
    [
        (["--duration", "nan"], "--duration: 'nan': give a finite number of seconds above 0"),
        (["--duration", "-5"], "--duration: '-5': give a finite number of seconds above 0"),
        (["--duration", "inf"], "give a finite number"),
        (["--duration", "soon"], "'soon' is not a number of seconds"),
        (["--log-level", "NOPE"], "--log-level: 'NOPE': choose one of DEBUG, INFO"),
    ],
)
def test_bad_arguments_are_refused_with_exit_2(capsys, command, args, says):
    with pytest.raises(SystemExit) as exc:
        main([command, *args])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


def test_ports_are_checked_on_the_command_line(capsys):
    for command, flag in (
        ("signal", "--port"),
        ("follower", "--feed-port"),
        ("expert", "--console-port"),
    ):
        with pytest.raises(SystemExit):
            main([command, flag, "70000"])
        assert "70000: a port is 0-65535" in capsys.readouterr().err


def test_record_into_a_directory(tmp_path):
    paths = recording_paths(f"{tmp_path}/")
    assert {p.parent for p in paths.values()} == {tmp_path}
    assert paths["expert"].name.startswith("session-")
    assert paths["expert"].name.endswith(".expert.mcap")
    assert paths["follower"].name.endswith(".follower.mcap")
    assert recording_paths(tmp_path)["expert"].parent == tmp_path  # no trailing slash
    with pytest.raises(ConfigError, match="--record: no directory"):
        recording_paths(f"{tmp_path}/missing/")
    assert recording_paths(tmp_path / "run1")["expert"] == tmp_path / "run1.expert.mcap"


def test_config_with_invalid_utf8_or_deep_nesting_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"[expert]\nservo_restart_s = 2.0 # caf\xe9\n")
    assert main(["expert", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: not UTF-8 text (byte 0xe9" in err and "Traceback" not in err
    bad.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    assert main(["follower", "--config", str(bad)]) == 2
    assert "bad.toml: not valid TOML: nested too deeply" in capsys.readouterr().err


def _busy_port() -> socket.socket:
    s = socket.socket()
    s.bind(("0.0.0.0", 0))
    s.listen()
    return s


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
def test_signal_port_in_use_and_unknown_host():
    with _busy_port() as s:
        port = s.getsockname()[1]
        r = subprocess.run([*CMD, "signal", "--port", str(port)], capture_output=True,
                           text=True, timeout=60, env=_env())  # fmt: skip
    assert r.returncode == 1
    assert f"cannot listen on 127.0.0.1:{port}: the port is in use" in r.stderr
    _one_clear_line(r.stderr)
    r = subprocess.run(
        [*CMD, "signal", "--host", "no-such-host.invalid", "--port", "0", "--insecure"],
        capture_output=True, text=True, timeout=60,
        env=_env(HUMANTELE_TOKEN="a-real-token-of-enough-length-1234"),
    )  # fmt: skip
    assert r.returncode == 1
    assert "cannot listen on no-such-host.invalid:0: cannot resolve the host name" in r.stderr
    _one_clear_line(r.stderr)


@pytest.mark.e2e  # runs the expert daemon's CLI (the fast lane leaves it out)
def test_a_bad_console_key_is_refused_before_the_servo_starts():
    r = subprocess.run([*CMD, "expert", "--duration", "5"], capture_output=True, text=True,
                       timeout=90, env=_env(HUMANTELE_CONSOLE_KEY="short"))  # fmt: skip
    assert r.returncode == 2
    assert "$HUMANTELE_CONSOLE_KEY: at least 16 printable ASCII characters" in r.stderr
    assert "leaked shared_memory" not in r.stderr  # (the servo's, left to the tracker)
    _one_clear_line(r.stderr)


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
def test_follower_feed_port_in_use(tmp_path):
    with _busy_port() as s:
        port = s.getsockname()[1]
        r = subprocess.run(
            [*CMD, "follower", "--feed-port", str(port), "--duration", "5",
             "--state-dir", str(tmp_path)],
            capture_output=True, text=True, timeout=90, env=_env(),
        )  # fmt: skip
    assert r.returncode == 1
    assert f"renderer feed: cannot listen on 0.0.0.0:{port}: the port is in use" in r.stderr
    _one_clear_line(r.stderr)


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
def test_follower_state_dir_that_cannot_hold_the_certificate(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    r = subprocess.run(
        [*CMD, "follower", "--feed-port", "0", "--duration", "5",
         "--state-dir", str(blocker / "state")],
        capture_output=True, text=True, timeout=90, env=_env(),
    )  # fmt: skip
    assert r.returncode == 1
    assert "renderer feed: cannot write" in r.stderr and "check --state-dir" in r.stderr
    _one_clear_line(r.stderr)


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
async def test_a_wrong_token_exits_3_with_the_reason():
    from humantele.signaling.server import SignalConfig, SignalingServer

    server = SignalingServer(SignalConfig(port=0), token="the-right-token-0123456789abcdef")
    await server.start()
    try:
        for role in ("expert", "follower"):
            extra = ["--feed-port", "0", "--state-dir", "/tmp/hard-unused"] * (role == "follower")
            proc = await asyncio.create_subprocess_exec(
                *CMD, role, "--signaling-url", server.url, "--duration", "30", *extra,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                env=_env(HUMANTELE_TOKEN="a-wrong-token-0123456789abcdef"),
            )  # fmt: skip
            out, err = await asyncio.wait_for(proc.communicate(), 60)
            text = err.decode()
            assert proc.returncode == 3, text[-2000:]
            assert f"humantele {role}: refused by the signaling server: unauthorized" in text
            _one_clear_line(text)
            assert "a-wrong-token" not in text + out.decode()  # tokens are never printed
    finally:
        await server.stop()


def test_unwritable_state_dir_saves_best_effort_and_the_model_still_goes(tmp_path):
    from humantele.follower.daemon import FollowerConfig, FollowerDaemon
    from humantele.wire import CalibrationProgress, EllipsoidModel

    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    cfg = FollowerConfig(state_dir=str(blocker / "state"), probe_source="truth")
    d = FollowerDaemon(cfg)

    class Link:
        connected, state = True, "connected"
        counters = type("C", (), {"connections": 1, "sent": {}, "dropped": {}})()
        controls: list = []

        def send_state(self, msg):
            return True

        def send_control(self, msg):
            self.controls.append(msg)
            return True

        def age_of(self, t):
            return 0.01

    d.link = Link()
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    t = 0.0
    while d.calibration is None and t < 20.0:
        d.tick(t)
        t += 0.01
    assert d.calibration is not None and not d.calibrating
    models = [m for m in d.link.controls if isinstance(m, EllipsoidModel)]
    assert len(models) == 1  # installing the model is not best-effort
    assert any(isinstance(m, CalibrationProgress) and m.event == "done" for m in d.link.controls)
    st = d.stats()
    assert st["calibrated"] is True and "Not a directory" in st["calibration_save_error"]
    assert not (blocker / "state").exists()
