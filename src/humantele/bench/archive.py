"""``humantele bench archive``: the exam sent to a real archive (Orthanc on loopback).

- a session of ``--seconds`` with a capture (still + ``--clip-frames`` clip, 640 x 480 JPEG
  frames as the console's) every ``60 / --captures-per-minute`` s, a caliper on every other:
  objects made and sent, time from Capture to "archived" (p50 / p95) for stills and clips;
- a whole scan sent live: the console's keeper (expert/console/scan_frames.py) offered the US
  frames of a ``--scan-seconds`` scan (640 x 480, 20 fps, their capture times those of a scan
  ending now, fed as fast as they are kept), "Archive scan" asked during it, then its end:
  frames kept (the memory bound), MB, the CPU of keeping them, and the scan's end to
  "archived";
- an outage of ``--outage-s``: the archive stopped, captures made meanwhile, the archive
  back: all archived after, none sent twice (the queue's journal), the time to drain;
- dciodvfy (Debian dicom3tools) on one object of each kind: its errors and warnings;
- this process's CPU (the expert's side: DICOM writing, the queue, C-STORE) over a window in
  which one clip is captured and sent, against the same window idle.

Writes the ``archive`` section of docs/benchmarks.md (``--no-write``: not).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from humantele.bench import publish
from humantele.report import machine_line, markdown_table

SECTION = "archive"
FPS = 20.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=120.0, help="session length, s")
    parser.add_argument("--captures-per-minute", type=float, default=12.0)
    parser.add_argument("--clip-frames", type=int, default=100, help="frames per clip (20 fps)")
    parser.add_argument("--scan-seconds", type=float, default=120.0,
                        help="length of the whole scan sent live, s (0: none)")  # fmt: skip
    parser.add_argument("--outage-s", type=float, default=60.0, help="archive down for, s")
    parser.add_argument("--cpu-window-s", type=float, default=5.0)
    parser.add_argument("--no-write", action="store_true", help="do not write benchmarks.md")
    parser.add_argument("--json", action="store_true", help="also print the figures as JSON")


def _frames(n: int, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    base = (rng.random((480, 640)) * 120 + 30).astype(np.uint8)
    out = []
    for i in range(n):
        img = np.roll(base, 3 * i, axis=1)
        cv2.circle(img, (200 + i % 200, 240), 60, 10, -1)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_GRAY2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, 88])  # fmt: skip
        out.append(buf.tobytes())
    return out


def _pct(values: list[float], q: float) -> float | None:
    return None if not values else float(np.percentile(values, q))


async def _session(args, pacs, tmp: Path) -> dict:
    from humantele.archive import objects as obj
    from humantele.archive.config import ArchiveConfig
    from humantele.archive.exam import Patient
    from humantele.archive.service import ExamArchive

    cfg = ArchiveConfig(enabled=True, port=pacs.dicom_port, called_ae=pacs.aet,
                        queue_dir=str(tmp / "queue"), retry_min_s=1.0, retry_max_s=5.0)  # fmt: skip
    a = ExamArchive(cfg)
    a.begin(Patient(patient_id="BENCH-1", family_name="Bench", given_name="Patient"))
    await a.start()
    frames = _frames(max(2, args.clip_frames))
    scale = obj.Scale((0.2, 0.2), 0.0)
    started: dict[int, tuple[str, float]] = {}  # item -> (kind, Capture pressed)
    period = 60.0 / args.captures_per_minute
    seq = 0

    async def capture(with_clip: bool = True) -> None:
        nonlocal seq
        seq += 1
        t0 = time.monotonic()
        clip = [(t0 - (len(frames) - k) / FPS, j) for k, j in enumerate(frames)] if with_clip \
            else None  # fmt: skip
        items = await asyncio.to_thread(a.capture, seq, frames[-1], t0, scale, "scan 1", clip)
        if seq % 2 == 0:
            items += await asyncio.to_thread(
                a.mark, seq, obj.Caliper((100, 100), (300, 200), 44.7), None, "scan 1"
            )
        for i in items:
            started[i.n] = (i.kind, t0)

    async def drained(timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if not a.queue.pending():
                return True
            await asyncio.sleep(0.05)
        return False

    # 1. the session, archive up
    t_end = time.monotonic() + args.seconds
    while time.monotonic() < t_end:
        await capture()
        await asyncio.sleep(max(0.0, period - 0.0))
    await drained(120.0)
    done = a.forwarder.archived_at
    lat = {"image": [], "clip": [], "sr": [], "pr": []}
    for n, (kind, t0) in started.items():
        if n in done:
            lat[kind].append(done[n] - t0)
    session = {"captures": seq, "made": dict(a.made), "status": a.status(),
               "bytes": sum(i.size for i in a.queue.items.values()),
               "lat": {k: (_pct(v, 50), _pct(v, 95), len(v)) for k, v in lat.items()}}  # fmt: skip

    session["scan"] = await _whole_scan(args, cfg, a, drained) if args.scan_seconds > 0 else None

    # 2. an outage
    before = set(a.queue.items)
    await asyncio.to_thread(pacs.stop)
    t_out = time.monotonic()
    outage_caps = 0
    while time.monotonic() - t_out < args.outage_s:
        await capture()
        outage_caps += 1
        await asyncio.sleep(min(period, max(0.5, args.outage_s / 4)))
    waiting = len(a.queue.pending())
    shown = a.status()["text"]
    await asyncio.to_thread(pacs.start)
    t_back = time.monotonic()
    a.forwarder.retry_at = 0.0  # (the bench does not wait out the back-off it chose)
    a.forwarder.kick()
    ok = await drained(300.0)
    drain_s = time.monotonic() - t_back
    sends: dict[int, int] = {}
    for line in (tmp / "queue" / "journal.jsonl").read_text().splitlines():
        ev = json.loads(line)
        if ev["ev"] == "sending":
            sends[ev["n"]] = sends.get(ev["n"], 0) + 1
    outage_items = [n for n in a.queue.items if n not in before]
    in_pacs = len(pacs.get("/instances"))
    outage = {"captures": outage_caps, "objects": len(outage_items), "waiting_shown": shown,
              "waiting": waiting, "all_archived": ok, "drain_s": drain_s,
              "max_sends": max(sends.values(), default=0), "in_archive": in_pacs,
              "made_total": len(a.queue.items)}  # fmt: skip

    # 3. CPU: a clip captured and sent, against idle
    w = args.cpu_window_s
    c0, t0 = time.process_time(), time.monotonic()
    await asyncio.sleep(w)
    idle = (time.process_time() - c0) / (time.monotonic() - t0) * 100.0
    c0, t0 = time.process_time(), time.monotonic()
    await capture()
    await drained(60.0)
    await asyncio.sleep(max(0.0, w - (time.monotonic() - t0)))
    sending = (time.process_time() - c0) / (time.monotonic() - t0) * 100.0
    await a.stop()
    return {"session": session, "outage": outage,
            "cpu": {"idle_percent": idle, "clip_percent": sending, "window_s": w}}  # fmt: skip


async def _whole_scan(args, cfg, a, drained) -> dict:
    """A whole scan through the console's own path: its keeper, "Archive scan", the queue."""
    from types import SimpleNamespace

    from humantele.expert.console.archive_routes import ConsoleArchive
    from humantele.web.credential import new_key

    scan: dict[str, int | None] = {"now": 2}
    console = ConsoleArchive(cfg, new_key(), scan=lambda: scan["now"], archive=a)
    pictures = [cv2.cvtColor(cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_GRAYSCALE),
                             cv2.COLOR_GRAY2BGR) for j in _frames(40, seed=2)]  # fmt: skip
    n = int(args.scan_seconds * FPS)
    t0 = time.monotonic() - args.scan_seconds
    ok, _ = console.request_scan()  # during the scan: archived at its end
    c0 = time.process_time()
    most = 0.0
    for i in range(n):
        f = SimpleNamespace(seq=i + 1, t_capture=t0 + i / FPS, width=640, height=480,
                            pixel_spacing_mm=(0.2, 0.2), depth_origin_row=0.0,
                            image=pictures[i % len(pictures)])  # fmt: skip
        console.scans.offer(f)
        await console.scans.idle()
        most = max(most, console.scans.current.nbytes)
    keep_cpu = time.process_time() - c0
    kept = console.scans.current
    encoded = console.scans.encoded
    frames, halved, fps = len(kept.frames), kept.halvings, 1.0 / kept.interval_s
    kb = kept.nbytes / max(1, frames) / 1e3
    before = set(a.queue.items)
    scan["now"] = None
    t_end = time.monotonic()
    c0 = time.process_time()
    console.scans.poll()  # its end: built and queued in a thread
    while kept.outcome == "building":
        await asyncio.sleep(0.01)
    new = [i for i in a.queue.items.values() if i.n not in before and i.kind == "scan"]
    await drained(300.0)
    done = a.forwarder.archived_at
    archived_s = (done[new[0].n] - t_end) if new and new[0].n in done else None
    return {"asked": ok, "seconds": args.scan_seconds, "scan_fps": cfg.scan_fps,
            "offered": n, "frames": frames, "fps": fps, "halved": halved, "kept_mb": most / 1e6,
            "kb_per_frame": kb,
            "mb": new[0].size / 1e6 if new else None, "outcome": kept.outcome,
            "keep_ms_per_frame": keep_cpu / max(1, encoded) * 1000.0,
            "keep_cpu_percent_at_20fps": keep_cpu / args.scan_seconds * 100.0,
            "end_to_archived_s": archived_s,
            "send_cpu_s": time.process_time() - c0}  # fmt: skip


