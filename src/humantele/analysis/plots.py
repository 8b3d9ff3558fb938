"""The study's figures as PNG (matplotlib, Agg backend): trajectories like the paper's Figs. 8-9
(virtual probe solid, follower's tracked probe dotted), quality-score bars (Figs. 5-6), the
NASA-TLX boxplot (Fig. 7) and the usability items.

Orientation is drawn as Euler angles ``xyz`` (extrinsic, about the patient axes, degrees,
unwrapped), for reading only: the error figures use rotation angles, never Euler differences.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from humantele.analysis.questionnaires import (  # noqa: E402
    TLX_SUBSCALES,
    USABILITY_ITEMS,
    Responses,
)
from humantele.analysis.sessions import ScanResult, Session  # noqa: E402

MAX_LINE_POINTS = 5000
_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _euler_deg(q: np.ndarray) -> np.ndarray:
    if len(q) == 0:
        return np.zeros((0, 3))
    return np.degrees(np.unwrap(Rotation.from_quat(q).as_euler("xyz"), axis=0))


def plot_trajectories(session: Session, result: ScanResult, out_dir: Path) -> list[Path]:
    """Position (mm) and orientation (Euler deg) of one scan; returns the two PNG paths."""
    iv = result.interval
    v = session.virtual
    sel = (v.t >= iv.start) & (v.t <= iv.stop)
    step = max(1, int(sel.sum() // MAX_LINE_POINTS))
    tv = v.t[sel][::step] - iv.start
    r = session.real
    rsel = (r.t >= iv.start) & (r.t <= iv.stop)
    tr = r.t[rsel] - iv.start
    stem = f"{session.session_id}_scan{iv.scan}"
    paths = []
    for kind, yv, yr, unit in (
        ("position", v.position[sel][::step] * 1e3, r.position[rsel] * 1e3, "mm"),
        (
            "orientation",
            _euler_deg(v.quaternion[sel][::step]),
            _euler_deg(r.quaternion[rsel]),
            "deg",
        ),
    ):
        fig, ax = plt.subplots(figsize=(8, 4))
        for k, (axis, colour) in enumerate(zip("xyz", _COLOURS, strict=True)):
            ax.plot(tv, yv[:, k], "-", color=colour, lw=1.2, label=f"{axis} virtual")
            ax.plot(tr, yr[:, k], ":", color=colour, lw=1.5, label=f"{axis} follower")
        ax.set_xlabel("time since scan start (s)")
        ax.set_ylabel(f"{kind} ({unit})" if kind == "position" else "Euler angle xyz (deg)")
        ax.set_title(f"scan {iv.scan}: {kind} (virtual solid, follower dotted)")
        ax.legend(ncol=3, fontsize=7)
        fig.tight_layout()
        path = out_dir / f"{stem}_{kind}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_quality_bars(summary: dict, path: Path, title: str) -> Path:
    """Bar chart of how often each score 0-5 was given (all raters), proportions on top."""
    counts = [summary["score_counts"][str(k)] for k in range(6)]
    props = [summary["score_proportions"][str(k)] for k in range(6)]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    bars = ax.bar(range(6), counts, color="tab:blue")
    for bar, p in zip(bars, props, strict=True):
        ax.annotate(
            f"{100 * p:.1f}%",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    ax.set_xticks(range(6))
    ax.set_xlabel("image quality score (0 = not obtained, 5 = good)")
    ax.set_ylabel("number of scores")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_tlx(responses: Responses, path: Path) -> Path:
    """Boxplot of each NASA-TLX subscale with its mean marked and written."""
    fig, ax = plt.subplots(figsize=(7, 3.8))
    data = [responses.values[:, k] for k in range(len(responses.items))]
    ax.boxplot(data, showmeans=True)
    ax.set_xticks(range(1, len(data) + 1), [TLX_SUBSCALES[i] for i in responses.items])
    for k, d in enumerate(data, start=1):
        ax.annotate(f"{d.mean():.1f}", (k, 100), ha="center", va="top", fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("rating (0-100, lower is better)")
    ax.set_title(f"NASA-TLX (n = {len(responses.respondents)})")
    ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_usability(responses: Responses, path: Path) -> Path:
    """Mean +- SD of each usability item (0 strongly disagree .. 4 strongly agree)."""
    v = responses.values
    means = v.mean(axis=0)
    sds = v.std(axis=0, ddof=1) if len(v) > 1 else np.zeros(v.shape[1])
    labels = [
        USABILITY_ITEMS[i][0] + (" (lower is better)" if USABILITY_ITEMS[i][1] else "")
        for i in responses.items
    ]
    fig, ax = plt.subplots(figsize=(8, 4))
    y = np.arange(len(labels))[::-1]
    ax.barh(y, means, xerr=sds, color="tab:green", capsize=3)
    ax.set_yticks(y, labels, fontsize=7)
    ax.set_xlim(0, 4.5)
    ax.set_xlabel("mean score (0 = strongly disagree, 4 = strongly agree)")
    ax.set_title(f"usability (n = {len(responses.respondents)})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
