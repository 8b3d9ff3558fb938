"""The paper's blinded image-quality rating: a shuffled, anonymised sheet of clips for the
raters, and the filled sheet read back and joined to the scans.

``humantele analyze RECORDING... --rating-sheet OUT.csv [--raters A,B] [--clips DIR]`` draws
one clip per scan (its ultrasound, ``humantele export``'s ``<session>_scan<N>_us.mp4``) under
a random id that says nothing of the session, scan, participant or condition, in a random
order, and writes:

- ``OUT.csv``, the template the raters fill: ``clip,<rater>...``, one row per clip, the scores
  blank (0-5, Table I of the paper: 0 target not obtained .. 5 good quality);
- ``OUT.key.csv``, the key (clip id -> session, scan, participants, the exported file): for
  the analyst only, never for the raters;
- with ``--clips DIR`` (the export directory), ``OUT_clips/<clip>.mp4``: the clips under their
  ids, the folder to give the raters with the sheet.

``humantele analyze RECORDING... --ratings FILLED.csv [--rating-key KEY]`` reads the filled
sheet (its key: ``FILLED.key.csv`` if there, else the one ``*.key.csv`` beside it), checks it
against the key (every clip once, nothing else, every score a whole number 0-5: a clear line
otherwise) and gives the paper's image-quality table and the Spearman correlation of each
scan's rated quality with its alignment error, joined on session and scan.
"""

from __future__ import annotations

import csv
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from humantele.analysis.csvfile import csv_rows, number_cell
from humantele.analysis.quality import Score, spearman, summarize_quality
from humantele.config import ConfigError

KEY_COLUMNS = ("clip", "session", "scan", "stream", "follower_id", "sonographer_id", "file")
ID_ALPHABET = "ABCDEFGHJKLMNPQRSTUVWXYZ23456789"  # no 0/O, 1/I: read aloud, typed back


@dataclass(frozen=True)
class Clip:
    """One clip to rate: its random id and what it is (the key's row)."""

    clip: str
    session: str
    scan: int
    stream: str
    follower_id: str
    sonographer_id: str
    file: str


def key_path(sheet: Path) -> Path:
    """``OUT.csv`` -> ``OUT.key.csv``."""
    return sheet.with_name(sheet.name.removesuffix(".csv") + ".key.csv")


def _new_ids(n: int, rng: Any) -> list[str]:
    ids: set[str] = set()
    while len(ids) < n:
        ids.add("".join(rng.choice(ID_ALPHABET) for _ in range(5)))
    return list(ids)


def draw_clips(scans: list[dict[str, Any]], stream: str = "us", rng: Any = None) -> list[Clip]:
    """One clip per scan (``scans``: ``analyze``'s per-scan dicts), random ids, random order."""
    rng = rng or secrets.SystemRandom()
    ids = _new_ids(len(scans), rng)
    clips = [
        Clip(ids[i], str(s["session"]), int(s["scan"]), stream, str(s.get("follower_id") or ""),
             str(s.get("sonographer_id") or ""), f"{s['session']}_scan{s['scan']}_{stream}.mp4")
        for i, s in enumerate(scans)
    ]  # fmt: skip
    rng.shuffle(clips)
    return clips


