"""The recorder: round trip, bad samples, errors at start and during a session, overflow."""

from __future__ import annotations

import errno
import io
import os
import time

import numpy as np
import pytest

from humantele.recording import (
    CHANNELS,
    Recorder,
    RecorderConfig,
    RecordingError,
    RecordingReadError,
    check_participant_id,
    read_recording,
    role_path,
)
from humantele.recording.schemas import json_schema


def _pose(i: int) -> dict:
    return {"position": np.array([i * 1e-3, 0.1, -0.2]), "quaternion": (0.0, 0.0, 0.0, 1.0)}


def test_round_trip_keeps_values_ids_and_packs_high_rate_samples(tmp_path):
    path = tmp_path / "s.mcap"
    with Recorder(path, "demo", session_id="abc", follower_id="F03", sonographer_id="S1") as rec:
        rec.scan_start(0.0, 4)
        for i in range(1500):
            rec.write("/expert/pose", i * 1e-3, _pose(i))
        rec.write("/follower/probe_pose", 0.5, {**_pose(7), "tracked": False})
        rec.write("/follower/clock_sync", 0.6, {"offset_s": 0.25, "rtt_s": 0.01})
        rec.scan_stop(1.5, 4)
    stats = rec.stats
    assert stats.written == 1504 and stats.dropped_invalid == 0 and stats.error is None
    r = read_recording(path)
    assert r.complete and r.problem is None
    assert r.session["follower_id"] == "F03" and r.session["sonographer_id"] == "S1"
    assert r.session["session_id"] == "abc" and r.session["role"] == "demo"
    # the daemons' clock (monotonic) to Unix time, for tools that show dates (the export)
    unix_now = time.monotonic() + float(r.session["clock_unix_offset_s"])
    assert abs(unix_now - time.time()) < 1.0
    t = r.times("/expert/pose")
    np.testing.assert_allclose(t, np.arange(1500) * 1e-3, atol=1e-6)
    pos = np.array(r.column("/expert/pose", "position").tolist())
    np.testing.assert_allclose(pos[:, 0], np.arange(1500) * 1e-3, atol=1e-7)
    probe = r.samples("/follower/probe_pose")[0]
    assert probe["tracked"] is False and probe["t"] == 0.5
    scan = r.samples("/expert/scan")
    assert [s["event"] for s in scan] == ["start", "stop"] and scan[0]["follower_id"] == "F03"
    assert r.samples("/follower/clock_sync")[0]["offset_s"] == 0.25


def test_bad_samples_are_dropped_and_counted_the_rest_kept(tmp_path):
    path = tmp_path / "bad.mcap"
    rec = Recorder(path, "expert")
    assert rec.write("/expert/pose", 0.0, _pose(0))
    rec.write("/expert/pose", 0.001, {"position": [np.nan, 0, 0], "quaternion": [0, 0, 0, 1]})
    rec.write("/expert/pose", 0.002, {"position": [0, 0], "quaternion": [0, 0, 0, 1]})
    rec.write("/expert/pose", 0.003, {"position": [0, 0, 0]})  # quaternion missing
    rec.write("/expert/pose", 0.004, {**_pose(1), "colour": "red"})  # unknown field
    rec.write("/expert/pose", 0.005, {"position": [0, 0, 0], "quaternion": [0, 0, 0, 0]})
    rec.write("/expert/scan", 0.006, {"event": "pause", "scan": 1})  # not an enum value
    rec.write("/no/such/topic", 0.007, {})
    rec.write("/expert/pose", float("inf"), _pose(2))
    rec.write("/expert/pose", 0.009, _pose(3))
    stats = rec.close()
    assert stats.dropped_invalid == 8 and stats.written == 2
    r = read_recording(path)
    np.testing.assert_allclose(r.times("/expert/pose"), [0.0, 0.009])


def test_every_channel_has_a_valid_looking_json_schema():
    for spec in CHANNELS.values():
        schema = json_schema(spec)
        assert schema["type"] == "object"
        assert "t" in schema["required"] and set(spec.required) <= set(schema["properties"])
        if spec.batch:  # columnar: every field is an array of per-sample values
            assert all(p["type"] == "array" for p in schema["properties"].values())