def _validate(tmp: Path) -> dict[str, str]:
    from humantele.archive import objects as obj
    from humantele.archive.exam import ExamStore, Patient
    from humantele.archive.queue import to_bytes

    if shutil.which("dciodvfy") is None:
        return {"all": "dciodvfy not installed (Debian dicom3tools)"}
    store = ExamStore(tmp)
    store.begin(Patient(patient_id="V-1", family_name="Valid", given_name="Vera"), time.time())

    def place(s):
        uid, num = store.series_for(s)
        return obj.Placement(store.exam, uid, num, store.next_instance())

    eq = obj.Equipment(performing_physician="Expert^Sam", institution="Clinic")
    fr = _frames(3)
    sc = obj.Scale((0.2, 0.2), 0.0)
    image = obj.us_image(fr[0], time.time(), sc, place("1"), eq)
    c = obj.Caliper((10, 20), (200, 100), 30.0)
    objs = {"US image": image,
            "US multi-frame": obj.us_multiframe(fr, [time.time() + k / FPS for k in range(3)],
                                                sc, place("1"), eq),
            "SR (TID 1500)": obj.measurement_report([image], [(0, c)], place("r"), eq),
            "colour presentation state": obj.presentation_state(
                image, [c], [obj.Note((5, 5), "note")], place("r"), eq)}  # fmt: skip
    out = {}
    for name, ds in objs.items():
        p = tmp / "v.dcm"
        p.write_bytes(to_bytes(ds))
        r = subprocess.run(["dciodvfy", str(p)], capture_output=True, text=True)
        lines = (r.stdout + r.stderr).splitlines()
        errs = [x for x in lines if x.startswith("Error")]
        warns = [x for x in lines if x.startswith("Warning")]
        out[name] = f"{len(errs)} errors, {len(warns)} warnings" + (
            f" ({'; '.join(sorted(set(w.split(' - ', 1)[-1][:90] for w in warns)))})"
            if warns else "")  # fmt: skip
    return out


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v * 1000:.0f} ms"