def write_sheet(
    sheet: Path, clips: list[Clip], raters: list[str], clips_dir: Path | None = None
) -> list[str]:
    """Write the template, the key and (from ``clips_dir``) the renamed clips; notes about
    clips whose MP4 is not in ``clips_dir``. Never overwrites a sheet or a key."""
    if not clips:
        raise ConfigError("--rating-sheet: no scans in the recordings: nothing to rate")
    key = key_path(sheet)
    for p in (sheet, key):
        if p.exists():
            raise ConfigError(f"--rating-sheet: {p} exists (a sheet is never overwritten)")
    if not sheet.parent.is_dir():
        raise ConfigError(f"--rating-sheet: no directory {sheet.parent}")
    with open(sheet, "x", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["clip", *raters])
        for c in clips:
            w.writerow([c.clip, *([""] * len(raters))])
    with open(key, "x", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(KEY_COLUMNS)
        for c in sorted(clips, key=lambda c: (c.session, c.scan)):
            w.writerow([getattr(c, k) for k in KEY_COLUMNS])
    notes = []
    if clips_dir is not None:
        out = sheet.with_name(sheet.name.removesuffix(".csv") + "_clips")
        out.mkdir(exist_ok=True)
        for c in clips:
            src = clips_dir / c.file
            if src.is_file():
                shutil.copyfile(src, out / f"{c.clip}.mp4")
            else:
                notes.append(f"no {src} (run humantele export): clip {c.clip} has no video")
    return notes


def _csv(path: Path, what: str) -> tuple[list[str], Any]:
    """:func:`csv_rows`, with a file that is not text as a ConfigError too."""
    try:
        path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a CSV text file ({what})") from None
    except OSError:
        pass  # csv_rows says it
    return csv_rows(path, what)


def read_key(path: Path) -> dict[str, Clip]:
    """The key written by :func:`write_sheet`; ConfigError naming the row if it is not one."""
    header, rows = _csv(path, "rating key")
    missing = [k for k in KEY_COLUMNS if k not in header]
    if missing:
        raise ConfigError(f"{path}: not a rating key (no column(s) {', '.join(missing)})")
    out: dict[str, Clip] = {}
    for _n, where, row in rows:
        scan = int(number_cell(row["scan"], where, "scan", 0, 10**6, integer=True))
        clip = (row["clip"] or "").strip()
        if not clip or clip in out:
            raise ConfigError(f"{where}: clip id {clip!r} empty or twice")
        out[clip] = Clip(clip, row["session"], scan, row["stream"], row["follower_id"] or "",
                         row["sonographer_id"] or "", row["file"])  # fmt: skip
    if not out:
        raise ConfigError(f"{path}: the key lists no clips")
    return out


def find_key(sheet: Path, given: Path | None) -> Path:
    """The key of a filled sheet: ``given``, else ``<sheet>.key.csv``, else the only key
    beside it."""
    if given is not None:
        return given
    own = key_path(sheet)
    if own.is_file():
        return own
    keys = sorted(sheet.parent.glob("*.key.csv"))
    if len(keys) == 1:
        return keys[0]
    raise ConfigError(
        f"--ratings: no key for {sheet} ({own.name} not there, {len(keys)} *.key.csv beside "
        "it): give --rating-key"
    )


def read_ratings(sheet: Path, key: dict[str, Clip]) -> list[Score]:
    """The filled sheet as scores (scan, target = the clip id, rater, 0-5), checked against
    the key: ConfigError (one line) for an unknown or repeated clip, a missing one, a blank or
    non-numeric score, or no rater column."""
    header, rows = _csv(sheet, "ratings")
    if "clip" not in header:
        raise ConfigError(f"{sheet}: no 'clip' column (header {header})")
    raters = [h for h in header if h and h != "clip"]
    if not raters:
        raise ConfigError(f"{sheet}: no rater column beside 'clip'")
    seen: set[str] = set()
    scores: list[Score] = []
    for _n, where, row in rows:
        clip = (row["clip"] or "").strip()
        if not clip and not any((row[r] or "").strip() for r in raters):
            continue  # an empty line
        if clip not in key:
            raise ConfigError(f"{where}: clip {clip!r} is not in the key (a sheet of another "
                              "draw, or a typing error)")  # fmt: skip
        if clip in seen:
            raise ConfigError(f"{where}: clip {clip!r} twice")
        seen.add(clip)
        for r in raters:
            if not (row[r] or "").strip():
                raise ConfigError(f"{where}: column {r!r}: no score for clip {clip!r}")
            value = int(number_cell(row[r], where, r, 0, 5, integer=True))
            scores.append(Score(key[clip].scan, clip, r, value))
    missing = sorted(set(key) - seen)
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise ConfigError(f"{sheet}: {len(missing)} of {len(key)} clips not rated ({shown})")
    return scores


def ratings_quality(
    scores: list[Score], key: dict[str, Clip], scans: list[dict[str, Any]], metrics: list[str]
) -> tuple[dict[str, Any], list[str]]:
    """The paper's quality table from the ratings and, per alignment metric, the Spearman
    correlation of each scan's rated quality (mean of its captured clip's scores) with it,
    joined on (session, scan); warnings for rated scans without a recording."""
    quality = summarize_quality(scores)
    by_clip: dict[str, list[int]] = {}
    for s in scores:
        by_clip.setdefault(s.target, []).append(s.score)
    rated = {
        (key[c].session, key[c].scan): sum(v) / len(v) for c, v in by_clip.items() if min(v) > 0
    }
    recorded = {(str(s["session"]), int(s["scan"])): s for s in scans}
    warnings = [
        f"rated clip of session {sess} scan {scan} has no recording given"
        for sess, scan in sorted(set((k.session, k.scan) for k in key.values()) - set(recorded))
    ]
    common = sorted(set(rated) & set(recorded))
    quality["scan_quality"] = {f"{sess}/{scan}": rated[(sess, scan)] for sess, scan in common}
    quality["spearman"] = {}
    for m in metrics:
        pairs = [(rated[k], recorded[k][m]) for k in common if recorded[k][m] is not None]
        quality["spearman"][m] = spearman([a for a, _ in pairs], [b for _, b in pairs])
    quality["source"] = "ratings"
    return quality, warnings


def add_arguments(parser: Any) -> None:
    """The rating options of ``humantele analyze``."""
    g = parser.add_argument_group("blinded rating (docs/export.md)")
    g.add_argument(
        "--rating-sheet",
        type=Path,
        metavar="OUT.csv",
        help="draw a shuffled, anonymised sheet of the scans' clips (and OUT.key.csv)",
    )
    g.add_argument(
        "--raters",
        default="rater1",
        metavar="A,B",
        help="the sheet's rater columns (default: rater1)",
    )
    g.add_argument(
        "--clips",
        type=Path,
        metavar="DIR",
        help="humantele export's directory: copy the clips under their ids",
    )
    g.add_argument("--seed", type=int, default=None, help="a reproducible draw (default: random)")
    g.add_argument(
        "--ratings",
        type=Path,
        metavar="FILLED.csv",
        help="the filled sheet: the image-quality table and its Spearman correlation",
    )
    g.add_argument(
        "--rating-key",
        type=Path,
        metavar="KEY",
        help="the sheet's key (default: FILLED.key.csv or the one key beside it)",
    )


def run(args: Any) -> int:
    """``analyze --rating-sheet`` or ``analyze --ratings`` (see the module docstring)."""
    import random
    import sys

    from humantele.analysis.report import METRICS, analyze, print_report
    from humantele.recording.reader import RecordingReadError

    if args.rating_sheet is not None and args.ratings is not None:
        raise ConfigError("give --rating-sheet (draw a sheet) or --ratings (read one), not both")
    if args.rating_sheet is not None and not args.recordings:
        raise ConfigError("--rating-sheet: give the recordings whose scans are to be rated")
    try:
        if args.rating_sheet is not None:
            raters = [r.strip() for r in args.raters.split(",") if r.strip()]
            if not raters or len(set(raters)) != len(raters) or "clip" in raters:
                raise ConfigError(f"--raters: {args.raters!r}: distinct names, not 'clip'")
            report, _ = analyze(list(args.recordings))
            rng = random.Random(args.seed) if args.seed is not None else None
            clips = draw_clips(report["scans"], rng=rng)
            notes = write_sheet(args.rating_sheet, clips, raters, args.clips)
            for line in report["warnings"] + notes:
                print(f"humantele analyze: {line}", file=sys.stderr)
            print(f"{args.rating_sheet}: {len(clips)} clips to rate (0-5), shuffled; the key "
                  f"(not for raters): {key_path(args.rating_sheet)}")  # fmt: skip
            return 0
        key = read_key(find_key(args.ratings, args.rating_key))
        scores = read_ratings(args.ratings, key)
        report, _ = analyze(list(args.recordings))
        quality, warnings = ratings_quality(scores, key, report["scans"], [m for m, _ in METRICS])
        report["quality"] = quality
        report["warnings"] += warnings
    except RecordingReadError as exc:
        print(f"humantele analyze: {exc}", file=sys.stderr)
        return 2
    print_report(report, args.json)
    return 0