def test_participant_ids_must_be_pseudonyms(tmp_path):
    for ok in ("F03", "S1", "P-12", "fol_7"):
        assert check_participant_id(ok) == ok
    for bad in ("John Smith", "jane@example.org", "Alice", "", "F03; DROP", "12345678"):
        with pytest.raises(ValueError, match="pseudonymous"):
            check_participant_id(bad)
    with pytest.raises(ValueError, match="follower_id"):
        Recorder(tmp_path / "x.mcap", "expert", follower_id="Mary Jones")
    rec = Recorder(tmp_path / "y.mcap", "expert", follower_id="F1")
    with pytest.raises(ValueError):
        rec.scan_start(0.0, 1, follower_id="mary@clinic.ca")
    rec.close()


def test_unusable_paths_fail_at_start_with_a_clear_error(tmp_path):
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"precious data")
    with pytest.raises(RecordingError, match="exists"):
        Recorder(existing, "expert")
    assert existing.read_bytes() == b"precious data"
    with pytest.raises(RecordingError, match="no directory"):
        Recorder(tmp_path / "missing" / "a.mcap", "expert")
    with pytest.raises(RecordingError, match="min_free_mb"):
        Recorder(tmp_path / "b.mcap", "expert", config=RecorderConfig(min_free_mb=1e15))
    with pytest.raises(ValueError, match="role"):
        Recorder(tmp_path / "c.mcap", "patient")


def test_full_disk_at_start_is_a_clear_error():
    with open("/dev/full", "wb", buffering=0) as full, pytest.raises(RecordingError, match="space"):
        Recorder(full, "expert")


class _FailingStream(io.BytesIO):
    """A file that fills up after ``limit`` bytes (ENOSPC), like a full disk."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit = limit

    def write(self, b) -> int:
        if self.tell() + len(b) > self.limit:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)

    def fileno(self) -> int:
        raise io.UnsupportedOperation("no fileno")


def test_disk_full_during_session_is_reported_never_raised():
    stream = _FailingStream(limit=20_000)
    rec = Recorder(stream, "expert", config=RecorderConfig(flush_interval_s=0.01))
    total = accepted = 0
    for _batch in range(200):  # the caller keeps going whatever happens
        for _ in range(200):
            accepted += rec.write("/expert/pose", total * 1e-3, _pose(total))
            total += 1
        flushes = rec.stats.flushes
        deadline = time.monotonic() + 5.0
        while rec.stats.flushes == flushes and not rec.failed and time.monotonic() < deadline:
            time.sleep(0.005)  # let the writer thread flush this batch
        if rec.failed:
            break
    for _ in range(100):
        accepted += rec.write("/expert/pose", total * 1e-3, _pose(total))
        total += 1
    stats = rec.close()
    assert rec.failed and "No space" in (stats.error or "")
    assert accepted <= total - 100  # refused once failed
    assert stats.written + stats.dropped_failed == total
    assert 0 < stats.written < total  # what was flushed before the disk filled


def test_overflow_is_counted_and_never_blocks(tmp_path):
    rec = Recorder(tmp_path / "o.mcap", "expert", config=RecorderConfig(queue_size=100))
    accepted = sum(rec.write("/expert/pose", i * 1e-3, _pose(i)) for i in range(5000))
    stats = rec.close()
    assert stats.dropped_overflow > 0
    assert accepted + stats.dropped_overflow == 5000
    assert len(read_recording(tmp_path / "o.mcap").samples("/expert/pose")) == accepted


def test_reader_refuses_a_file_that_is_not_a_recording(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(os.urandom(100))
    with pytest.raises(RecordingReadError, match="not an MCAP"):
        read_recording(junk)
    with pytest.raises(RecordingReadError, match="cannot read"):
        read_recording(tmp_path / "none.mcap")


def test_role_paths_split_one_session_name_per_daemon(tmp_path):
    assert role_path(tmp_path / "demo.mcap", "expert") == tmp_path / "demo.expert.mcap"
    assert role_path("runs/s1", "follower").name == "s1.follower.mcap"