def _scan_rows(sc: dict | None) -> list[list[str]]:
    if sc is None:
        return []
    end = sc["end_to_archived_s"]
    return [
        ["whole scan sent live", f"{sc['seconds']:.0f} s of 640 x 480 US at {FPS:.0f} fps "
         f"(asked for during it: {sc['asked']}): {sc['frames']} frames kept at "
         f"{sc['fps']:.2g} a second (scan_fps {sc['scan_fps']:g}, halved {sc['halved']} times; "
         f"at most {sc['kept_mb']:.1f} MB kept; the bench's speckle JPEGs {sc['kb_per_frame']:.0f} "
         f"kB a frame), {sc['mb'] or 0:.1f} MB object, {sc['outcome']}"],
        ["whole scan: the expert's cost", f"keeping: {sc['keep_ms_per_frame']:.1f} ms CPU a "
         f"kept frame ({sc['keep_cpu_percent_at_20fps']:.1f} % of a core over the scan); "
         f"building, queueing and sending: {sc['send_cpu_s']:.2f} s CPU"],
        ["whole scan: its end to archived", "n/a" if end is None else f"{end:.2f} s"],
    ]  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from humantele.archive.orthanc import OrthancError, OrthancServer

    load0 = os.getloadavg()[0]
    tmp = Path(tempfile.mkdtemp(prefix="humantele-bench-archive-"))
    try:
        with OrthancServer() as pacs:
            r = asyncio.run(_session(args, pacs, tmp))
        r["dciodvfy"] = _validate(tmp)
    except OrthancError as exc:
        print(f"humantele bench archive: {exc}", file=sys.stderr)
        return 1
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s, o, c = r["session"], r["outage"], r["cpu"]
    lat = s["lat"]
    rows = [
        ["session", f"{args.seconds:.0f} s, {s['captures']} captures (still + "
                    f"{args.clip_frames}-frame clip), a caliper on every other"],
        ["objects made", ", ".join(f"{k} {v}" for k, v in s["made"].items() if k != "scan" or v)
         + f"; {s['status']['text']}; {s['bytes'] / 1e6:.1f} MB"],
        ["Capture to archived, still p50 / p95", f"{_ms(lat['image'][0])} / "
                                                 f"{_ms(lat['image'][1])} (n {lat['image'][2]})"],
        ["Capture to archived, clip p50 / p95", f"{_ms(lat['clip'][0])} / "
                                                f"{_ms(lat['clip'][1])} (n {lat['clip'][2]})"],
        ["Capture to archived, SR p50 / p95", f"{_ms(lat['sr'][0])} / {_ms(lat['sr'][1])}"],
        *_scan_rows(s["scan"]),
        ["outage", f"{args.outage_s:.0f} s: {o['captures']} captures ({o['objects']} objects) "
                   f"made during it; the page said \"{o['waiting_shown']}\""],
        ["after the outage", f"all archived: {o['all_archived']} in {o['drain_s']:.1f} s; "
                             f"most sends of one object: {o['max_sends']}; archive holds "
                             f"{o['in_archive']} of {o['made_total']}"],
        ["expert CPU, idle / sending a clip", f"{c['idle_percent']:.1f} / "
                                              f"{c['clip_percent']:.1f} % of a core "
                                              f"({c['window_s']:.0f} s windows)"],
        *[[f"dciodvfy: {k}", v] for k, v in r["dciodvfy"].items()],
    ]  # fmt: skip
    md = "\n".join([
        "## The hospital's archive: DICOM to Orthanc (`humantele bench archive`)",
        "",
        machine_line(),
        "Orthanc 1.x on loopback (C-STORE), the queue on this machine's disk. Capture to"
        " archived: from the capture's call to the archive's Success for that instance."
        f" Load average {load0:.1f} at start, {os.getloadavg()[0]:.1f} at the end.",
        "",
        markdown_table(["figure", "value"], rows),
    ])  # fmt: skip
    print(md)
    publish(SECTION, md, r, args)
    return 0
