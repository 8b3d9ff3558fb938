"""The study's charts (matplotlib, Agg, PNG): alignment error against one-way delay with the
750 km study marked, video freezes against loss, and (conditions capping the link's rate) the
US picture's share live, age and SSIM against the rate, per loss."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from humantele.study.table import BOUND, STUDY, STUDY_ONE_WAY_MS  # noqa: E402


def _series(summary: list[dict], x: str, y: str) -> tuple[list, list, list]:
    pts = [(s[x], s[y], s.get(f"{y}_sd") or 0.0) for s in summary if s.get(y) is not None]
    pts.sort()
    return [p[0] for p in pts], [p[1] for p in pts], [p[2] for p in pts]


def alignment_vs_delay(summary: list[dict], path: Path) -> Path:
    """Position RMSE and centered RMSE (mean ± SD over each condition's scans) against the
    one-way delay, for the conditions without loss or a bandwidth cap; the 750 km study's
    figures at its one-way propagation delay; the study's bound (its worst scan) dashed."""
    clean = [s for s in summary if not s["loss_pct"] and not s["bandwidth_kbps"]]
    fig, ax = plt.subplots(figsize=(7.5, 4.3))
    for key, colour, label in (
        ("position_rmse_mm", "tab:blue", "position RMSE (simulated follower)"),
        ("centered_position_rmse_mm", "tab:orange", "centered position RMSE (simulated)"),
    ):
        x, y, sd = _series(clean, "delay_ms", key)
        ax.errorbar(x, y, yerr=sd, fmt="o-", color=colour, capsize=3, label=label)
        mean, study_sd = STUDY[key]
        ax.errorbar([STUDY_ONE_WAY_MS], [mean], yerr=[study_sd], fmt="*", ms=14,
                    color=colour, mec="black", capsize=4)  # fmt: skip
        kind = " (centered)" if "centered" in key else ""
        ax.axhline(BOUND[key], color=colour, ls="--", lw=0.9,
                   label=f"bound: the study's worst scan{kind}, {BOUND[key]:g} mm")  # fmt: skip
    ax.annotate(
        f"750 km study (human followers,\nTable II): >= {STUDY_ONE_WAY_MS:.1f} ms one way",
        (STUDY_ONE_WAY_MS, STUDY["position_rmse_mm"][0]), xytext=(40, 25),
        textcoords="offset points", fontsize=8, arrowprops={"arrowstyle": "->", "lw": 0.8},
    )  # fmt: skip
    ax.set_xlabel("one-way delay added each way (ms)")
    ax.set_ylabel("alignment error (mm)")
    ax.set_title("Follower alignment against network delay (whole sessions, simulated follower)")
    ax.set_ylim(bottom=0)
    ax.set_ylim(0, max(ax.get_ylim()[1], BOUND["position_rmse_mm"] * 1.25))
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def freezes_vs_loss(summary: list[dict], path: Path) -> Path:
    """Share of each scan the expert's US and POV pictures were frozen (mean ± SD) against
    the loss each way, for every condition (the delay, and a cap, written beside each point)."""
    fig, ax = plt.subplots(figsize=(7.5, 4.3))
    for key, colour, label in (
        ("us_frozen_pct", "tab:green", "ultrasound"),
        ("pov_frozen_pct", "tab:purple", "point of view"),
    ):
        x, y, sd = _series(summary, "loss_pct", key)
        ax.errorbar(x, y, yerr=sd, fmt="o", color=colour, capsize=3, label=label)
    for s in summary:
        if s.get("us_frozen_pct") is not None:
            cap = f", {s['bandwidth_kbps']:g} kbit/s" if s["bandwidth_kbps"] else ""
            ax.annotate(f"{s['delay_ms']:g} ms{cap}", (s["loss_pct"], s["us_frozen_pct"]),
                        xytext=(4, 3), textcoords="offset points", fontsize=6)  # fmt: skip
    ax.set_xlabel("datagrams lost each way (%)")
    ax.set_ylabel("time frozen at the expert (% of the scan)")
    ax.set_title("Video freezes against loss (WebRTC freeze definition)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


US_PANELS = (  # key, title, axis range, the figure's own bounds (its SD bars clipped to them)
    ("us_live_pct", "US picture live (% of the scan)", (0, 102), (0.0, 100.0)),
    ("us_age_p95_ms", "US glass-to-glass age p95 (ms)", None, (0.0, None)),
    ("us_ssim", "US SSIM against the captured frame", None, (0.0, 1.0)),
)


def clipped_errors(
    y: list[float], sd: list[float], low: float | None, high: float | None
) -> list[list[float]]:
    """Error bars (below, above) of mean ± SD for a figure bounded to [low, high] (None: no
    bound): each bar stops at the bound (a share live cannot pass 100 %, an SSIM 1)."""
    below = [e if low is None else max(0.0, min(e, v - low)) for v, e in zip(y, sd, strict=True)]
    above = [e if high is None else max(0.0, min(e, high - v)) for v, e in zip(y, sd, strict=True)]
    return [below, above]


def us_over_thin_links(summary: list[dict], path: Path) -> Path:
    """The US picture against the link's rate, one line per loss (mean ± SD over each
    condition's scans, the SD bars clipped to each figure's bounds): its share of the scan
    live (not frozen), its glass-to-glass age p95 and its quality (SSIM against the frame the
    follower captured). Conditions with a rate cap only; the delay of each line in its
    legend."""
    capped = [s for s in summary if s.get("bandwidth_kbps")]
    losses = sorted({s["loss_pct"] for s in capped})
    fig, axes = plt.subplots(1, 3, figsize=(12.0, 4.0))
    colours = plt.get_cmap("viridis")
    for i, loss in enumerate(losses):
        mine = [s for s in capped if s["loss_pct"] == loss]
        delays = sorted({f"{s['delay_ms']:g}" + (f" ± {s['jitter_ms']:g}" if s.get("jitter_ms")
                         else "") for s in mine})  # fmt: skip
        label = f"{loss:g} % loss ({', '.join(delays)} ms)"
        colour = colours(i / max(1, len(losses) - 1) * 0.85)
        for ax, (key, _, _, bounds) in zip(axes, US_PANELS, strict=True):
            x, y, sd = _series(mine, "bandwidth_kbps", key)
            err = clipped_errors(y, sd, *bounds)
            ax.errorbar(x, y, yerr=err, fmt="o-", color=colour, capsize=3, label=label)
    for ax, (_key, title, ylim, _bounds) in zip(axes, US_PANELS, strict=True):
        ax.set_xscale("log")
        ticks = sorted({s["bandwidth_kbps"] for s in capped})
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.minorticks_off()
        ax.set_xlabel("link rate each way (kbit/s)")
        ax.set_title(title, fontsize=9)
        if ylim:
            ax.set_ylim(*ylim)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle("The ultrasound over thin, lossy links: speed against quality (mean ± SD of "
                 "the scans, clipped to each figure's range)", fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_charts(summary: list[dict], out_dir: Path) -> list[Path]:
    """The charts the conditions allow: alignment against delay and freezes against loss
    always; the US over thin links when at least two conditions cap the rate."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [
        alignment_vs_delay(summary, out_dir / "study_alignment_vs_delay.png"),
        freezes_vs_loss(summary, out_dir / "study_freezes_vs_loss.png"),
    ]
    if sum(1 for s in summary if s.get("bandwidth_kbps")) >= 2:
        paths.append(us_over_thin_links(summary, out_dir / "study_us_thin_links.png"))
    return paths
