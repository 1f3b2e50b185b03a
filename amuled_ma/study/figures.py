"""The study report's figures (PNG, Agg backend), drawn from ``summary.json``'s data only."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from amuled_ma.evaluate.report.plotting import pyplot, save_figure


def _interval_bars(ax: Any, names: Sequence[str], rows: Sequence[Mapping[str, Any]],
                   key: str) -> None:  # fmt: skip
    """Points with horizontal 95% intervals, one row per name (top to bottom)."""
    ys = list(range(len(names)))[::-1]
    for y, row in zip(ys, rows, strict=True):
        value, low, high = row[key], row["low"], row["high"]
        if value is None or not math.isfinite(value):
            ax.text(0.02, y, "no data", va="center", transform=ax.get_yaxis_transform())
            continue
        if low is not None and math.isfinite(low) and math.isfinite(high):
            ax.plot([low, high], [y, y], color="#555", lw=2, solid_capstyle="butt")
        ax.plot([value], [y], "o", color="#1d3557", ms=7)
        ax.annotate(f"{value:.2f}", (value, y), textcoords="offset points", xytext=(0, 7),
                    ha="center", fontsize=8)  # fmt: skip
    ax.set_yticks(ys, list(names))
    ax.set_ylim(-0.7, len(names) - 0.3)
    ax.grid(axis="x", color="#ddd")


def strengths_figure(summary: Mapping[str, Any], path: Path) -> Path:
    """``strengths.png``: Bradley-Terry strengths and mean acceptability, with intervals."""
    plt = pyplot()
    bt = summary["bradley_terry"]
    acc = summary.get("acceptability") or []
    panels = 2 if acc else 1
    names = [row["variant"] for row in bt]
    fig, axes = plt.subplots(1, panels, figsize=(4.4 * panels + 0.6, 0.55 * len(names) + 1.8),
                             squeeze=False)  # fmt: skip
    ax = axes[0][0]
    _interval_bars(ax, names, bt, "strength")
    ax.axvline(0.0, color="#999", lw=1, ls="--")
    ax.set_xlabel("Bradley-Terry strength (log scale, mean 0)")
    ax.set_title("Chosen as the more acceptable", fontsize=10)
    if acc:
        ax = axes[0][1]
        _interval_bars(ax, [row["variant"] for row in acc], acc, "mean")
        points = int(summary.get("rating_points") or 7)
        ax.set_xlim(0.5, points + 0.5)
        ax.set_xticks(range(1, points + 1))
        ax.set_xlabel(f"mean rating (1: completely unacceptable,\n{points}: completely "
                      "acceptable)")  # fmt: skip
        ax.set_title("Rated acceptability", fontsize=10)
    fig.suptitle("Variants as people judged them (95% bootstrap intervals over participants)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    return save_figure(fig, path)


def expert_figure(summary: Mapping[str, Any], path: Path) -> Path:
    """``expert.png``: frameworks cited, and agreement with the experts' acceptable sets."""
    plt = pyplot()
    cites = summary["frameworks"]
    agree = summary["agreement"]
    who = sorted(agree)
    height = max(len(cites), len(who)) * 0.45 + 1.8
    fig, (left, right) = plt.subplots(1, 2, figsize=(10.5, height))
    names = [c["framework"] for c in cites][::-1]
    yes = [c["acceptable"] for c in cites][::-1]
    no = [c["cited"] - c["acceptable"] for c in cites][::-1]
    left.barh(names, yes, color="#2a9d8f", label="action found acceptable")
    left.barh(names, no, left=yes, color="#e76f51", label="found unacceptable")
    left.set_xlabel("judgements citing the framework")
    left.set_title("Frameworks the experts cite", fontsize=10)
    left.legend(fontsize=8, loc="lower right")
    rows = [agree[w] for w in who]
    _interval_bars(right, who, rows, "rate")
    right.set_xlim(-0.02, 1.02)
    right.set_xlabel("share of states where its top action\nis acceptable to the experts")
    right.set_title("Agreement with the experts (Wilson 95%)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
