"""Captures on a full disk (issue 34 §4): written whole or not at all, the JSON names a clip
only once it is there whole, the refusals said once, and nothing held per failed clip.

The disk is made full for a child process by a file size limit (RLIMIT_FSIZE, no root
needed: a write past it fails, EFBIG, as one on a full disk does, ENOSPC), or by an
OSError(ENOSPC) injected at the write seam."""

import errno
import json
import logging
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from humantele.expert.console import captures
from humantele.expert.console.captures import FailureLog, name_clip, save_capture

LIMITED = textwrap.dedent(
    """
    import json, os, resource, signal, sys
    from pathlib import Path
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, EFBIG
    import cv2, numpy as np
    from humantele.expert.console.captures import save_capture
    from humantele.export.clip import write_clip
    out, limit = Path(sys.argv[1]), int(sys.argv[2])
    rng = np.random.default_rng(1)
    jpegs = [cv2.imencode(".jpg", rng.integers(0, 255, (240, 320, 3), np.uint8))[1].tobytes()
             for _ in range(12)]
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    fds = len(os.listdir("/proc/self/fd"))
    errors = []
    for i in range(8):
        try:
            save_capture(out, i, jpegs[0] * 2, {"seq": i})
        except OSError as exc:
            errors.append(exc.errno)
        try:
            write_clip([(k / 20, j) for k, j in enumerate(jpegs)], out / f"clip-{i}.mp4")
        except OSError as exc:
            errors.append(exc.errno)
    print(json.dumps({"errors": errors, "fds_grew": len(os.listdir("/proc/self/fd")) - fds,
                      "jpeg": len(jpegs[0])}))
    """
)


@pytest.mark.e2e  # runs a Python process with a file-size limit (the fast lane leaves it out)
def test_captures_and_clips_past_the_disk_leave_nothing_and_hold_no_descriptor(tmp_path):
    out = tmp_path / "captures"
    res = subprocess.run([sys.executable, "-c", LIMITED, str(out), "20000"],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    got = json.loads(res.stdout.splitlines()[-1])
    assert got["jpeg"] > 10000  # each still (two of them) is past the 20 kB limit
    assert len(got["errors"]) == 16 and set(got["errors"]) == {errno.EFBIG}
    assert sorted(p.name for p in out.iterdir()) == []  # no orphan still, clip or temp file
    assert got["fds_grew"] == 0  # PyAV's failed close kept each clip's file open


def test_a_capture_whose_side_file_fails_leaves_neither(tmp_path, monkeypatch):
    real = captures.write_new

    def full_at_json(path, data, mode=0o644):
        if path.suffix == ".json":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, data, mode)

    monkeypatch.setattr(captures, "write_new", full_at_json)
    with pytest.raises(OSError, match="No space"):
        save_capture(tmp_path, 7, b"\xff\xd8jpeg", {"seq": 7})
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(captures, "write_new", real)
    still = save_capture(tmp_path, 7, b"\xff\xd8jpeg", {"seq": 7})
    assert json.loads(still.with_suffix(".json").read_text()) == {"seq": 7}  # no clip named


class _Clip:
    def __init__(self, path: Path, frames: int) -> None:
        self.path, self.frames = path, frames


def test_the_json_names_a_clip_only_once_it_is_whole_and_a_clip_it_cannot_name_goes(
    tmp_path, monkeypatch
):
    still = save_capture(tmp_path, 3, b"\xff\xd8jpeg", {"seq": 3})
    clip = captures.clip_path(still)
    clip.write_bytes(b"mp4")
    name_clip(still, _Clip(clip, 21))
    assert json.loads(still.with_suffix(".json").read_text())["clip"] == {
        "file": clip.name, "frames": 21}  # fmt: skip
    other = save_capture(tmp_path, 4, b"\xff\xd8jpeg", {"seq": 4})
    clip2 = captures.clip_path(other)
    clip2.write_bytes(b"mp4")

    def full(path, data, mode=0o644):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(captures, "replace_whole", full)
    with pytest.raises(OSError, match="not named"):
        name_clip(other, _Clip(clip2, 5))
    assert not clip2.exists()  # not left unnamed
    assert json.loads(other.with_suffix(".json").read_text()) == {"seq": 4}
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_run_of_failures_is_said_once_then_again_when_it_ends(caplog):
    fl = FailureLog(logging.getLogger("humantele.test"), "capture")
    with caplog.at_level(logging.DEBUG, "humantele.test"):
        for _ in range(335):
            fl.failure(OSError(errno.ENOSPC, "No space left on device"))
        fl.success()
        fl.failure("again")
    levels = [r.levelno for r in caplog.records]
    assert levels.count(logging.ERROR) == 2 and fl.failed == 336
    assert levels.count(logging.INFO) == 1 and "after 335" in caplog.records[-2].getMessage()
