"""`humantele export`: per scan an MP4 (H.264) and a Foxglove MCAP (foxglove.CompressedVideo
H.264 beside poses and force), a clip window, several worker processes, and bad input (a
foreign file, a truncated recording, no video) as one line each, never a traceback."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import av
import numpy as np
import pytest
from mcap.reader import make_reader
from video_fixtures import FPS, picture, session_with_video

from humantele.cli import main
from humantele.export.video import EncodedFrame, TranscodeJob, transcode
from humantele.recording.synthetic import T0_EXPERT
from humantele.video.fidelity import psnr


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> list[Path]:
    return session_with_video(tmp_path_factory.mktemp("rec"))


def nal_types(data: bytes) -> set[int]:
    out, i = set(), data.find(b"\x00\x00\x01")
    while i != -1 and i + 3 < len(data):
        out.add(data[i + 3] & 0x1F)
        i = data.find(b"\x00\x00\x01", i + 3)
    return out


def read_mcap(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((schema.name, msg.log_time, msg.data))
    return out


def test_each_scan_gives_an_mp4_and_a_foxglove_file_that_play(files, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["export", *map(str, files), "--out", str(out), "--jobs", "1"]) == 0
    printed = capsys.readouterr()
    assert "Traceback" not in printed.err
    mp4s = sorted(out.glob("*.mp4"))
    assert [p.name for p in mp4s] == ["vid01_scan1_us.mp4", "vid01_scan2_us.mp4"]
    assert "no pov video recorded" in printed.err  # the fixture records the us stream only
    assert b"vid01" not in mp4s[0].read_bytes()  # a rater's clip names no session
    # the MP4: H.264, the scan's frames (about its length at 20 fps), the pictures recorded
    with av.open(str(mp4s[0])) as c:
        stream = c.streams.video[0]
        assert stream.codec_context.name == "h264"
        pics = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]
    doc = read_mcap(out / "vid01_scan1.mcap")
    video = doc["/us/video"]
    assert len(video) == len(pics) > 2 * FPS
    assert {name for name, _, _ in video} == {"foxglove.CompressedVideo"}
    # Foxglove's rules: Annex B, one frame a message, SPS with each keyframe (IDR), no B-frames
    dec = av.CodecContext.create("h264", "r")
    decoded = 0
    for i, (_, _, data) in enumerate(video):
        m = json.loads(data)
        assert m["format"] == "h264" and m["frame_id"] == "us"
        raw = base64.b64decode(m["data"])
        assert raw.startswith((b"\x00\x00\x00\x01", b"\x00\x00\x01"))
        types = nal_types(raw)
        if 5 in types:
            assert 7 in types and 8 in types
        if i == 0:
            assert 5 in types  # it starts on a keyframe
        frames = dec.decode(av.Packet(raw))
        assert len(frames) == 1  # decodes at once: no B-frame reordering
        decoded += 1
    assert decoded == len(pics)
    # the picture survives: the exported first frame against the source picture it came from
    first_t = json.loads(video[0][2])["timestamp"]
    i0 = round((first_t["sec"] + first_t["nsec"] / 1e9 + 0.03 - T0_EXPERT) * FPS)
    assert psnr(picture(i0), pics[0]) > 30.0
    assert psnr(picture(i0 + 7), pics[0]) < psnr(picture(i0), pics[0])  # and not another
    # the poses and force are there, in the same time span as the video
    t_video = [t for _, t, _ in video]
    for topic in ("/expert/pose", "/follower/probe_pose", "/expert/force"):
        times = [t for _, t, _ in doc[topic]]
        assert len(times) > 10 and min(times) >= t_video[0] - 0.2e9
        assert max(times) <= t_video[-1] + 0.2e9
    assert doc["/expert/pose"][0][0] == "foxglove.PoseInFrame"
    pose = json.loads(doc["/expert/pose"][0][2])
    assert pose["frame_id"] == "patient" and set(pose["pose"]["orientation"]) == set("xyzw")


def test_foxglove_times_are_unix_times_with_the_recording_s_clock_offset(tmp_path):
    """A recording that says where its clock sits in Unix time (as the recorder writes
    ``clock_unix_offset_s``): the file shows the session's date, its messages in the same
    order and spacing as on the expert's clock, and says so in its metadata."""
    offset = 1_795_000_000.25  # 2026-11
    (tmp_path / "rec").mkdir()
    (tmp_path / "plain").mkdir()
    files = session_with_video(tmp_path / "rec", n_scans=1, duration_s=5.0,
                               metadata={"clock_unix_offset_s": f"{offset:.6f}"})  # fmt: skip
    plain = session_with_video(tmp_path / "plain", n_scans=1, duration_s=5.0)
    runs = {}
    for name, f in (("unix", files), ("plain", plain)):
        out = tmp_path / name
        assert main(["export", *map(str, f), "--out", str(out), "--jobs", "1"]) == 0
        runs[name] = out / "vid01_scan1.mcap"
    unix, expert = read_mcap(runs["unix"]), read_mcap(runs["plain"])
    assert set(unix) == set(expert)
    for topic in unix:
        got = [t for _, t, _ in unix[topic]]
        want = [t + round(offset * 1e9) for _, t, _ in expert[topic]]
        assert len(got) == len(want) > 0
        assert max(abs(a - b) for a, b in zip(got, want, strict=True)) <= 1000  # 1 us
    stamp = json.loads(unix["/us/video"][0][2])["timestamp"]
    plain_stamp = json.loads(expert["/us/video"][0][2])["timestamp"]
    assert stamp["sec"] - plain_stamp["sec"] in (offset // 1, offset // 1 + 1)
    with open(runs["unix"], "rb") as f:
        (md,) = [m for m in make_reader(f).iter_metadata() if m.name == "humantele.export"]
    assert md.metadata["clock_unix_offset_s"] == f"{offset:.6f}"
    assert md.metadata["clock"].startswith("Unix time")
    # a value that is not a finite number: the expert's clock as it is, said so
    for bad in ("soon", "nan", "inf"):
        (tmp_path / bad).mkdir()
        f = session_with_video(tmp_path / bad, n_scans=1, duration_s=5.0,
                               metadata={"clock_unix_offset_s": bad})  # fmt: skip
        assert main(["export", *map(str, f), "--out", str(tmp_path / bad / "out")]) == 0
        doc = read_mcap(tmp_path / bad / "out" / "vid01_scan1.mcap")
        assert [t for _, t, _ in doc["/us/video"]] == [t for _, t, _ in expert["/us/video"]]


@pytest.mark.e2e  # transcodes on two worker processes (the fast lane leaves it out)
def test_scan_and_clip_window_and_two_workers(files, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["export", *map(str, files), "--out", str(out), "--scan", "2",
                 "--start", "1", "--end", "2.5", "--jobs", "2"])  # fmt: skip
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["vid01_scan2.mcap", "vid01_scan2_us.mp4"]
    with av.open(str(out / "vid01_scan2_us.mp4")) as c:
        n = sum(1 for _ in c.decode(video=0))
    assert abs(n - 1.5 * FPS) <= 2
    assert "x real time" in capsys.readouterr().out


def test_a_scan_that_is_not_there_is_named(files, tmp_path, capsys):
    assert main(["export", *map(str, files), "--out", str(tmp_path), "--scan", "7"]) == 1
    err = capsys.readouterr().err
    assert "no scan 7 (scans: [1, 2])" in err and "Traceback" not in err


def test_a_foreign_file_is_named_in_one_line_and_left_out(files, tmp_path, capsys):
    foreign = tmp_path / "notes.mcap"
    foreign.write_text("not a recording\n")
    assert main(["export", str(foreign), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any("notes.mcap: not an MCAP recording" in line and "left out" in line for line in err)
    assert not any("Traceback" in line for line in err)
    # beside good files it is left out and the rest exported
    assert main(["export", str(foreign), *map(str, files), "--out", str(tmp_path / "o"),
                 "--jobs", "1"]) == 0  # fmt: skip
    assert (tmp_path / "o" / "vid01_scan1_us.mp4").exists()


def test_a_truncated_recording_exports_what_is_intact_and_says_where_it_stops(
    files, tmp_path, capsys
):
    video = files[1].read_bytes()
    cut = tmp_path / "video.expert.mcap"
    cut.write_bytes(video[: int(len(video) * 0.6)])  # killed mid-write
    code = main(["export", str(files[0]), str(cut), "--out", str(tmp_path / "o"), "--jobs", "1"])
    err = capsys.readouterr().err
    assert code == 0 and "Traceback" not in err
    lines = [line for line in err.splitlines() if str(cut) in line]
    assert len(lines) == 1 and "last sample at t =" in lines[0]
    assert (tmp_path / "o" / "vid01_scan1_us.mp4").exists()


def test_a_recording_without_video_says_so(tmp_path, capsys):
    from humantele.recording.synthetic import SyntheticSession, write_synthetic

    path = tmp_path / "old.mcap"
    write_synthetic(path, SyntheticSession(duration_s=4.0, expert_rate_hz=100.0))
    assert main(["export", str(path), "--out", str(tmp_path / "o")]) == 0  # what there is
    err = capsys.readouterr().err
    assert "no us video recorded" in err and "Traceback" not in err
    assert (tmp_path / "o" / "sim0001_scan1.mcap").exists()  # poses and force still exported


@pytest.mark.parametrize("args", [["--jobs", "0"], ["--crf", "60"], ["--start", "3", "--end", "2"]])
def test_bad_arguments_are_one_line(files, tmp_path, capsys, args):
    assert main(["export", str(files[0]), "--out", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err
    assert "configuration error" in err and "Traceback" not in err


def test_undecodable_frames_are_counted_not_fatal(tmp_path):
    from video_fixtures import vp8_frames

    frames = [EncodedFrame(i / FPS, d, k) for i, (d, k) in enumerate(vp8_frames(20))]
    frames[5] = EncodedFrame(frames[5].t, b"\x00garbage", False)
    res = transcode(TranscodeJob("x", frames, 0.0, 1.0, "vp8", tmp_path / "x.mp4"))
    assert res.error is None and res.frames_in == 20
    assert res.frames_out + res.decode_errors + res.skipped_before_keyframe == 20
    assert res.frames_out >= 15 and len(res.h264) == res.frames_out
    assert np.isfinite(res.duration_s)


def test_an_h264_link_recording_transcodes_too(tmp_path):
    """[expert.video] codec = "h264": the recorded access units (Annex B) decode and export."""
    import fractions

    from video_fixtures import H, W

    from humantele.media.jitter import h264_is_keyframe

    enc = av.CodecContext.create("libx264", "w")
    enc.width, enc.height, enc.pix_fmt = W, H, "yuv420p"
    enc.time_base = fractions.Fraction(1, FPS)
    enc.gop_size, enc.max_b_frames = 10, 0
    frames = []
    for i in range(30):
        f = av.VideoFrame.from_ndarray(picture(i), format="bgr24").reformat(format="yuv420p")
        f.pts = i
        for p in enc.encode(f):
            data = bytes(p)
            frames.append(EncodedFrame(float(p.pts) / FPS, data, h264_is_keyframe(data)))
    assert frames[0].keyframe
    res = transcode(TranscodeJob("h", frames, 0.0, 2.0, "h264", tmp_path / "h.mp4"))
    assert res.error is None and res.frames_out == len(frames) and res.decode_errors == 0
    with av.open(str(tmp_path / "h.mp4")) as c:
        first = next(c.decode(video=0)).to_ndarray(format="bgr24")
    assert psnr(picture(0), first) > 30.0
