"""The pages' configuration refuses at load what cannot work (issue 20 item 5): feed paths
with ``..`` or ``//``, certificate host names with a space, a NUL or 300 characters, an
empty or unusable captures directory; each refusal names the field."""

from __future__ import annotations

import pytest

from humantele.config import ConfigError, load_config
from humantele.follower.daemon import FollowerConfig


def _follower(tmp_path, text: str) -> FollowerConfig:
    f = tmp_path / "f.toml"
    f.write_text(text)
    return load_config(FollowerConfig, f, "follower")


@pytest.mark.parametrize("path", ["/..", "//", "/feed/..", "/feed//x", "/.", "/a/./b", "/", ""])
def test_feed_paths_with_dot_segments_or_empty_ones_are_refused(tmp_path, path):
    with pytest.raises(ConfigError, match=r"\[follower\]: feed\.path: "):
        _follower(tmp_path, f'[follower.feed]\npath = "{path}"\n')


def test_good_feed_paths_load(tmp_path):
    for path in ("/feed", "/a/b_c/d-1", "/v1.2/feed"):
        assert _follower(tmp_path, f'[follower.feed]\npath = "{path}"\n').feed.path == path


@pytest.mark.parametrize(
    "host, why",
    [
        ('"scanner pc"', "characters a certificate cannot name"),
        ('"a\\u0000b"', "characters a certificate cannot name"),
        ('"' + "a" * 300 + '"', "300 characters"),
    ],
)
def test_certificate_host_names_are_checked_at_load(tmp_path, host, why):
    with pytest.raises(ConfigError, match=rf"\[follower\]: feed\.hosts\.0: .*{why}"):
        _follower(tmp_path, f"[follower.feed]\nhosts = [{host}]\n")
    ok = _follower(tmp_path, '[follower.feed]\nhosts = ["scanner.clinic.example", "10.0.0.9"]\n')
    assert ok.feed.hosts == ["scanner.clinic.example", "10.0.0.9"]


def _expert(tmp_path, text: str):
    from humantele.expert.config import ExpertConfig

    f = tmp_path / "e.toml"
    f.write_text(text)
    return load_config(ExpertConfig, f, "expert")


def test_an_empty_or_impossible_captures_dir_is_refused_at_load(tmp_path):
    for value in ('""', '"  "'):
        with pytest.raises(ConfigError, match=r"\[expert\]: console\.captures_dir: empty"):
            _expert(tmp_path, f"[expert.console]\ncaptures_dir = {value}\n")
    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    for value in (a_file, a_file / "captures"):
        with pytest.raises(ConfigError, match=r"console\.captures_dir: .*is a file"):
            _expert(tmp_path, f'[expert.console]\ncaptures_dir = "{value}"\n')
    with pytest.raises(ConfigError, match=r"console\.captures_dir: "):
        _expert(tmp_path, f'[expert.console]\ncaptures_dir = "{tmp_path}/{"c" * 5000}"\n')
    ok = _expert(tmp_path, f'[expert.console]\ncaptures_dir = "{tmp_path}/new/captures"\n')
    assert ok.console.captures_dir.endswith("new/captures")


async def test_an_unwritable_captures_dir_is_said_at_start_naming_the_field(tmp_path, caplog):
    from humantele.config import directory_problem
    from humantele.expert.console import ConsoleConfig, ConsoleServer

    assert directory_problem(tmp_path / "fine") is None and (tmp_path / "fine").is_dir()
    unwritable = "/proc/humantele-captures"  # not even root can make a directory there
    assert directory_problem(unwritable)

    class Session:
        recorder = None

        def snapshot(self) -> dict:
            return {"link": {}, "scan": None, "force": {}, "alignment": {}}

    server = ConsoleServer(ConsoleConfig(port=0, captures_dir=unwritable), None, Session())
    await server.start()
    try:
        assert "[expert.console] captures_dir '/proc/humantele-captures'" in caplog.text
        assert "captures will be refused" in caplog.text
    finally:
        await server.stop()
