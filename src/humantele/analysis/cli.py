"""``humantele analyze RECORDING... [--json] [--scores FILE] [--tlx FILE] [--usability FILE]
[--plots DIR]``: the paper's results (Table II, the trajectory figures, image quality against
alignment error, NASA-TLX and usability) from recorded sessions."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from humantele.analysis.report import analyze, print_report
from humantele.config import ConfigError
from humantele.recording.reader import RecordingReadError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "recordings",
        nargs="*",
        type=Path,
        metavar="RECORDING",
        help="MCAP recordings (expert and follower files of a session, or demo)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--scores",
        type=Path,
        metavar="FILE",
        help="image-quality scores CSV (scan,target,rater,score or wide)",
    )
    parser.add_argument("--tlx", type=Path, metavar="FILE", help="NASA-TLX responses CSV")
    parser.add_argument("--usability", type=Path, metavar="FILE", help="usability CSV")
    parser.add_argument("--plots", type=Path, metavar="DIR", help="write PNG figures here")
    parser.add_argument(
        "--exclude-scans",
        default="",
        metavar="N,N",
        help="also summarise quality without these scans (the paper: 1,2)",
    )
    parser.add_argument(
        "--max-gap-ms",
        type=float,
        default=50.0,
        help="longest gap in the virtual pose to interpolate over (ms)",
    )
    from humantele.analysis import rating

    rating.add_arguments(parser)


def write_plots(report: dict[str, Any], pairs: list, out_dir: Path, args: Any) -> list[Path]:
    from humantele.analysis import plots

    out_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    for session, result in pairs:
        if result.rmse.n:
            paths += plots.plot_trajectories(session, result, out_dir)
    q = report.get("quality")
    if q and q.get("source") != "sim":  # the bars are of rater scores (0-5)
        paths.append(plots.plot_quality_bars(q, out_dir / "quality_scores.png", "image quality"))
        if q.get("without_excluded"):
            excl = ",".join(map(str, q["without_excluded"]["excluded_scans"]))
            paths.append(
                plots.plot_quality_bars(
                    q["without_excluded"],
                    out_dir / "quality_scores_excluded.png",
                    f"image quality without scans {excl}",
                )
            )
    if getattr(args, "tlx", None):
        from humantele.analysis.questionnaires import read_tlx

        paths.append(plots.plot_tlx(read_tlx(args.tlx), out_dir / "nasa_tlx.png"))
    if getattr(args, "usability", None):
        from humantele.analysis.questionnaires import read_usability

        paths.append(
            plots.plot_usability(read_usability(args.usability), out_dir / "usability.png")
        )
    return paths


def _parse_scans(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.replace(" ", "").split(",") if x)
    except ValueError:
        raise ConfigError(f"--exclude-scans: {text!r} is not a list of scan numbers") from None


def run(args: argparse.Namespace) -> int:
    if getattr(args, "rating_sheet", None) or getattr(args, "ratings", None):
        from humantele.analysis import rating

        return rating.run(args)
    if not (args.recordings or args.scores or args.tlx or args.usability):
        print(
            "humantele analyze: give recordings and/or --scores/--tlx/--usability", file=sys.stderr
        )
        return 2
    if not args.max_gap_ms > 0:
        raise ConfigError(f"--max-gap-ms: must be > 0, got {args.max_gap_ms}")
    try:
        report, pairs = analyze(
            list(args.recordings),
            args.scores,
            args.tlx,
            args.usability,
            _parse_scans(args.exclude_scans),
            args.max_gap_ms / 1000.0,
        )
        if args.plots is not None:
            report["plots"] = [str(p) for p in write_plots(report, pairs, args.plots, args)]
    except RecordingReadError as exc:
        print(f"humantele analyze: {exc}", file=sys.stderr)
        return 2
    print_report(report, args.json)
    if not args.json and report.get("plots"):
        print(f"{len(report['plots'])} figure(s) in {args.plots}")
    return 0
