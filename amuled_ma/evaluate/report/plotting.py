"""The report's figures' common ground: numbers, colours, panels, the PNG files."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, overload

import numpy as np
import numpy.typing as npt

from amuled_ma.evaluate.results import Stat
from amuled_ma.files.safe import atomic_writer

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Two means closer than this are "equal" (the difference table and the equals-base note).
EQUAL_TOL = 1e-9
_DPI = 110


def pyplot() -> ModuleType:
    """Matplotlib's pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def format_stat(stat: Stat | Mapping[str, Any] | None, digits: int = 2) -> str:
    """``mean ± half width`` of a `mean_ci` summary (``n/a``; ``± n/a (n = 1)``)."""
    if stat is not None and not isinstance(stat, Stat):
        stat = Stat.model_validate(dict(stat))
    mean = mean_of(stat)
    if stat is None or not math.isfinite(mean):
        return "n/a"
    half = stat.half_width
    if half is None or not math.isfinite(half):
        return f"{mean:.{digits}f} ± n/a (n = {'?' if stat.n is None else stat.n})"
    return f"{mean:.{digits}f} ± {half:.{digits}f}"


def compact_number(value: float) -> str:
    """A tick label that stays short: ``950``, ``10k``, ``12.5k``, ``1.25M``."""
    magnitude = abs(value)
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if magnitude >= scale:
            return f"{value / scale:.3g}{suffix}"
    return f"{value:.3g}" if magnitude else "0"


def short_label(value: float) -> str:
    """A bar's value label: 3 significant figures at most, no exponent below 1e6."""
    magnitude = abs(value)
    if magnitude <= EQUAL_TOL:
        return "0"
    if magnitude >= 100:
        return f"{value:.0f}"
    if magnitude >= 10:
        return f"{value:.1f}"
    return f"{value:.2f}"


def variant_colors(names: Iterable[str]) -> dict[str, str]:
    """One ``#rrggbb`` per variant whatever their order: sorted names take tab10 (past 10 tab20)."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    unique = sorted(set(names))
    if len(unique) <= 10:
        palette = [colormaps["tab10"](i) for i in range(10)]
    else:
        tab20 = colormaps["tab20"]
        palette = [tab20(i) for i in (*range(0, 20, 2), *range(1, 20, 2))]
    return {name: to_hex(palette[i % len(palette)]) for i, name in enumerate(unique)}


def robust_ylim(
    series: Sequence[npt.ArrayLike],
    *,
    skip: float = 0.1,
    percentiles: tuple[float, float] = (2.0, 98.0),
    reach: float = 1.0,
    pad: float = 0.08,
) -> tuple[float, float, str] | None:
    """A y-range for learning curves that early spikes do not squash; None without a finite value.

    The core range is the ``percentiles`` of the values after each series' first ``skip``
    share, widened to every value within ``reach`` core ranges (a flat core counts as
    ``max(0.1 * |value|, 0.5)``), plus ``pad`` on each side. Returns ``(low, high, note)``,
    ``note`` saying which values are clipped, or ``""``.
    """
    arrays = [np.asarray(s, dtype=float) for s in series]
    starts = [math.floor(skip * len(a)) for a in arrays]
    every = np.concatenate([*arrays, np.empty(0)])
    every = every[np.isfinite(every)]
    if not every.size:
        return None
    tail = np.concatenate([*(a[k:] for a, k in zip(arrays, starts, strict=True)), np.empty(0)])
    tail = tail[np.isfinite(tail)]
    core = np.percentile(tail if tail.size else every, percentiles, method="nearest")
    low, high = float(core[0]), float(core[1])
    width = high - low if high > low else max(0.1 * abs(low), 0.5)
    near = every[(every >= low - reach * width) & (every <= high + reach * width)]
    low, high = float(near.min()), float(near.max())
    margin = pad * (high - low) if high > low else max(0.1 * abs(low), 0.5)
    low, high = low - margin, high + margin
    above = below = False
    early_only = True
    for a, k in zip(arrays, starts, strict=True):
        with np.errstate(invalid="ignore"):
            out_high, out_low = a > high, a < low
        above |= bool(out_high.any())
        below |= bool(out_low.any())
        if (out_high | out_low)[k:].any():
            early_only = False
    if not (above or below):
        return low, high, ""
    side = "above and below" if above and below else "above" if above else "below"
    return low, high, f"{'early ' if early_only else ''}values {side} the range clipped"


def grid_axes(
    plt: ModuleType, n: int, cols: int, width: float, height: float, **kwargs: Any
) -> tuple[Figure, list[Axes]]:
    """A figure of ``n`` panels, ``cols`` wide: ``(figure, [axes])``, spare axes past ``n`` off."""
    cols = max(1, min(cols, n))
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(width * cols, height * rows), squeeze=False,
        layout="constrained", **kwargs,
    )  # fmt: skip
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, list(axes.flat)


def legend_below(fig: Figure, handles: list, labels: list[str], spare: list) -> None:
    """The figure's one legend: in the first unused panel, else below the panels."""
    if not handles:
        return
    if spare:
        spare[0].legend(handles, labels, loc="center", fontsize=8, frameon=False)
        return
    fig.legend(
        handles, labels, loc="outside lower center", ncol=min(4, len(labels)), fontsize=8,
        frameon=False,
    )  # fmt: skip


@overload
def save_figure(fig: Figure, path: Path) -> Path: ...
@overload
def save_figure(fig: Figure | None, path: Path) -> Path | None: ...
def save_figure(fig: Figure | None, path: Path) -> Path | None:
    """Write a figure as PNG by `atomic_writer` (UnsafePathError, FileWriteError) and close it.

    Returns ``path``; None, writing nothing, when ``fig`` is None (no data to draw).
    """
    if fig is None:
        return None
    plt = pyplot()
    try:
        with atomic_writer(path) as handle:
            fig.savefig(handle, format="png", dpi=_DPI)
    finally:
        plt.close(fig)
    return path


def mean_of(stat: Stat | None) -> float:
    """A statistic's mean; NaN when there is none."""
    value = None if stat is None else stat.mean
    return float(value) if value is not None else math.nan


def half_of(stat: Stat | None) -> float:
    """A statistic's half width for an error bar (0 where the interval is undefined)."""
    value = None if stat is None else stat.half_width
    return value if value is not None and math.isfinite(value) else 0.0
