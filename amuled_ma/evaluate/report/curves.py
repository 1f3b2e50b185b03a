"""Learning curves: each variant's ``curve.json``, a rolling mean, its seeds readable."""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.evaluate.report.plotting import (
    compact_number,
    grid_axes,
    legend_below,
    pyplot,
    robust_ylim,
    variant_colors,
)
from amuled_ma.evaluate.stats import t_quantile
from amuled_ma.files.safe import checked_read_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Curve keys plotted per task (the first that exists in a curve is used).
CURVE_KEYS = {
    "findmilk": ["episode/return_env", "episode/steps_to_milk", "episode/crying_pacified",
                 "episode/sleeping_woken"],
    "driving": ["episode/return_env", "episode/collisions", "episode/rescues",
                "episode/lane_changes"],
}  # fmt: skip
#: Curve keys of a fine-tune's feedback.
FT_KEYS = ["feedback/feedback_reward", "feedback/kl"]
#: Up to this many seeds a variant's seeds are faint lines behind the mean (a t-interval over so
#: few is too wide to read); past it, a 95% band. One seed: its raw values, faint.
MAX_SEED_LINES = 5
#: Opacity of a seed's line (and of one seed's raw values) and of a band over the seeds.
SPREAD_ALPHA = 0.3
BAND_ALPHA = 0.15
#: Largest ``curve.json`` read [bytes]: about 590 an iteration, so some 450,000 iterations.
MAX_CURVE_BYTES = 256 * 2**20


def _rolling_band(arr: np.ndarray, window: int) -> tuple[np.ndarray, ...]:
    mean = np.full_like(arr, np.nan)
    half = np.full_like(arr, np.nan)
    for i in range(len(arr)):
        chunk = arr[max(0, i - window + 1) : i + 1]
        chunk = chunk[np.isfinite(chunk)]
        if len(chunk):
            mean[i] = chunk.mean()
            if len(chunk) > 1:
                half[i] = t_quantile(len(chunk) - 1) * chunk.std(ddof=1) / math.sqrt(len(chunk))
            else:
                half[i] = 0.0
    return mean, half


def load_curves(
    run_dir: Path, names: Mapping[str, str] | None = None
) -> dict[str, list[list[dict]]]:
    """Every variant's ``curve.json``: ``{variant: [replica, ...]}`` (``names``: folder -> variant).

    AmuledError: a ``curve.json`` over `MAX_CURVE_BYTES`, unsafe, unreadable or not JSON.
    """
    from amuled_ma.files.limits import read_bounded_json

    fix = (
        "is it the right folder? It is written by 'amuled train' and 'amuled finetune'; "
        "retrain the variant with --force, or move its folder out of the run"
    )
    names = names or {}
    curves: dict[str, list[list[dict]]] = {}
    run_dir = Path(run_dir)
    for path in sorted(run_dir.glob("*/curve.json")):
        variant = names.get(path.parent.name, path.parent.name)
        checked_read_path(run_dir, path.relative_to(run_dir))
        note = "about 590 bytes an iteration"
        curve = read_bounded_json(path, MAX_CURVE_BYTES, "learning curve", note=note, fix=fix)
        curves.setdefault(variant, []).append(curve)
    return curves


