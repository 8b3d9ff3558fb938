"""``humantele bench analysis``: how long ``humantele analyze`` takes on a 10-minute session
(1 kHz expert pose, 45 Hz tracking), what packing samples per message buys when reading, and
what recording costs a daemon at those rates (caller side and writer thread, % of one core).
Deterministic by seed; writes the "analysis" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from pathlib import Path

from humantele.analysis.sessions import TOPICS, analyze_scans, build_session
from humantele.bench import publish
from humantele.recording.reader import read_recording
from humantele.recording.synthetic import SyntheticSession, write_synthetic
from humantele.recording.writer import Recorder
from humantele.report import machine_line, markdown_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=10.0, help="session length to analyse")
    parser.add_argument("--repeat", type=int, default=3, help="analysis runs (median reported)")
    parser.add_argument(
        "--record-seconds",
        type=float,
        default=10.0,
        help="real-time recording run for the CPU cost",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-write", action="store_true", help="print only")


def _session(minutes: float, seed: int, batch: int = 100) -> SyntheticSession:
    return SyntheticSession(
        duration_s=60.0 * minutes,
        n_scans=max(1, int(minutes)),
        offset_mm=(20.0, -5.0, 3.0),
        rotation_offset_deg=(5.0, 0.0, 2.0),
        lag_s=0.35,
        tremor_mm=3.0,
        tremor_deg=2.0,
        tracking_noise_mm=0.5,
        dropout=0.05,
        clock_offset_s=2.0,
        clock_drift_ppm=30.0,
        seed=seed,
        batch_max_samples=batch,
    )


def time_analysis(path: Path) -> tuple[float, float, int]:
    """(read s, alignment s, scans) for one analysis of ``path``."""
    t0 = time.perf_counter()
    rec = read_recording(path, TOPICS)
    t1 = time.perf_counter()
    session = build_session(rec.session.get("session_id", "bench"), [rec])
    results = analyze_scans(session)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1, len(results)


def record_cost(seconds: float, path: Path) -> dict[str, float]:
    """Run a 1 kHz producer (expert pose) + 45 Hz (probe pose) in real time into a Recorder."""
    rec = Recorder(path, "demo", follower_id="F01", sonographer_id="S1")
    caller_ns = 0
    n = int(seconds * 1000)
    start = time.perf_counter()
    deadline = start
    q = [0.0, 0.0, 0.0, 1.0]

    def producer() -> None:
        nonlocal caller_ns, deadline
        for i in range(n):
            c0 = time.thread_time_ns()
            t = time.monotonic()
            rec.write(
                "/expert/pose", t, {"position": [1e-3 * (i % 100), 0.15, 0.0], "quaternion": q}
            )
            if i % 22 == 0:
                rec.write(
                    "/follower/probe_pose",
                    t,
                    {"position": [0.0, 0.15, 0.0], "quaternion": q, "tracked": True},
                )
            caller_ns += time.thread_time_ns() - c0
            deadline += 0.001
            delay = deadline - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

    th = threading.Thread(target=producer)
    th.start()
    th.join()
    wall = time.perf_counter() - start
    stats = rec.close()
    return {
        "wall_s": wall,
        "samples": float(stats.written),
        "caller_pct": 100.0 * caller_ns * 1e-9 / wall,
        "writer_pct": 100.0 * stats.writer_cpu_s / wall,
        "caller_us_per_write": caller_ns * 1e-3 / max(stats.queued, 1),
        "dropped": float(stats.dropped_overflow + stats.dropped_invalid + stats.dropped_failed),
        "bytes_per_s": path.stat().st_size / wall,
    }


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="humantele-bench-") as tmp:
        tmpdir = Path(tmp)
        main = tmpdir / "session.mcap"
        t0 = time.perf_counter()
        write_synthetic(main, _session(args.minutes, args.seed))
        gen_s = time.perf_counter() - t0
        size_mb = main.stat().st_size / 1e6
        runs = [time_analysis(main) for _ in range(max(1, args.repeat))]
        total = statistics.median(r[0] + r[1] for r in runs)
        read_s = statistics.median(r[0] for r in runs)
        align_s = statistics.median(r[1] for r in runs)
        print(
            f"analyze {args.minutes:g} min session ({size_mb:.1f} MB, {runs[0][2]} scans): "
            f"{total:.2f} s (read {read_s:.2f} s, alignment {align_s:.2f} s)"
        )

        # Packing: read time per sample at several samples-per-message, on a 1-minute session.
        pack_rows = []
        for batch in (1, 10, 100):
            p = tmpdir / f"pack{batch}.mcap"
            write_synthetic(p, _session(1.0, args.seed, batch))
            read_1min = min(time_analysis(p)[0] for _ in range(2))
            pack_rows.append(
                [batch, f"{p.stat().st_size / 1e6:.2f}", f"{read_1min * args.minutes:.1f}"]
            )
            print(
                f"  {batch:>3} samples/message: {p.stat().st_size / 1e6:.2f} MB/min, "
                f"read {read_1min:.2f} s/min"
            )

        cost = record_cost(args.record_seconds, tmpdir / "rt.mcap")
        print(
            f"recording at 1 kHz + 45 Hz: caller {cost['caller_pct']:.2f} % of a core "
            f"({cost['caller_us_per_write']:.1f} us/write), writer thread "
            f"{cost['writer_pct']:.2f} %, dropped {cost['dropped']:.0f}, "
            f"{cost['bytes_per_s'] / 1e3:.0f} kB/s"
        )

    md = "\n".join(
        [
            "## analysis: `humantele analyze` and recording cost",
            "",
            machine_line(),
            f"Command: `humantele bench analysis --minutes {args.minutes:g} --repeat {args.repeat} "
            f"--record-seconds {args.record_seconds:g} --seed {args.seed}`",
            "",
            f"Analyse a {args.minutes:g}-minute recorded session (1 kHz expert pose, "
            f"45 Hz tracking, "
            f"{size_mb:.1f} MB MCAP): **{total:.2f} s** (target <= 5 s), of which reading "
            f"{read_s:.2f} s and alignment {align_s:.2f} s (median of {len(runs)}). "
            f"Writing the synthetic file took {gen_s:.1f} s.",
            "",
            "Packing high-rate samples into one MCAP message (JSON) against reading time:",
            "",
            markdown_table(
                ["samples/message", "MB per minute", f"read s per {args.minutes:g} min"], pack_rows
            ),
            "",
            f"Recording cost in the daemon ({args.record_seconds:g} s real time, "
            "1 kHz pose + 45 Hz probe pose):",
            "",
            markdown_table(
                [
                    "caller (% core)",
                    "us per write",
                    "writer thread (% core)",
                    "total (% core)",
                    "dropped",
                    "kB/s",
                ],
                [
                    [
                        f"{cost['caller_pct']:.2f}",
                        f"{cost['caller_us_per_write']:.1f}",
                        f"{cost['writer_pct']:.2f}",
                        f"{cost['caller_pct'] + cost['writer_pct']:.2f}",
                        f"{cost['dropped']:.0f}",
                        f"{cost['bytes_per_s'] / 1e3:.0f}",
                    ]
                ],
            ),
            "",
            "Target: recording costs the daemon <= 5 % of a core.",
        ]
    )
    publish("analysis", md, None, args)
    return 0
