"""The run report: ``report.md`` with PNG figures (matplotlib, headless).

The report opens with the run's settings (task, recipe, lambda_KL, iterations, seeds, the
panel and its sources, the recording and its SHA-256) and a link to the step-by-step
viewer (``amuled view``). Then the metric tables (greedy and sampled) with each variant's
difference to the base policy and a sentence for every fine-tune whose greedy policy
scores exactly as the base one, each fine-tune's feedback, the fused-belief diagnostics,
how often each panel agent answered, abstained or missed the replay and, for fine-tunes
with ``[feedback.distill]``, the feedback budget's accounting (states asked, answered by
the distilled model, requests sent, the model's agreement with the panel).

Figures, one colour per variant in all of them (:func:`variant_colors`): learning curves
with 95% bands (y-range robust to early spikes, :func:`robust_ylim`), the metrics as bars
with 95% CIs and value labels (a bar of height 0 gets a marker), one greedy trajectory per
variant (FindMilk: the grid with the path, the milk and each baby pacified or woken;
Driving: one strip of lanes and events per variant) and, in an ablation folder, the
ablation's own figure (each variant vs AMULED on the paper's metrics, sorted; lambda_KL
sweeps as metric against lambda_KL; budget sweeps as metric against the budget).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.beliefs.types import FUSED_STATUSES
from amuled_ma.evaluate.evaluator import PAPER_METRICS, metric_order
from amuled_ma.evaluate.stats import t_quantile
from amuled_ma.experiments.run_folder import split_replica

#: Curve keys plotted per task (the first that exists in a curve is used).
_CURVE_KEYS = {
    "findmilk": ["episode/return_env", "episode/steps_to_milk", "episode/crying_pacified",
                 "episode/sleeping_woken"],
    "driving": ["episode/return_env", "episode/collisions", "episode/rescues",
                "episode/lane_changes"],
}  # fmt: skip
_FT_KEYS = ["feedback/feedback_reward", "feedback/kl"]

#: Two means closer than this are "equal" (the difference table and the equals-base note).
EQUAL_TOL = 1e-9
#: Metrics left out of the bar charts (book-keeping, or the shaping the base never sees).
_NOT_PLOTTED = ("terminated", "return_shaping", "return")
#: The figures :func:`write_report` writes; one of these it did not write this time is a
#: stale one from an earlier report and is removed, so every PNG is the report's.
FIGURE_NAMES = (
    "curves_base.png", "curves_finetune.png", "metrics_greedy.png", "metrics_sampled.png",
    "trajectory_findmilk.png", "episode_driving.png",
)  # fmt: skip
#: The viewer page ``amuled view`` writes by default (episode 0).
VIEWER_PAGE = "view-episode0.html"
#: How the report's viewer line starts (:func:`link_viewer` finds it by this).
VIEWER_PREFIX = "**Step by step:**"
_DPI = 110


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------------------------------
# Numbers and colours


def format_stat(stat: dict[str, Any] | None, digits: int = 2) -> str:
    """``mean ± half width`` of a :func:`~amuled_ma.evaluate.stats.mean_ci` summary.

    ``n/a`` without a mean; ``± n/a (n = 1)`` where the interval is undefined.
    """
    if not stat or stat.get("mean") is None or not math.isfinite(stat["mean"]):
        return "n/a"
    half = stat.get("half_width")
    if half is None or not math.isfinite(half):
        return f"{stat['mean']:.{digits}f} ± n/a (n = {stat.get('n', '?')})"
    return f"{stat['mean']:.{digits}f} ± {half:.{digits}f}"


def compact_number(value: float) -> str:
    """A tick label that stays short: ``950``, ``10k``, ``12.5k``, ``1.25M``.

    Args:
        value: The tick's value.

    Returns:
        The label (at most 3 significant digits past the first thousand).

    """
    magnitude = abs(value)
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if magnitude >= scale:
            return f"{value / scale:.3g}{suffix}"
    return f"{value:.3g}" if magnitude else "0"


def _short(value: float) -> str:
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
    """One fixed colour per variant: the sorted names take matplotlib's tab10 in turn.

    The same names give the same colours whatever their order, so a report's figures
    (curves, bars, trajectories, the ablation's) all draw a variant in one colour. Past
    ten variants the palette is tab20 with its ten dark shades first, then the light ones.

    Args:
        names: The variants (repeats are ignored).

    Returns:
        ``{name: "#rrggbb"}``.

    """
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
    series: Sequence[Sequence[float]],
    *,
    skip: float = 0.1,
    percentiles: tuple[float, float] = (2.0, 98.0),
    reach: float = 1.0,
    pad: float = 0.08,
) -> tuple[float, float, str] | None:
    """A y-range for learning curves that early spikes do not squash.

    The core range is the 2nd to 98th percentile (nearest value) of all series' values
    after their first 10% of points: the first 5% and the 5% rolling window that carries
    them into the smoothed line. It is widened to every value (early ones too) within one
    core range of it, so a curve's genuine ramp or late extreme stays in view and only a far
    outlier (a spike of the first iterations) is left out; then a margin of 8% is added.

    Args:
        series: The plotted lines (NaN points are ignored).
        skip: Share of each series' first points left out of the percentiles.
        percentiles: Lower and upper percentile of the core range.
        reach: Values within ``reach`` core ranges of it are kept in view (a flat core
            counts as ``max(0.1 * |value|, 0.5)`` wide).
        pad: Margin on each side, as a share of the range.

    Returns:
        ``(low, high, note)``: ``note`` says which values fall outside and are clipped
        (``"early values above the range clipped"``, ``"values below the range
        clipped"``, ...), or is ``""``. None without a finite value.

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


# ---------------------------------------------------------------------------------------
# Learning curves


def _rolling_band(values: list[float | None], window: int) -> tuple[np.ndarray, ...]:
    arr = np.array([np.nan if v is None else v for v in values], dtype=float)
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


def load_curves(run_dir: Path) -> dict[str, list[list[dict]]]:
    """Read every variant's ``curve.json``, seed replicas grouped under their variant."""
    curves: dict[str, list[list[dict]]] = {}
    for path in sorted(Path(run_dir).glob("*/curve.json")):
        variant = split_replica(path.parent.name)[0]
        curves.setdefault(variant, []).append(json.loads(path.read_text()))
    return curves


def curve_band(replicas: list[list[dict]], key: str) -> tuple[np.ndarray, ...]:
    """x, mean and 95% half-width of one metric over a variant's replicas.

    Each replica's curve is first smoothed by a rolling mean over 5% of its iterations.
    One replica: the band is the t-interval over that window. Several: the mean over the
    seeds and the t-interval over the seeds (curves cut to the shortest).
    """
    n = min(len(c) for c in replicas)
    x = np.array([row["env_steps"] for row in replicas[0][:n]], dtype=float)
    window = max(1, n // 20)
    bands = [_rolling_band([row.get(key) for row in c[:n]], window) for c in replicas]
    if len(bands) == 1:
        return x, bands[0][0], bands[0][1]
    means = np.stack([mean for mean, _ in bands])
    # Iterations where no seed logged the metric (NaN everywhere) stay NaN, silently.
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        count = np.isfinite(means).sum(axis=0)
        mean = np.nanmean(np.where(np.isfinite(means), means, np.nan), axis=0)
        std = np.nanstd(means, axis=0, ddof=1)
        quantile = np.array([t_quantile(int(k) - 1) if k > 1 else 0.0 for k in count])
        half = np.where(count > 1, quantile * std / np.sqrt(np.maximum(count, 1)), 0.0)
    return x, mean, half


def _grid(plt: Any, n: int, cols: int, width: float, height: float, **kwargs: Any) -> tuple:
    cols = max(1, min(cols, n))
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(width * cols, height * rows), squeeze=False,
        layout="constrained", **kwargs,
    )  # fmt: skip
    return fig, list(axes.flat)


def _legend_below(fig: Any, handles: list, labels: list[str], spare: list) -> None:
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


def curves_figure(
    curves: dict[str, list[list[dict]]],
    keys: list[str],
    title: str,
    colors: dict[str, str] | None = None,
) -> Any | None:
    """The learning-curve figure (see :func:`plot_curves`); None when nothing to draw."""
    keys = [k for k in keys if any(k in row for cs in curves.values() for c in cs for row in c)]
    if not keys or not curves:
        return None
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    colors = colors or variant_colors(curves)
    plt = _plt()
    fig, axes = _grid(plt, len(keys), 3, 4.3, 3.2)
    legend: dict[str, Any] = {}
    for ax, key in zip(axes, keys, strict=False):
        lines = []
        for name, replicas in curves.items():
            if not any(key in row for c in replicas for row in c):
                continue
            x, mean, half = curve_band(replicas, key)
            label = name if len(replicas) == 1 else f"{name} ({len(replicas)} seeds)"
            (line,) = ax.plot(x, mean, label=label, lw=1.5, color=colors.get(name))
            ax.fill_between(x, mean - half, mean + half, color=line.get_color(), alpha=0.2, lw=0)
            legend.setdefault(label, line)
            lines.append(mean)
        heading = key.split("/", 1)[-1].replace("_", " ")
        limits = robust_ylim(lines)
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
    for ax in spare:
        ax.axis("off")
    several = any(len(r) > 1 for r in curves.values())
    band = "over seeds" if several else "over a 5% window of iterations"
    fig.suptitle(f"{title} (rolling mean over 5% of iterations, 95% band {band})", fontsize=9)
    _legend_below(fig, list(legend.values()), list(legend), spare)
    return fig


def _save(fig: Any, path: Path) -> Path:
    plt = _plt()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_curves(
    curves: dict[str, list[list[dict]]],
    keys: list[str],
    path: Path,
    title: str,
    colors: dict[str, str] | None = None,
) -> Path | None:
    """Plot one panel per key, one line (rolling mean, 95% band) per variant.

    The y-range of each panel is :func:`robust_ylim` of its lines (the panel's title says
    when values are clipped); x ticks are compact (``20k``).

    Args:
        curves: ``{variant: [replica curve, ...]}`` (:func:`load_curves`).
        keys: Curve keys, one panel each (missing ones are skipped).
        path: The PNG to write.
        title: The figure's title.
        colors: ``{variant: colour}`` (default: :func:`variant_colors` of the curves).

    Returns:
        ``path``, or None when no key has data.

    """
    fig = curves_figure(curves, keys, title, colors)
    return None if fig is None else _save(fig, path)


# ---------------------------------------------------------------------------------------
# Bars


def _hbars(
    ax: Any,
    positions: Sequence[float],
    stats: Sequence[dict[str, Any] | None],
    colors: Sequence[str],
    *,
    emphasise: Sequence[bool] | None = None,
) -> None:
    """Horizontal bars with 95% CI whiskers and value labels; a zero bar gets a marker.

    A bar of height 0 would be invisible: it is drawn as a thick tick of its colour at 0
    (``gid="zero-bar"``) with its label ``0``; a missing mean is labelled ``n/a``.
    """
    means = np.array([_mean(s) for s in stats], dtype=float)
    errs = np.array([_finite_or_zero((s or {}).get("half_width")) for s in stats])
    drawn = np.where(np.isfinite(means), means, 0.0)
    bold = list(emphasise or [False] * len(stats))
    ax.barh(
        positions, drawn, xerr=errs, height=0.72, color=colors,
        edgecolor=["black" if b else c for b, c in zip(bold, colors, strict=True)],
        linewidth=[1.8 if b else 0.8 for b in bold],
        error_kw={"capsize": 2, "elinewidth": 1.0, "ecolor": "0.25"},
    )  # fmt: skip
    ax.axvline(0.0, color="0.35", lw=0.8, zorder=1)
    for pos, mean, err, color in zip(positions, means, errs, colors, strict=True):
        if not math.isfinite(mean):
            ax.annotate("n/a", (0, pos), xytext=(4, 0), textcoords="offset points",
                        va="center", fontsize=7, color="0.4", gid="bar-label")  # fmt: skip
            continue
        if abs(mean) <= EQUAL_TOL:
            ax.plot([0.0], [pos], marker="|", markersize=12, markeredgewidth=3.0,
                    color=color, zorder=4, gid="zero-bar")  # fmt: skip
        right = mean >= 0
        ax.annotate(
            _short(mean), (mean + err if right else mean - err, pos),
            xytext=(4 if right else -4, 0), textcoords="offset points",
            ha="left" if right else "right", va="center", fontsize=7, gid="bar-label",
        )  # fmt: skip
    reach = np.abs(drawn) + errs
    if not reach.size or float(reach.max()) <= EQUAL_TOL:
        ax.set_xlim(-0.15, 1.0)
    else:
        ax.margins(x=0.25)


def _mean(stat: dict[str, Any] | None) -> float:
    value = (stat or {}).get("mean")
    return float(value) if value is not None else math.nan


def _finite_or_zero(value: float | None) -> float:
    """An error bar's half width; an undefined interval (one value) draws none."""
    return value if value is not None and math.isfinite(value) else 0.0


def _plotted_metrics(results: dict[str, Any], variants: dict[str, Any]) -> list[str]:
    metrics = metric_order(
        results.get("task", ""), sorted({m for v in variants.values() for m in v["metrics"]})
    )
    return [m for m in metrics if m not in _NOT_PLOTTED]


def bars_figure(
    results: dict[str, Any], mode: str, title: str = "", colors: dict[str, str] | None = None
) -> Any | None:
    """The metrics bar figure (see :func:`plot_bars`); None without that mode."""
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    metrics = _plotted_metrics(results, variants)
    if not metrics:
        return None
    names = list(variants)
    colors = colors or variant_colors(names)
    plt = _plt()
    height = 0.3 * len(names) + 1.1
    fig, axes = _grid(plt, len(metrics), 3, 3.3, height, sharey=True)
    fig.set_size_inches(fig.get_size_inches()[0] + 1.8, fig.get_size_inches()[1] + 0.4)
    positions = np.arange(len(names))[::-1]  # the first variant on top
    for ax, metric in zip(axes, metrics, strict=False):
        stats = [variants[n]["metrics"].get(metric) for n in names]
        _hbars(ax, positions, stats, [colors[n] for n in names])
        ax.set_title(metric.replace("_", " "), fontsize=9)
        ax.set_yticks(positions, names, fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    for ax in axes[len(metrics) :]:
        ax.axis("off")
    fig.suptitle(
        title
        or f"{results.get('scenario')}: {mode} policy, mean and 95% CI "
        "(a bar of height 0: a thick tick at 0)",
        fontsize=9,
    )
    return fig


def plot_bars(
    results: dict[str, Any],
    mode: str,
    path: Path,
    title: str = "",
    colors: dict[str, str] | None = None,
) -> Path | None:
    """Bar chart per metric, one horizontal bar per variant, 95% CI whiskers, value labels.

    Args:
        results: The evaluation results.
        mode: ``greedy`` or ``sampled``.
        path: The PNG to write.
        title: The figure's title (default: scenario, mode).
        colors: ``{variant: colour}`` (default: :func:`variant_colors` of the variants).

    Returns:
        ``path``, or None when no variant was evaluated in ``mode``.

    """
    fig = bars_figure(results, mode, title, colors)
    return None if fig is None else _save(fig, path)


def ablation_figure(
    results: dict[str, Any],
    what: str,
    colors: dict[str, str] | None = None,
    mode: str = "greedy",
) -> Any | None:
    """An ablation's own figure: its fine-tunes against AMULED on the paper's metrics.

    ``kl``: each paper metric against lambda_KL (one point per fine-tune, 95% CI). Other
    ablations: one panel per paper metric, the fine-tunes as horizontal bars sorted by
    their mean (largest on top), AMULED outlined in black. The base policy is a dashed
    line in every panel.

    Args:
        results: The ablation's evaluation results.
        what: ``clusters``, ``aggregation``, ``models`` or ``kl``.
        colors: ``{variant: colour}``.
        mode: Which policy mode.

    Returns:
        The figure, or None without a fine-tune.

    """
    if what == "budget":
        return budget_figure(results, mode)
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    base = variants.pop("base", None)
    tunes = {k: v for k, v in variants.items() if k != "shaped"}
    if not tunes:
        return None
    task = results.get("task", "")
    metrics = [
        m for m in PAPER_METRICS.get(task, []) if any(m in v["metrics"] for v in tunes.values())
    ]
    metrics = metrics or _plotted_metrics(results, tunes)[:4]
    colors = colors or variant_colors(results["variants"])
    lambdas = {
        name: (results["variants"][name].get("panel") or {}).get("lambda_kl") for name in tunes
    }
    plt = _plt()
    if what == "kl" and all(isinstance(v, int | float) for v in lambdas.values()):
        order = sorted(tunes, key=lambda n: (lambdas[n], n))
        fig, axes = _grid(plt, len(metrics), 2, 4.6, 3.2)
        for ax, metric in zip(axes, metrics, strict=False):
            stats = [tunes[n]["metrics"].get(metric) for n in order]
            x = np.arange(len(order))
            y = np.array([_mean(s) for s in stats])
            err = np.array([_finite_or_zero((s or {}).get("half_width")) for s in stats])
            ax.plot(x, y, color="0.5", lw=1.0, zorder=1)
            for xi, yi, ei, name in zip(x, y, err, order, strict=True):
                ax.errorbar(xi, yi, yerr=ei, fmt="o", color=colors[name], capsize=3, ms=6)
                if math.isfinite(yi):
                    ax.annotate(_short(yi), (xi, yi), xytext=(5, 4), textcoords="offset points",
                                fontsize=7, gid="bar-label")  # fmt: skip
            _base_line(ax, base, metric, vertical=False)
            ax.set_xticks(x, [f"{lambdas[n]:g}" for n in order], fontsize=8)
            ax.set_xlabel("lambda_KL", fontsize=8)
            ax.set_title(metric.replace("_", " "), fontsize=9)
            ax.grid(alpha=0.3)
        for ax in axes[len(metrics) :]:
            ax.axis("off")
        fig.suptitle(
            f"Ablation of lambda_KL: {mode} mean and 95% CI per fine-tune; dashed: base",
            fontsize=9,
        )
        return fig
    height = 0.3 * len(tunes) + 1.1
    fig, axes = _grid(plt, len(metrics), 2, 5.2, height)
    for ax, metric in zip(axes, metrics, strict=False):
        order = sorted(tunes, key=lambda n: (_sort_key(tunes[n]["metrics"].get(metric)), n))
        stats = [tunes[n]["metrics"].get(metric) for n in order]
        positions = np.arange(len(order))
        _hbars(ax, positions, stats, [colors[n] for n in order],
               emphasise=[n == "finetune-amuled" for n in order])  # fmt: skip
        _base_line(ax, base, metric, vertical=True)
        ax.set_yticks(positions, order, fontsize=8)
        for label in ax.get_yticklabels():
            if label.get_text() == "finetune-amuled":
                label.set_fontweight("bold")
        ax.set_title(metric.replace("_", " "), fontsize=9)
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    for ax in axes[len(metrics) :]:
        ax.axis("off")
    fig.suptitle(
        f"Ablation of {what}: each fine-tune's {mode} mean and 95% CI on the paper's metrics, "
        "sorted (largest on top); AMULED outlined in black, dashed: base",
        fontsize=9,
    )
    return fig


#: Colours of the budget ablation's selections (:func:`budget_figure`; random also dashed).
SELECTION_COLORS = {"uncertainty": "tab:blue", "random": "tab:orange"}


def budget_points(results: dict[str, Any]) -> tuple[list[dict[str, Any]], str | None]:
    """The budget ablation's fine-tunes as points, and its full-feedback fine-tune.

    Returns:
        ``([{"variant", "budget", "selection", "distill"}...], full)``: one point per
        fine-tune with ``[feedback.distill]`` (``budget``: the share of distinct states
        it may ask; for a count, the share it asked), sorted by selection and budget; and
        the name of the AMULED fine-tune that asked every state (None without one).

    """
    points, full = [], None
    for name, entry in results.get("variants", {}).items():
        panel = entry.get("panel") or {}
        settings = panel.get("distill")
        if not settings:
            if panel.get("feedback") == "amuled" and full is None:
                full = name
            continue
        report = (entry.get("feedback") or {}).get("distill") or {}
        budget = settings.get("budget")
        share = budget if isinstance(budget, float) else report.get("asked_share")
        selection = "all" if share == 1.0 else str(settings.get("selection"))
        points.append({
            "variant": name, "budget": share, "selection": selection, "distill": report,
        })  # fmt: skip
    points.sort(key=lambda p: (p["selection"], -(p["budget"] or 0.0), p["variant"]))
    return points, full


def budget_figure(results: dict[str, Any], mode: str = "greedy") -> Any | None:
    """The budget ablation's figure: each paper metric against the budget.

    One panel per paper metric and one for the model's held-out agreement with the
    panel (total-variation distance of the fused beliefs): x is the budget (share of the
    distinct states asked, log scale), one colour per selection (:data:`SELECTION_COLORS`;
    the 100% point, where nothing is selected, starts both lines), 95% CIs as error bars;
    the fine-tune that asked every state without a model is a grey band (its 95% CI) with
    its mean as a line, the base policy a dashed line.

    Returns:
        The figure, or None without a distilled fine-tune.

    """
    points, full = budget_points(results)
    points = [p for p in points if isinstance(p["budget"], int | float) and p["budget"] > 0]
    if not points:
        return None
    variants = results["variants"]
    task = results.get("task", "")
    tunes = {p["variant"]: variants[p["variant"]].get(mode) or {} for p in points}
    metrics = [
        m for m in PAPER_METRICS.get(task, [])
        if any(m in (v.get("metrics") or {}) for v in tunes.values())
    ]  # fmt: skip
    if not metrics:
        metrics = _plotted_metrics(results, {k: v for k, v in tunes.items() if v})[:4]
    panels = [*metrics, "holdout_tv_fused"]
    plt = _plt()
    fig, axes = _grid(plt, len(panels), 2, 4.6, 3.2)
    base = (variants.get("base") or {}).get(mode)
    full_stats = (variants.get(full) or {}).get(mode) if full else None
    selections = sorted({p["selection"] for p in points} - {"all"}) or ["all"]
    budgets = sorted({p["budget"] for p in points})
    for ax, metric in zip(axes, panels, strict=False):
        for selection in selections:
            line = [p for p in points if p["selection"] in (selection, "all")]
            line.sort(key=lambda p: p["budget"])
            xs = np.array([p["budget"] for p in line], dtype=float)
            if metric == "holdout_tv_fused":
                ys = np.array([
                    np.nan if p["distill"].get("holdout_tv_fused") is None
                    else float(p["distill"]["holdout_tv_fused"]) for p in line
                ])  # fmt: skip
                err = np.zeros(len(line))
            else:
                stats = [(tunes[p["variant"]].get("metrics") or {}).get(metric) for p in line]
                ys = np.array([_mean(s) for s in stats])
                err = np.array([_finite_or_zero((s or {}).get("half_width")) for s in stats])
            color = SELECTION_COLORS.get(selection, "0.3")
            style = "s--" if selection == "random" else "o-"  # visible where the lines meet
            ax.errorbar(xs, ys, yerr=err, fmt=style, color=color, capsize=3, ms=5, lw=1.2,
                        label=selection, gid=f"selection-{selection}")  # fmt: skip
        if metric != "holdout_tv_fused":
            stat = ((full_stats or {}).get("metrics") or {}).get(metric)
            mean = _mean(stat)
            if math.isfinite(mean):
                half = _finite_or_zero((stat or {}).get("half_width"))
                ax.axhspan(mean - half, mean + half, color="0.6", alpha=0.25, lw=0,
                           gid="full-band")  # fmt: skip
                ax.axhline(mean, color="0.45", lw=1.0, gid="full-line")
            _base_line(ax, base, metric, vertical=False)
            ax.set_title(metric.replace("_", " "), fontsize=9)
        else:
            ax.set_title("held-out TV to the panel (fused)", fontsize=9)
        ax.set_xscale("log")
        ax.set_xticks(budgets, [f"{100 * b:g}%" for b in budgets], fontsize=8)
        ax.minorticks_off()
        ax.set_xlabel("budget (share of distinct states asked)", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes[len(panels) :]:
        ax.axis("off")
    axes[0].legend(fontsize=7, title="selection", title_fontsize=7)
    fig.suptitle(
        f"Ablation of the feedback budget: {mode} mean and 95% CI per fine-tune; grey band: "
        "every state asked (no model); dashed: base",
        fontsize=9,
    )
    return fig


def _sort_key(stat: dict[str, Any] | None) -> float:
    mean = _mean(stat)
    return mean if math.isfinite(mean) else -math.inf


def _base_line(ax: Any, base: dict[str, Any] | None, metric: str, *, vertical: bool) -> None:
    value = _mean((base or {}).get("metrics", {}).get(metric))
    if not math.isfinite(value):
        return
    if vertical:
        ax.axvline(value, color="0.15", ls="--", lw=1.1, zorder=5, gid="base-line")
    else:
        ax.axhline(value, color="0.15", ls="--", lw=1.1, zorder=0, gid="base-line")


def plot_ablation(
    results: dict[str, Any], what: str, path: Path, colors: dict[str, str] | None = None
) -> Path | None:
    """Write :func:`ablation_figure` to ``path`` (None when there is no fine-tune)."""
    fig = ablation_figure(results, what, colors)
    return None if fig is None else _save(fig, path)


# ---------------------------------------------------------------------------------------
# Trajectories


def findmilk_subgoals(trajectory: dict[str, Any]) -> dict[str, Any]:
    """What a FindMilk trajectory did: babies pacified and woken, milk reached.

    Entering a baby's cell removes it (a crying one is pacified, a sleeping one woken), so
    the babies of the layout on the path are the ones the episode reached.

    Args:
        trajectory: ``{"obs": [[x, y, milk_x, milk_y, ...], ...], "layout": {"crying":
            [[x, y], ...], "sleeping": [...]}}`` (the evaluator's recorded episode).

    Returns:
        ``{"start", "milk", "end": (x, y), "visited": set of cells, "crying",
        "sleeping", "pacified", "woken": lists of (x, y), "reached_milk": bool}``.

    """
    obs = np.asarray(trajectory["obs"], dtype=float)
    cells = [(int(np.rint(x)), int(np.rint(y))) for x, y in obs[:, :2]]
    visited = set(cells[1:])
    layout = trajectory.get("layout") or {}
    crying = [tuple(int(v) for v in p) for p in layout.get("crying", [])]
    sleeping = [tuple(int(v) for v in p) for p in layout.get("sleeping", [])]
    milk = (int(np.rint(obs[0, 2])), int(np.rint(obs[0, 3])))
    return {
        "start": cells[0],
        "milk": milk,
        "end": cells[-1],
        "visited": visited,
        "crying": crying,
        "sleeping": sleeping,
        "pacified": [p for p in crying if p in visited],
        "woken": [p for p in sleeping if p in visited],
        "reached_milk": milk in visited,
    }


def findmilk_figure(
    results: dict[str, Any], mode: str = "greedy", colors: dict[str, str] | None = None
) -> Any | None:
    """The FindMilk trajectories (see :func:`plot_findmilk`); None without that mode."""
    variants = {k: v[mode]["trajectory"] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    from matplotlib.lines import Line2D

    colors = colors or variant_colors(variants)
    plt = _plt()
    size = 8
    cols = 2 if len(variants) <= 4 else 3 if len(variants) <= 9 else 4
    fig, axes = _grid(plt, len(variants), cols, 3.9, 4.4)
    for ax, (name, traj) in zip(axes, variants.items(), strict=False):
        goals = findmilk_subgoals(traj)
        obs = np.asarray(traj["obs"], dtype=float)
        for x, y in goals["sleeping"]:
            woken = (x, y) in goals["woken"]
            ax.scatter(x, y, marker="s", s=300, zorder=2, linewidths=2,
                       color="#f4a261" if woken else "#8ecae6",
                       edgecolor="#d62828" if woken else "#219ebc")  # fmt: skip
            if woken:
                ax.text(x, y, "!", ha="center", va="center", fontsize=12, weight="bold",
                        color="#d62828", zorder=6)  # fmt: skip
        for x, y in goals["crying"]:
            pacified = (x, y) in goals["pacified"]
            ax.scatter(x, y, marker="o", s=300, zorder=2, linewidths=2,
                       color="#b7e4c7" if pacified else "#f28482",
                       edgecolor="#2d6a4f" if pacified else "#c1121f")  # fmt: skip
            if pacified:
                ax.text(x, y, "+", ha="center", va="center", fontsize=13, weight="bold",
                        color="#2d6a4f", zorder=6)  # fmt: skip
        mx, my = goals["milk"]
        ax.scatter(mx, my, marker="*", s=330, color="gold", edgecolor="k", zorder=3)
        jitter = np.linspace(-0.13, 0.13, len(obs))
        ax.plot(obs[:, 0] + jitter, obs[:, 1] + jitter, "-", color=colors.get(name, "k"),
                lw=2.0, alpha=0.9, zorder=4, gid="path")  # fmt: skip
        sx, sy = goals["start"]
        ax.scatter(sx, sy, marker="^", s=90, color="green", edgecolor="k", zorder=5)
        ex, ey = goals["end"]
        ax.scatter(ex, ey, marker="X", s=90, color="k", zorder=5)
        ax.set_xlim(-0.5, size - 0.5)
        ax.set_ylim(-0.5, size - 0.5)
        ax.set_xticks(range(size))
        ax.set_yticks(range(size))
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_aspect("equal")
        milk = "milk reached" if goals["reached_milk"] else "milk NOT reached"
        ax.set_title(
            f"{name}\n{len(traj['actions'])} steps, {milk}\n"
            f"pacified {len(goals['pacified'])}/{len(goals['crying'])}, "
            f"woken {len(goals['woken'])}/{len(goals['sleeping'])}",
            fontsize=8, color=colors.get(name, "k"),
        )  # fmt: skip
    spare = axes[len(variants) :]
    for ax in spare:
        ax.axis("off")
    handles = [
        Line2D([], [], marker="^", ls="", color="green", markeredgecolor="k", ms=8),
        Line2D([], [], marker="X", ls="", color="k", ms=8),
        Line2D([], [], marker="*", ls="", color="gold", markeredgecolor="k", ms=13),
        Line2D([], [], marker="o", ls="", color="#f28482", markeredgecolor="#c1121f", ms=10),
        Line2D([], [], marker="o", ls="", color="#b7e4c7", markeredgecolor="#2d6a4f", ms=10),
        Line2D([], [], marker="s", ls="", color="#8ecae6", markeredgecolor="#219ebc", ms=10),
        Line2D([], [], marker="s", ls="", color="#f4a261", markeredgecolor="#d62828", ms=10),
    ]
    labels = ["start", "end", "milk", "crying baby", "crying baby pacified (+)",
              "sleeping baby", "sleeping baby woken (!)"]  # fmt: skip
    fig.suptitle(f"FindMilk {mode} trajectory, one per variant (path in the variant's colour)",
                 fontsize=9)  # fmt: skip
    _legend_below(fig, handles, labels, spare)
    return fig


def plot_findmilk(
    results: dict[str, Any],
    path: Path,
    mode: str = "greedy",
    colors: dict[str, str] | None = None,
) -> Path | None:
    """One FindMilk trajectory per variant, one grid per panel, sub-goals marked.

    Each panel: the path in the variant's colour (start ▲, end ✕), the milk (★), every
    crying baby (red; green with ``+`` once pacified) and sleeping baby (blue; orange with
    ``!`` once woken); its title says the steps, whether the milk was reached and the
    babies pacified and woken.

    Args:
        results: The evaluation results.
        path: The PNG to write.
        mode: ``greedy`` or ``sampled``.
        colors: ``{variant: colour}``.

    Returns:
        ``path``, or None without that mode.

    """
    fig = findmilk_figure(results, mode, colors)
    return None if fig is None else _save(fig, path)


_DRIVING_EVENTS = {"collisions": ("X", "#d62828", 60), "rescues": ("o", "#2a9d8f", 45)}


def driving_figure(
    results: dict[str, Any], mode: str = "greedy", colors: dict[str, str] | None = None
) -> Any | None:
    """The Driving episodes (see :func:`plot_driving`); None without that mode."""
    variants = {k: v[mode]["trajectory"] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    from matplotlib.lines import Line2D

    colors = colors or variant_colors(variants)
    plt = _plt()
    n = len(variants)
    height = 1.3 * n + 0.9
    fig, axes = plt.subplots(
        n, 1, figsize=(10, height), squeeze=False, sharex=True, layout="constrained"
    )
    for ax, (name, traj) in zip(axes[:, 0], variants.items(), strict=True):
        obs = np.asarray(traj["obs"], dtype=float)
        lane = obs[:, -5:].argmax(axis=1) if obs.shape[1] >= 5 else np.zeros(len(obs), int)
        steps = np.arange(len(lane))
        ax.step(steps, lane, where="post", color=colors.get(name, "k"), lw=1.6, gid="path")
        events = traj.get("events", {})
        counts = []
        for key, (marker, color, size) in _DRIVING_EVENTS.items():
            values = events.get(key, [])
            hits = [i + 1 for i, v in enumerate(values) if v]
            counts.append(f"{key} {int(sum(v for v in values if v))}")
            if hits:
                ax.scatter(hits, lane[hits], marker=marker, color=color, s=size, zorder=3,
                           edgecolor="k", linewidths=0.5)  # fmt: skip
        changes = int(np.count_nonzero(np.diff(lane)))
        ax.set_title(f"{name}: {len(traj['actions'])} steps, {', '.join(counts)}, "
                     f"lane changes {changes}", fontsize=8, loc="left",
                     color=colors.get(name, "k"))  # fmt: skip
        ax.set_ylim(-0.5, 4.5)
        ax.set_yticks(range(5))
        ax.tick_params(labelsize=7)
        ax.set_ylabel("lane", fontsize=7)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("step", fontsize=8)
    handles = [
        Line2D([], [], marker=m, ls="", color=c, markeredgecolor="k", ms=7)
        for m, c, _ in _DRIVING_EVENTS.values()
    ]
    fig.legend(handles, ["collision", "grandma rescued"], loc="outside upper right", ncol=2,
               fontsize=8, frameon=False)  # fmt: skip
    fig.suptitle(f"Driving {mode} episode per variant: lane (0-4) over time, with events",
                 fontsize=9, x=0.02, ha="left")  # fmt: skip
    return fig


def plot_driving(
    results: dict[str, Any],
    path: Path,
    mode: str = "greedy",
    colors: dict[str, str] | None = None,
) -> Path | None:
    """One Driving episode per variant: a strip of its lane over time with its events.

    Args:
        results: The evaluation results.
        path: The PNG to write.
        mode: ``greedy`` or ``sampled``.
        colors: ``{variant: colour}``.

    Returns:
        ``path``, or None without that mode.

    """
    fig = driving_figure(results, mode, colors)
    return None if fig is None else _save(fig, path)


# ---------------------------------------------------------------------------------------
# Tables


def diagnostics_table(results: dict[str, Any]) -> str:
    """Markdown table of mean per-cluster weight, mean conflict and miss rate per variant."""
    rows = {k: v["feedback"] for k, v in results["variants"].items() if "feedback" in v}
    if not rows:
        return "_No fine-tuned variant in this run._\n"
    clusters = sorted({c for fb in rows.values() for c in (fb.get("mean_weight") or {})})
    head = ["variant", *clusters, "mean conflict", "replay miss rate", "unique states"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, fb in rows.items():
        weights = fb.get("mean_weight") or {}
        conflict = fb.get("mean_conflict")
        cells = [name]
        cells += [f"{weights[c]:.3f}" if c in weights else "" for c in clusters]
        cells.append("" if conflict is None else f"{conflict:.3f}")
        cells.append(f"{100 * fb.get('miss_rate', 0.0):.1f}%")
        states = fb.get("unique_states", "")
        cells.append(f"{states:.1f}" if isinstance(states, float) else str(states))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


#: Columns of :func:`agents_table`: (status key, heading).
_AGENT_COLUMNS = (
    ("repaired", "repaired"),
    ("abstained", "abstained"),
    ("replay_miss", "replay miss"),
    ("timeout", "timeout"),
    ("error", "error"),
)


#: Columns of :func:`agents_table` for a distilled feedback: the model's answers (for states
#: not asked; for an asked state's miss) and the states it could not answer.
_MODEL_COLUMNS = (
    ("distilled", "by the model"),
    ("distilled_miss", "miss by the model"),
    ("unasked", "unasked"),
)


def agents_table(results: dict[str, Any]) -> str:
    """Markdown table: per fine-tune and panel agent, the share of each belief status.

    From ``feedback["agents"]`` (counts per rewarded step): the number of beliefs, the
    share repaired (answered after a repair), abstained, missed by the replay, timed out
    and failed with an error, and the share not answered (every status but ``ok`` and
    ``repaired`` and the distilled model's answers: the fused reward went on without that
    agent). With a distilled feedback (``[feedback.distill]``) three more columns: the
    share the model answered for states not asked, instead of a miss, and could not.

    Returns:
        The table, or ``""`` when no variant recorded per-agent counts.

    """
    lines = []
    rows = [
        (name, agent, row)
        for name, entry in results.get("variants", {}).items()
        for agent, row in ((entry.get("feedback") or {}).get("agents") or {}).items()
    ]
    # the distilled model's answers and its failures, only where a fine-tune had one
    columns = list(_AGENT_COLUMNS)
    if any(row.get(key) for _, _, row in rows for key, _ in _MODEL_COLUMNS):
        columns += _MODEL_COLUMNS
    for name, agent, row in rows:
        total = row.get("total") or sum(
            n for k, n in row.items() if k not in ("total", "failed", "failure_rate")
        )
        cells = [name, agent, f"{int(total):,}"]
        cells += [_percent(row.get(key, 0), total) for key, _ in columns]
        failed = row.get("failed")
        if failed is None:
            failed = total - sum(row.get(key, 0) for key in FUSED_STATUSES)
        cells.append(_percent(failed, total))
        lines.append("| " + " | ".join(cells) + " |")
    if not lines:
        return ""
    head = ["variant", "agent", "beliefs", *(h for _, h in columns), "not answered"]
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *lines]) + "\n"


def servers_table(results: dict[str, Any]) -> str:
    """Markdown table: per fine-tune and LLM server, what the server was asked and did.

    From ``feedback["llm_servers"]`` (:func:`amuled_ma.deliberation.feedback.llm_server_stats`):
    requests sent (every attempt: retries and probes included), answered, failed with the
    kinds of failure, requests retried on another host after failing there, times the
    server was taken out of the pool and put back, and the mean and 95th-percentile
    latency of its answered requests.

    Returns:
        The table, or ``""`` when no variant asked an LLM server.

    """
    lines = []
    for name, entry in results.get("variants", {}).items():
        for host, row in ((entry.get("feedback") or {}).get("llm_servers") or {}).items():
            kinds = ", ".join(f"{k} {n:,}" for k, n in (row.get("failures") or {}).items())
            failed = f"{int(row.get('failed', 0)):,}" + (f" ({kinds})" if kinds else "")
            cells = [
                name,
                f"`{host}`",
                f"{int(row.get('sent', 0)):,}",
                f"{int(row.get('answered', 0)):,}",
                failed,
                f"{int(row.get('retried_from', 0)):,}",
                f"{int(row.get('went_down', 0))} / {int(row.get('came_back', 0))}",
                *(
                    "-" if row.get(key) is None else f"{float(row[key]):.2f}"
                    for key in ("mean_latency_s", "p95_latency_s")
                ),
            ]
            lines.append("| " + " | ".join(cells) + " |")
    if not lines:
        return ""
    head = ["variant", "server", "sent", "answered", "failed", "retried elsewhere",
            "out / back", "mean latency (s)", "p95 latency (s)"]  # fmt: skip
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *lines]) + "\n"


def _tv(value: Any) -> str:
    return "-" if value is None else f"{float(value):.3f}"


def budget_table(results: dict[str, Any]) -> str:
    """Markdown table: the feedback budget's accounting of every distilled fine-tune.

    From ``feedback["distill"]`` (:meth:`amuled_ma.distill.DistilledSource.report`): the
    budget and selection, the distinct states visited, asked (and their share), answered
    by the model, the misses the model answered, the requests forwarded to the panel's
    source and of those sent to the LLMs (the rest were in the belief store), the refits,
    and the model's agreement with the panel on the held-out asked states (mean
    total-variation distance, fused and per member).

    Returns:
        The table, or ``""`` when no fine-tune was distilled.

    """
    lines = []
    for name, entry in results.get("variants", {}).items():
        d = (entry.get("feedback") or {}).get("distill")
        if not d:
            continue
        budget = d.get("budget")
        shown = f"{100 * budget:g}%" if isinstance(budget, float) else f"{budget} states"
        members = ", ".join(f"{m} {_tv(v)}" for m, v in (d.get("holdout_tv") or {}).items())
        cells = [
            name,
            shown,
            str(d.get("selection")),
            f"{int(d.get('visited_states', 0)):,}",
            f"{int(d.get('asked_states', 0)):,} ({100 * d.get('asked_share', 0.0):.1f}%)",
            f"{int(d.get('model_states', 0)):,}",
            f"{int(d.get('miss_answers', 0)):,}",
            f"{int(d.get('requests_forwarded', 0)):,} / {int(d.get('requests_sent', 0)):,}",
            str(d.get("refits", 0)),
            f"{_tv(d.get('holdout_tv_fused'))} ({int(d.get('holdout_states', 0))} states)",
            members or "-",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    if not lines:
        return ""
    head = ["variant", "budget", "selection", "states visited", "asked", "answered by the model",
            "misses by the model", "requests forwarded / sent", "refits",
            "held-out TV, fused", "held-out TV per member"]  # fmt: skip
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *lines]) + "\n"


def budget_ablation_table(results: dict[str, Any], mode: str = "greedy") -> str:
    """Markdown table of the budget ablation: the paper's metrics against the budget.

    One row per distilled fine-tune (selection, budget, states asked, requests sent, the
    model's held-out fused TV) and one for the AMULED fine-tune that asked every state,
    each with the paper's metrics (``mean ± half-width``, ``mode`` policy).

    Returns:
        The table, or ``""`` without a distilled fine-tune.

    """
    points, full = budget_points(results)
    if not points:
        return ""
    variants = results["variants"]
    data = {n: (variants[n].get(mode) or {}) for n in [*(p["variant"] for p in points), full] if n}
    metrics = [m for m in PAPER_METRICS.get(results.get("task", ""), [])
               if any(m in (v.get("metrics") or {}) for v in data.values())]  # fmt: skip
    head = ["selection", "budget", "variant", "asked", "requests sent", "held-out TV, fused",
            *metrics]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in points:
        d = p["distill"]
        budget = p["budget"]
        cells = [
            p["selection"],
            "-" if budget is None else f"{100 * budget:g}%",
            p["variant"],
            f"{int(d.get('asked_states', 0)):,} of {int(d.get('visited_states', 0)):,}",
            f"{int(d.get('requests_sent', 0)):,}",
            _tv(d.get("holdout_tv_fused")),
        ]
        cells += [format_stat((data[p["variant"]].get("metrics") or {}).get(m)) for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    if full:
        stats = data[full].get("metrics") or {}
        cells = ["full feedback", "100%", full, "every state", "-", "-"]
        lines.append("| " + " | ".join(cells + [format_stat(stats.get(m)) for m in metrics]) + " |")
    return "\n".join(lines) + "\n"


def _percent(count: float, total: float) -> str:
    return f"{100 * count / total:.1f}%" if total else "-"


def _table_metrics(results: dict[str, Any], variants: dict[str, Any]) -> list[str]:
    metrics = metric_order(
        results.get("task", ""), sorted({m for v in variants.values() for m in v["metrics"]})
    )
    return [m for m in metrics if m not in ("terminated", "return")]


def metrics_table(results: dict[str, Any], mode: str) -> str:
    """Markdown table: one row per variant, one column per metric, ``mean ± 95% CI``."""
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return ""
    metrics = _table_metrics(results, variants)
    head = "| variant | seeds | " + " | ".join(metrics) + " |"
    lines = [head, "|---|---|" + "---|" * len(metrics)]
    for name, data in variants.items():
        cells = [format_stat(data["metrics"].get(m)) for m in metrics]
        lines.append(f"| {name} | {data.get('n_seeds', 1)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def base_differences(
    results: dict[str, Any], mode: str, base: str = "base"
) -> dict[str, dict[str, float]]:
    """Each variant's mean minus the base policy's mean, per metric both have.

    Args:
        results: The evaluation results.
        mode: ``greedy`` or ``sampled``.
        base: The reference variant.

    Returns:
        ``{variant: {metric: difference}}`` for every variant but ``base`` (metrics
        without a finite mean on either side are left out); ``{}`` without ``base``.

    """
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    if base not in variants:
        return {}
    ref = variants[base]["metrics"]
    out: dict[str, dict[str, float]] = {}
    for name, data in variants.items():
        if name == base:
            continue
        row = {}
        for metric, stat in data["metrics"].items():
            mine, theirs = _mean(stat), _mean(ref.get(metric))
            if math.isfinite(mine) and math.isfinite(theirs):
                row[metric] = mine - theirs
        out[name] = row
    return out


def same_as_base(results: dict[str, Any], mode: str = "greedy") -> list[str]:
    """The fine-tunes whose every metric equals the base policy's within 1e-9.

    Returns:
        Variant names (``finetune*``), in results order; a variant sharing no metric with
        base is not listed.

    """
    return [
        name
        for name, row in base_differences(results, mode).items()
        if name.startswith("finetune") and row and all(abs(d) <= EQUAL_TOL for d in row.values())
    ]


def differences_table(results: dict[str, Any], mode: str) -> str:
    """Markdown table of :func:`base_differences`: ``+1.20``, ``-0.40``, ``=`` (equal)."""
    diffs = base_differences(results, mode)
    if not diffs:
        return ""
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    metrics = _table_metrics(results, variants)
    lines = ["| variant | " + " | ".join(metrics) + " |", "|---|" + "---|" * len(metrics)]
    for name, row in diffs.items():
        cells = [
            "" if m not in row else "=" if abs(row[m]) <= EQUAL_TOL else f"{row[m]:+.2f}"
            for m in metrics
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _base_label(checkpoint: str | None) -> str:
    """The base a fine-tune started from: its variant folder, or where it lives."""
    if not checkpoint:
        return "-"
    folder = Path(checkpoint).parent
    return f"`{folder}`" if folder.parent.name and "authors" in folder.parts else folder.name


def panels_table(results: dict[str, Any]) -> str:
    """A Markdown table of each fine-tune's feedback (``results["variants"][*]["panel"]``)."""
    rows = []
    for name, entry in results.get("variants", {}).items():
        panel = entry.get("panel")
        if not panel:
            continue
        agents = ", ".join(panel.get("agents") or []) or "-"
        if panel.get("feedback") in ("human", "human:rules"):
            agents = "the synthetic human" if panel["feedback"] == "human" else "our human rule"
        elif str(panel.get("feedback", "")).startswith(("cluster:", "moral")):
            agents = str(panel["feedback"])
        source = panel.get("source") or "-"
        detail = panel.get("recording") if source == "replay" else panel.get("model")
        overrides = panel.get("agent_sources") or {}
        if overrides:
            source += "; " + ", ".join(
                f"{agent}: {spec.get('source', '?')}" for agent, spec in overrides.items()
            )
        rows.append(
            f"| {name} | {panel.get('feedback')} | {panel.get('recipe')} | "
            f"{panel.get('lambda_kl')} | {panel.get('iterations')} | {agents} | "
            f"{source}{f' ({detail})' if detail else ''} | {panel.get('fusion') or '-'} | "
            f"{_base_label(panel.get('base_checkpoint'))} |"
        )
    if not rows:
        return ""
    head = (
        "| variant | feedback | recipe | lambda_KL | iterations | agents | source | fusion | "
        "base |\n|---|---|---|---|---|---|---|---|---|"
    )
    return head + "\n" + "\n".join(rows) + "\n"


def read_run_config(run_dir: Path) -> dict[str, Any]:
    """The run folder's ``config.json`` (``{}`` when absent or unreadable)."""
    try:
        data = json.loads((Path(run_dir) / "config.json").read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _distinct(values: Iterable[Any]) -> list[Any]:
    out: list[Any] = []
    for value in values:
        if value is not None and value != "" and value not in out:
            out.append(value)
    return out


def _joined(values: Iterable[Any], several: str = " (per variant)") -> str:
    found = [f"{v:g}" if isinstance(v, float) else str(v) for v in _distinct(values)]
    if not found:
        return ""
    return found[0] if len(found) == 1 else ", ".join(found) + several


def _source_text(panel: dict[str, Any]) -> str:
    source = str(panel.get("source") or "")
    if source == "replay":
        text = f"replay of `{panel.get('recording')}`"
    elif source == "ollama":
        text = f"ollama, model `{panel.get('model')}`"
    elif source in ("openai", "llm") and panel.get("model"):
        text = f"{source}, model `{panel.get('model')}`"
    else:
        text = source
    overrides = panel.get("agent_sources") or {}
    if overrides:
        text += "; " + ", ".join(
            f"{agent}: {spec.get('source', '?')}"
            + (f" `{spec['recording']}`" if spec.get("recording") else "")
            + (f" `{spec['model']}`" if spec.get("model") and not spec.get("recording") else "")
            for agent, spec in overrides.items()
        )
    return text


def _recordings(panels: list[dict[str, Any]]) -> list[str]:
    """``file sha256 hash`` of every replayed recording the fine-tunes read."""
    out = []
    for panel in panels:
        inputs = panel.get("inputs") or {}
        overrides = panel.get("agent_sources") or {}
        for key, digest in inputs.items():
            if key == "recording_sha256":
                name = panel.get("recording")
            elif key.startswith("recording_sha256[") and key.endswith("]"):
                agent = key[len("recording_sha256[") : -1]
                name = f"{(overrides.get(agent) or {}).get('recording', '?')} ({agent})"
            else:
                continue
            text = f"`{name}` sha256 `{digest}`"
            if text not in out:
                out.append(text)
        if panel.get("source") == "replay" and "recording_sha256" not in inputs:
            text = f"`{panel.get('recording')}` (no hash recorded)"
            if text not in out:
                out.append(text)
    return out


def settings_table(results: dict[str, Any], config: dict[str, Any] | None = None) -> str:
    """The report's header: what was run, as a two-column Markdown table.

    Rows: task and scenario, evaluation (episodes, seeds, confidence), training seeds,
    base training steps, the fine-tunes' recipe, lambda_KL and iterations, the panel
    (agents, fusion), where its beliefs came from, and each recording read with its
    SHA-256. Fine-tune settings come from each variant's ``panel`` entry (several values:
    ``(per variant)``), else from the run's ``config.json`` scenario.

    Args:
        results: The evaluation results.
        config: The run's ``config.json`` (:func:`read_run_config`; may be empty).

    Returns:
        The table.

    """
    config = config or {}
    scenario = config.get("scenario") or {}
    variants = results.get("variants", {})
    panels = [entry["panel"] for entry in variants.values() if entry.get("panel")]
    tunes = [n for n in variants if n.startswith("finetune")]
    rows: list[tuple[str, str]] = [
        ("task", f"`{results.get('task', '')}` (scenario `{results.get('scenario')}`)"),
        (
            "evaluation",
            f"{results.get('episodes')} episodes per variant and mode, seeds from "
            f"{results.get('seed')}, {100 * results.get('confidence', 0.95):g}% "
            "Student-t intervals",
        ),
    ]
    seeds = config.get("seeds")
    if isinstance(seeds, list) and seeds:
        rows.append(("training seeds", f"{len(seeds)}: {', '.join(str(s) for s in seeds)}"))
    else:
        most = max((e.get(m, {}).get("n_seeds", 1) for e in variants.values()
                    for m in ("greedy", "sampled") if m in e), default=1)  # fmt: skip
        rows.append(("training seeds", str(most)))
    base = scenario.get("base") or {}
    if base.get("total_steps"):
        rows.append(("base training", f"{int(base['total_steps']):,} env steps per policy"))
    if config.get("ablation"):
        rows.append(("ablation", f"`{config['ablation']}`"))
    finetune = scenario.get("finetune") or {}
    if tunes or panels:
        for key, label, fallback in (
            ("recipe", "fine-tune recipe", finetune.get("recipe")),
            ("lambda_kl", "lambda_KL", finetune.get("lambda_kl")),
            ("iterations", "fine-tune iterations", finetune.get("iterations")),
        ):
            text = _joined(p.get(key) for p in panels) or _joined([fallback])
            if text:
                rows.append((label, text))
    judged = [p for p in panels if p.get("agents")]
    feedback = scenario.get("feedback") or {}
    if not judged and feedback and any(n != "finetune-human" for n in tunes):
        # results without panel entries (older runs): the scenario's feedback settings
        judged = [
            {
                "feedback": "amuled",
                "agents": list(feedback.get("clusters") or []),
                "fusion": feedback.get("fusion"),
                "source": feedback.get("source"),
                "model": feedback.get("model"),
                "recording": Path(str(feedback.get("recording") or "")).name or None,
                "agent_sources": feedback.get("agents") or {},
            }
        ]
    if judged:
        amuled = [p for p in judged if p.get("feedback") == "amuled"] or judged
        agents = _joined((", ".join(p["agents"]) for p in amuled), " (per variant)")
        fusion = _joined(p.get("fusion") for p in amuled)
        rows.append(("panel", agents + (f"; fusion `{fusion}`" if fusion else "")))
        rows.append(("beliefs from", _joined((_source_text(p) for p in judged), "")))
        recordings = _recordings(judged)
        replayed = any(p.get("source") == "replay" for p in judged) or recordings
        if recordings:
            rows.append(("recording", "; ".join(recordings)))
        elif not replayed:
            rows.append(("recording", "none (no fine-tune replayed a recording)"))
    lines = ["| setting | value |", "|---|---|"]
    lines += [f"| {label} | {value} |" for label, value in rows]
    return "\n".join(lines) + "\n"


def viewer_line(run_dir: Path) -> str:
    """The report's pointer to ``amuled view``: a link when the page is already there."""
    run_dir = Path(run_dir)
    what = (
        "one offline HTML page replaying evaluation episode 0 of each fine-tune step by "
        "step, with every panel agent's belief, weight and reasoning"
    )
    if (run_dir / VIEWER_PAGE).is_file():
        return (
            f"{VIEWER_PREFIX} open [`{VIEWER_PAGE}`]({VIEWER_PAGE}) (or run "
            f"`amuled view {run_dir}` to write it again): {what}."
        )
    return f"{VIEWER_PREFIX} open `{VIEWER_PAGE}` (or run `amuled view {run_dir}`): {what}."


def link_viewer(run_dir: Path) -> bool:
    """Rewrite ``report.md``'s viewer line (:func:`viewer_line`) now the page may exist.

    Returns:
        True when the report had a viewer line (it now links the page if it exists).

    """
    report = Path(run_dir) / "report.md"
    if not report.is_file():
        return False
    lines = report.read_text().split("\n")
    found = False
    for i, line in enumerate(lines):
        if line.startswith(VIEWER_PREFIX):
            lines[i] = viewer_line(run_dir)
            found = True
    if found:
        report.write_text("\n".join(lines))
    return found


# ---------------------------------------------------------------------------------------
# The report


def write_report(
    run_dir: Path,
    results: dict[str, Any],
    *,
    title: str | None = None,
    ablation: str | None = None,
) -> Path:
    """Write ``report.md`` and its PNG figures into ``run_dir``.

    A figure of :data:`FIGURE_NAMES` (or an ``ablation_*.png``) left from an earlier
    report that this one does not draw is removed, so every PNG of the folder is one the
    report shows.

    Args:
        run_dir: The run directory (curves are read from its variant folders, settings
            from its ``config.json``).
        results: The evaluation results (:func:`~amuled_ma.evaluate.evaluator.evaluate_run`).
        title: Report title.
        ablation: The ablation this folder holds (``clusters``, ``aggregation``,
            ``models``, ``kl``; default: ``config.json``'s ``"ablation"``): adds its
            figure ``ablation_<what>.png``.

    Returns:
        Path of ``report.md``.

    """
    run_dir = Path(run_dir)
    task = results.get("task", "")
    config = read_run_config(run_dir)
    ablation = ablation or config.get("ablation")
    curves = load_curves(run_dir)
    colors = variant_colors([*results.get("variants", {}), *curves])
    base_curves = {k: v for k, v in curves.items() if not k.startswith("finetune")}
    ft_curves = {k: v for k, v in curves.items() if k.startswith("finetune")}
    figures: list[tuple[str, str, Path | None]] = []
    if ablation == "budget":
        figures.append((
            "Ablation of the feedback budget",
            "Each paper metric (greedy) and the distilled model's held-out agreement with the "
            "panel against the budget, the share of distinct states the panel was asked "
            "(log scale), one colour per selection; the grey band is the 95% CI of the "
            "fine-tune that asked every state without a model, the dashed line the base "
            "policy.",
            plot_ablation(results, ablation, run_dir / f"ablation_{ablation}.png", colors),
        ))  # fmt: skip
    elif ablation:
        figures.append((
            f"Ablation of {ablation}",
            "Each fine-tune of the ablation against AMULED on the paper's metrics (greedy), "
            + ("against lambda_KL." if ablation == "kl" else "sorted by the metric's mean.")
            + " The dashed line is the base policy.",
            plot_ablation(results, ablation, run_dir / f"ablation_{ablation}.png", colors),
        ))  # fmt: skip
    curve_note = (
        "A panel's y-range is the 2nd-98th percentile of its lines after their first 10% of "
        "points, widened to the values within that range's width of it: a far outlier (an "
        "early spike) is clipped, and the panel's title says so."
    )
    figures += [
        ("Base training curves", curve_note,
         plot_curves(base_curves, _CURVE_KEYS.get(task, ["episode/return_env"]),
                     run_dir / "curves_base.png", "base training", colors)),
        ("Fine-tuning curves", curve_note,
         plot_curves(ft_curves, _FT_KEYS + _CURVE_KEYS.get(task, [])[1:],
                     run_dir / "curves_finetune.png", "fine-tuning", colors)),
    ]  # fmt: skip
    for mode in ("greedy", "sampled"):
        figures.append((
            f"Metrics, {mode} policy",
            "Mean and 95% CI per variant; a thick tick at 0 marks a mean of 0.",
            plot_bars(results, mode, run_dir / f"metrics_{mode}.png", colors=colors),
        ))  # fmt: skip
    if task == "findmilk":
        figures.append((
            "A FindMilk trajectory per variant",
            "The first greedy evaluation episode of each variant.",
            plot_findmilk(results, run_dir / "trajectory_findmilk.png", colors=colors),
        ))  # fmt: skip
    elif task == "driving":
        figures.append((
            "A Driving episode per variant",
            "The first greedy evaluation episode of each variant.",
            plot_driving(results, run_dir / "episode_driving.png", colors=colors),
        ))  # fmt: skip
    written = {path.name for _, _, path in figures if path is not None}
    _remove_stale_figures(run_dir, written)
    lines = [
        f"# {title or 'Run report: ' + str(results.get('scenario'))}",
        "",
        "## Settings",
        "",
        settings_table(results, config),
    ]
    if any(n.startswith("finetune") for n in results.get("variants", {})):
        lines += [viewer_line(run_dir), ""]
    lines += [
        f"Figures are mean ± half-width of the {100 * results.get('confidence', 0.95):g}% "
        "Student-t confidence interval. A variant trained with one seed has its interval over "
        "the evaluation episodes; one trained with several (column *seeds*) has the mean of "
        "its per-seed means and the interval over the seeds, so it covers the spread of "
        "training runs.",
        "",
    ]
    for mode in ("greedy", "sampled"):
        table = metrics_table(results, mode)
        if not table:
            continue
        lines += [f"## Metrics, {mode} policy", "", table]
        diffs = differences_table(results, mode)
        if diffs:
            lines += [
                f"Difference to the base policy ({mode}): each variant's mean minus base's "
                "mean; `=` is equal within 1e-9.",
                "",
                diffs,
            ]
        same = same_as_base(results, mode) if mode == "greedy" else []
        if same:
            lines += [f"- **{name} behaves exactly as the base policy (greedy).**" for name in same]
            lines += [
                "",
                f"Every greedy metric of {'this fine-tune' if len(same) == 1 else 'these'} "
                "equals base's within 1e-9: the fine-tune did not change what the greedy "
                "policy achieves (a strong KL anchor, or too few iterations, keeps its most "
                "probable actions; the sampled policy may still differ).",
                "",
            ]
    panels = panels_table(results)
    if panels:
        lines += [
            "## Feedback of each fine-tune",
            "",
            "What each fine-tuned variant was trained on (its folder's `config.json`): the "
            "recipe of the KL anchor, lambda_KL, the panel's agents and where their beliefs "
            "came from.",
            "",
            panels,
        ]
    lines += [
        "## Fused-belief diagnostics",
        "",
        "Mean weight of each cluster in the fusion and mean Dempster conflict over the "
        "fine-tuning steps (which cluster drove the agent), and the replay miss rate.",
        "",
        diagnostics_table(results),
    ]
    agents = agents_table(results)
    if agents:
        lines += [
            "## Answers of each panel agent",
            "",
            "Per fine-tune and agent, over the rewarded fine-tuning steps: how many beliefs "
            "it gave and the share repaired (answered after the parser repaired the reply), "
            "abstained, missed by the replay, timed out or failed. *Not answered* counts "
            "every status but ok and repaired: there the agent abstained (weight 0) and the "
            "fusion went on without it.",
            "",
            agents,
        ]
    budget = budget_table(results)
    if budget:
        lines += [
            "## Feedback budget",
            "",
            "Fine-tunes whose panel was asked on a budget (`[feedback.distill]`, "
            "docs/distill.md): of the distinct states visited, how many the panel was asked "
            "(the budget caps them), how many the distilled model answered instead, the "
            "misses and abstentions of asked states it answered, the requests handed to the "
            "panel's source and how many of them were sent to the LLMs (the others were in "
            "the belief store), the model's refits, and its agreement with the panel on the "
            "held-out asked states (mean total-variation distance: 0 agrees, 1 disagrees "
            "entirely) of the fused belief and of each member.",
            "",
            budget,
        ]
    if ablation == "budget":
        table = budget_ablation_table(results)
        if table:
            lines += [
                "## Metrics against the budget",
                "",
                "The paper's metrics (greedy, mean ± half-width of the 95% CI) of each "
                "distilled fine-tune by selection and budget, and of the fine-tune that "
                "asked the panel about every state.",
                "",
                table,
            ]
    servers = servers_table(results)
    if servers:
        lines += [
            "## LLM servers",
            "",
            "Per fine-tune and LLM server: requests sent (every attempt, retries and probes "
            "included), answered, failed (by kind), retried on another server of the pool "
            "after failing there, times taken out of the pool and put back, and the latency "
            "of the answered requests (the 95th percentile over seed replicas is the largest "
            "replica's). Each request went to the least-busy live server "
            "(amuled-ma's docs/ollama.md, section 'A pool of servers').",
            "",
            servers,
        ]
    lines += ["## Figures", ""]
    for caption, note, path in figures:
        if path is not None:
            lines += [f"### {caption}", "", note, "", f"![{caption}]({path.name})", ""]
    report = run_dir / "report.md"
    report.write_text("\n".join(lines))
    return report


def _remove_stale_figures(run_dir: Path, written: set[str]) -> None:
    """Remove this module's figures left in ``run_dir`` by an earlier report."""
    stale = [run_dir / name for name in FIGURE_NAMES]
    stale += list(run_dir.glob("ablation_*.png"))
    for path in stale:
        if path.name not in written and path.is_file():
            path.unlink()