def curve_band(
    replicas: list[list[dict]], key: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """x, mean and 95% half-width of one metric over a variant's replicas, and each one's line.

    Each curve is smoothed by a rolling mean over 5% of its iterations; one replica: the
    t-interval over that window, its line the raw values; several: the t-interval over the seeds
    (cut to the shortest), each line its rolling mean.
    """
    n = min(len(c) for c in replicas)
    x = np.array([row["env_steps"] for row in replicas[0][:n]], dtype=float)
    raw = [
        np.array([np.nan if (v := row.get(key)) is None else v for row in c[:n]], dtype=float)
        for c in replicas
    ]
    bands = [_rolling_band(values, max(1, n // 20)) for values in raw]
    if len(bands) == 1:
        return x, bands[0][0], bands[0][1], raw
    means = np.stack([mean for mean, _ in bands])
    # Iterations where no seed logged the metric (NaN everywhere) stay NaN, silently.
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        count = np.isfinite(means).sum(axis=0)
        mean = np.nanmean(np.where(np.isfinite(means), means, np.nan), axis=0)
        std = np.nanstd(means, axis=0, ddof=1)
        quantile = np.array([t_quantile(int(k) - 1) if k > 1 else 0.0 for k in count])
        half = np.where(count > 1, quantile * std / np.sqrt(np.maximum(count, 1)), 0.0)
    return x, mean, half, list(means)


def curves_figure(
    curves: dict[str, list[list[dict]]],
    keys: list[str],
    title: str,
    colors: dict[str, str] | None = None,
) -> Figure | None:
    """One panel per key, one line per variant; None when nothing to draw."""
    keys = [k for k in keys if any(k in row for cs in curves.values() for c in cs for row in c)]
    if not keys or not curves:
        return None
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    colors = colors or variant_colors(curves)
    plt = pyplot()
    fig, axes = grid_axes(plt, len(keys), 3, 4.3, 3.2)
    legend: dict[str, Any] = {}
    bands: list[tuple] = []
    for ax, key in zip(axes, keys, strict=False):
        lines, spread = [], []
        for name, replicas in curves.items():
            if not any(key in row for c in replicas for row in c):
                continue
            x, mean, half, each = curve_band(replicas, key)
            label = name if len(replicas) == 1 else f"{name} ({len(replicas)} seeds)"
            colour = colors.get(name)
            if len(replicas) <= MAX_SEED_LINES:
                gid = "raw-line" if len(replicas) == 1 else "seed-line"
                for values in each:
                    ax.plot(x, values, lw=0.8, color=colour, alpha=SPREAD_ALPHA, gid=gid,
                            zorder=1)  # fmt: skip
                if len(replicas) > 1:  # one seed's raw values do not set the range
                    spread += each
            else:
                bands.append((ax, x, mean, half, colour))
            (line,) = ax.plot(x, mean, label=label, lw=1.8, color=colour, gid="mean-line",
                              zorder=3)  # fmt: skip
            legend.setdefault(label, line)
            lines.append(mean)
        heading = key.split("/", 1)[-1].replace("_", " ")
        limits = robust_ylim(lines + spread)
        for band_ax, x, mean, half, colour in [b for b in bands if b[0] is ax]:
            low, high = mean - half, mean + half
            if limits is not None:  # a band is cut to the panel: it never fills it
                low, high = np.maximum(low, limits[0]), np.minimum(high, limits[1])
            band_ax.fill_between(x, low, high, color=colour, alpha=BAND_ALPHA, lw=0,
                                 gid="seed-band", zorder=2)  # fmt: skip
        if limits is not None:
            ax.set_ylim(limits[0], limits[1])
            if limits[2]:
                heading += f"\n({limits[2]})"
        ax.set_title(heading, fontsize=9)
        ax.set_xlabel("environment steps", fontsize=8)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5, integer=True))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _pos: compact_number(value)))
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    spare = axes[len(keys) :]
    seeds = {len(r) for r in curves.values()}
    notes = [  # what the faint lines or bands are
        (1 in seeds, "one seed: faint, its raw values"),
        (
            any(1 < k <= MAX_SEED_LINES for k in seeds),
            "bold: the mean over seeds, faint: each seed",
        ),
        (any(k > MAX_SEED_LINES for k in seeds), "band: 95% interval over seeds"),
    ]
    fig.suptitle(f"{title}: rolling mean over 5% of iterations; "
                 + "; ".join(text for shown, text in notes if shown), fontsize=9)  # fmt: skip
    legend_below(fig, list(legend.values()), list(legend), spare)
    return fig
