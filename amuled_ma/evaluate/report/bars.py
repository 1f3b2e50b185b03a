"""Bar figures: the metrics per variant, and an ablation's own figure."""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.evaluate.evaluator import PAPER_METRICS, metric_order
from amuled_ma.evaluate.report.plotting import (
    EQUAL_TOL,
    grid_axes,
    half_of,
    mean_of,
    pyplot,
    short_label,
    variant_colors,
)
from amuled_ma.evaluate.results import ModeResult, Results, Stat
from amuled_ma.tasks.colors import COLORS

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Metrics left out of the bar charts (book-keeping, or the shaping the base never sees).
NOT_PLOTTED = ("terminated", "return_shaping", "return")


#: Fewer training seeds than this: a bar's whisker is the seeds' range, not a 95% CI (a
#: t-interval over 2 seeds is 12.7 standard errors wide and hides every bar).
FEW_SEEDS = 5


def seed_means(result: ModeResult | None, metric: str) -> list[float]:
    """Each training seed's mean of ``metric`` (empty for a single-seed variant)."""
    if result is None or not result.replicas or result.n_seeds < 2:
        return []
    values = [mean_of(rep.get(metric)) for rep in result.replicas.values()]
    return [v for v in values if math.isfinite(v)]


def _hbars(
    ax: Axes,
    positions: np.ndarray,
    names: Sequence[str],
    stats: Sequence[Stat | None],
    colors: Sequence[str],
    *,
    emphasise: Sequence[bool] | None = None,
    seeds: Sequence[Sequence[float]] | None = None,
) -> None:
    """Horizontal bars at ``positions`` named ``names``, with whiskers, seed dots and values.

    The whisker is the 95% CI, or with 2-4 seeds the range of the seeds' means (`FEW_SEEDS`).
    A bar of height 0 is drawn as a thick tick at 0 (``gid="zero-bar"``); a missing mean is
    labelled ``n/a``.
    """
    means = np.array([mean_of(s) for s in stats], dtype=float)
    seeds = list(seeds) if seeds is not None else [[] for _ in stats]
    xerr = np.array([[half_of(s) for s in stats]] * 2)  # left and right: the 95% CI
    for i, values in enumerate(seeds):
        if 2 <= len(values) < FEW_SEEDS and math.isfinite(means[i]):  # or few seeds' range
            xerr[:, i] = max(means[i] - min(values), 0.0), max(max(values) - means[i], 0.0)
    errs = xerr.max(axis=0)
    drawn = np.where(np.isfinite(means), means, 0.0)
    bold = list(emphasise or [False] * len(stats))
    for pos, values in zip(positions, seeds, strict=True):
        if values:
            offsets = np.linspace(-0.18, 0.18, len(values)) if len(values) > 1 else [0.0]
            ax.plot(values, np.asarray(offsets) + pos, "o", ms=3.2, color="black", alpha=0.75,
                    zorder=5, gid="seed-dot")  # fmt: skip
    ax.barh(
        positions, drawn, xerr=xerr, height=0.72, color=colors,
        edgecolor=["black" if b else c for b, c in zip(bold, colors, strict=True)],
        linewidth=[1.8 if b else 0.8 for b in bold],
        error_kw={"capsize": 2, "elinewidth": 1.0, "ecolor": "0.25"},
    )  # fmt: skip
    ax.axvline(0.0, color="0.35", lw=0.8, zorder=1)
    for pos, mean, left, right, color in zip(positions, means, *xerr, colors, strict=True):
        if not math.isfinite(mean):
            ax.annotate("n/a", (0, pos), xytext=(4, 0), textcoords="offset points",
                        va="center", fontsize=7, color="0.4", gid="bar-label")  # fmt: skip
            continue
        if abs(mean) <= EQUAL_TOL:
            ax.plot([0.0], [pos], marker="|", markersize=12, markeredgewidth=3.0,
                    color=color, zorder=4, gid="zero-bar")  # fmt: skip
        up = mean >= 0
        ax.annotate(
            short_label(mean), (mean + right if up else mean - left, pos),
            xytext=(4 if up else -4, 0), textcoords="offset points",
            ha="left" if up else "right", va="center", fontsize=7, gid="bar-label",
        )  # fmt: skip
    reach = np.abs(drawn) + errs
    if not reach.size or float(reach.max()) <= EQUAL_TOL:
        ax.set_xlim(-0.15, 1.0)
    else:
        ax.margins(x=0.25)
    ax.set_yticks(positions, names, fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(axis="x", alpha=0.3)


def shown_metrics(
    results: Results, variants: Mapping[str, ModeResult], skip: Collection[str] = NOT_PLOTTED
) -> list[str]:
    """The metrics any of ``variants`` has, in `metric_order`, but ``skip``."""
    metrics = metric_order(results.task, sorted({m for v in variants.values() for m in v.metrics}))
    return [m for m in metrics if m not in skip]


def _paper_metrics(results: Results, tunes: Mapping[str, ModeResult]) -> list[str]:
    """The paper's metrics any of ``tunes`` has, else the first four plotted."""
    found = [
        m
        for m in PAPER_METRICS.get(results.task, [])
        if any(m in v.metrics for v in tunes.values())
    ]
    return found or shown_metrics(results, tunes)[:4]


def bars_figure(
    results: Results, mode: str, title: str = "", colors: dict[str, str] | None = None
) -> Figure | None:
    """Bar chart per metric, one bar per variant in ``mode``; None without that mode."""
    variants = results.in_mode(mode)
    if not variants:
        return None
    metrics = shown_metrics(results, variants)
    if not metrics:
        return None
    names = list(variants)
    colors = colors or variant_colors(names)
    plt = pyplot()
    height = 0.3 * len(names) + 1.1
    fig, axes = grid_axes(plt, len(metrics), 3, 3.3, height, sharey=True)
    fig.set_size_inches(fig.get_size_inches()[0] + 1.8, fig.get_size_inches()[1] + 0.4)
    positions = np.arange(len(names))[::-1]  # the first variant on top
    for ax, metric in zip(axes, metrics, strict=False):
        stats = [variants[n].metrics.get(metric) for n in names]
        seeds = [seed_means(variants[n], metric) for n in names]
        _hbars(ax, positions, names, stats, [colors[n] for n in names], seeds=seeds)
        ax.set_title(metric.replace("_", " "), fontsize=9)
    fig.suptitle(
        title or f"{results.scenario}: {mode} policy, {interval_words(variants.values())} "
        "(a bar of height 0: a thick tick at 0)",
        fontsize=9, wrap=True,
    )  # fmt: skip
    return fig


def interval_words(results: Iterable[ModeResult]) -> str:
    """What the bars' whiskers and dots are, for a figure's title."""
    counts = {r.n_seeds for r in results if r.replicas and r.n_seeds >= 2}
    if not counts:
        return "mean and 95% CI"
    few = min(counts) < FEW_SEEDS
    whisker = "95% CI, or the seeds' range where fewer than 5 seeds" if few else "95% CI"
    return f"mean, {whisker}; dots: each training seed"


def ablation_figure(
    results: Results, what: str, colors: dict[str, str] | None = None, mode: str = "greedy"
) -> Figure | None:
    """An ablation's own figure: fine-tunes against AMULED on the paper's metrics; None without.

    ``kl``: each metric against lambda_KL. Other ablations: a panel per metric that differs
    (`varying_panels`), bars sorted by mean, AMULED outlined, the base policy dashed.
    """
    if what == "budget":
        return budget_figure(results, mode)
    variants = results.in_mode(mode)
    base = variants.pop("base", None)
    tunes = {k: v for k, v in variants.items() if k != "shaped"}
    if not tunes:
        return None
    metrics = _paper_metrics(results, tunes)
    colors = colors or variant_colors(results.variants)
    entries = {name: results.variants[name].panel for name in tunes}
    lambdas = {name: p.lambda_kl if p is not None else None for name, p in entries.items()}
    plt = pyplot()
    if what == "kl" and all(isinstance(v, int | float) for v in lambdas.values()):
        order = sorted(tunes, key=lambda n: (lambdas[n], n))
        fig, axes = grid_axes(plt, len(metrics), 2, 4.6, 3.2)
        for ax, metric in zip(axes, metrics, strict=False):
            stats = [tunes[n].metrics.get(metric) for n in order]
            x = np.arange(len(order))
            y = np.array([mean_of(s) for s in stats])
            err = np.array([half_of(s) for s in stats])
            ax.plot(x, y, color="0.5", lw=1.0, zorder=1)
            for xi, yi, ei, name in zip(x, y, err, order, strict=True):
                ax.errorbar(xi, yi, yerr=ei, fmt="o", color=colors[name], capsize=3, ms=6)
                if math.isfinite(yi):
                    ax.annotate(short_label(yi), (xi, yi), xytext=(5, 4),
                                textcoords="offset points", fontsize=7,
                                gid="bar-label")  # fmt: skip
            _base_line(ax, base, metric, vertical=False)
            ax.set_xticks(x, [f"{lambdas[n]:g}" for n in order], fontsize=8)
            ax.set_xlabel("lambda_KL", fontsize=8)
            ax.set_title(metric.replace("_", " "), fontsize=9)
            ax.grid(alpha=0.3)
        fig.suptitle(
            f"Ablation of lambda_KL: {mode} mean and 95% CI per fine-tune; dashed: base",
            fontsize=9,
        )
        return fig
    panels, equal = varying_panels(results, metrics, mode)
    height = 0.3 * len(tunes) + 1.1
    fig, axes = grid_axes(plt, len(panels), 2, 5.2, height)
    for ax, (panel_mode, metric) in zip(axes, panels, strict=False):
        in_mode = {n: results.variants[n].mode(panel_mode) or ModeResult() for n in tunes}
        means = {n: mean_of(in_mode[n].metrics.get(metric)) for n in tunes}  # no mean: bottom
        order = sorted(tunes, key=lambda n: (means[n] if math.isfinite(means[n]) else -math.inf, n))
        stats = [in_mode[n].metrics.get(metric) for n in order]
        _hbars(ax, np.arange(len(order)), order, stats, [colors[n] for n in order],
               emphasise=[n == "finetune-amuled" for n in order],
               seeds=[seed_means(in_mode[n], metric) for n in order])  # fmt: skip
        base_mode = results.variants["base"].mode(panel_mode) if base is not None else None
        _base_line(ax, base_mode, metric, vertical=True)
        for label in ax.get_yticklabels():
            if label.get_text() == "finetune-amuled":
                label.set_fontweight("bold")
        title = metric.replace("_", " ")
        ax.set_title(title if panel_mode == mode else f"{title} ({panel_mode})", fontsize=9)
    shown = sorted({m for m, _ in panels}, key=lambda m: m != mode)
    note = ""
    if equal:
        note = "\nnot shown, equal for every fine-tune: " + "; ".join(
            f"{', '.join(m.replace('_', ' ') for m in names)} ({m})" for m, names in equal.items()
        )
    fig.suptitle(
        f"Ablation of {what}: each fine-tune's {interval_words(tunes.values())} "
        f"({' and '.join(shown)} policy) "
        "on the paper's metrics that differ between the fine-tunes, sorted (largest on top); "
        f"AMULED outlined in black, dashed: base{note}",
        fontsize=9, wrap=True,
    )  # fmt: skip
    return fig


def varying_panels(
    results: Results, metrics: Sequence[str], mode: str = "greedy"
) -> tuple[list[tuple[str, str]], dict[str, list[str]]]:
    """The ``(mode, metric)`` panels of an ablation figure and ``{mode: [metric left out]}``.

    A metric equal for every fine-tune is left out; the run's other modes add the metrics that
    differ there; when none differs, every metric of ``mode`` is shown.
    """
    tunes = [n for n in results.variants if n not in ("base", "shaped")]
    modes = sorted({m for n in tunes for m in results.variants[n].modes()}, key=lambda m: m != mode)
    panels: list[tuple[str, str]] = []
    equal: dict[str, list[str]] = {}
    for panel_mode in modes:
        for metric in metrics:
            means = [
                mean_of(r.metrics.get(metric))
                for n in tunes
                if (r := results.variants[n].mode(panel_mode)) is not None
            ]
            finite = [v for v in means if math.isfinite(v)]
            if not finite:
                continue
            if len(finite) > 1 and max(finite) - min(finite) > EQUAL_TOL:
                panels.append((panel_mode, metric))
            else:
                equal.setdefault(panel_mode, []).append(metric)
    if not panels:
        return [(mode, m) for m in metrics], {}
    return panels, equal


#: Colours of the budget ablation's selections (`budget_figure`; random also dashed).
SELECTION_COLORS = {"uncertainty": "tab:blue", "random": "tab:orange"}


def budget_points(
    results: Results,
) -> tuple[list[dict[str, Any]], str | None]:
    """The budget ablation's distilled fine-tunes as points, and the full-feedback one.

    ``budget`` is the share of distinct states a point may ask (for a count, the share asked);
    the full-feedback name is None without one.
    """
    points: list[dict[str, Any]] = []
    full: str | None = None
    for name, entry in results.variants.items():
        settings = entry.panel.distill if entry.panel is not None else None
        if not settings:
            if entry.panel is not None and entry.panel.feedback == "amuled" and full is None:
                full = name
            continue
        report = (entry.feedback.distill if entry.feedback is not None else None) or {}
        budget = settings.get("budget")
        share = budget if isinstance(budget, float) else report.get("asked_share")
        selection = "all" if share == 1.0 else str(settings.get("selection"))
        points.append({
            "variant": name, "budget": share, "selection": selection, "distill": report,
        })  # fmt: skip
    points.sort(key=lambda p: (p["selection"], -(p["budget"] or 0.0), p["variant"]))
    return points, full


def budget_figure(results: Results, mode: str = "greedy") -> Figure | None:
    """The budget ablation's figure: each paper metric against the budget (None: none distilled).

    Also a panel of the model's held-out fused TV; x is the share asked (log scale), one colour
    per selection; the full-feedback fine-tune is a grey band, the base a dashed line.
    """
    points, full = budget_points(results)
    points = [p for p in points if isinstance(p["budget"], int | float) and p["budget"] > 0]
    if not points:
        return None
    variants = results.variants
    tunes = {p["variant"]: variants[p["variant"]].mode(mode) or ModeResult() for p in points}
    panels = [*_paper_metrics(results, tunes), "holdout_tv_fused"]
    plt = pyplot()
    fig, axes = grid_axes(plt, len(panels), 2, 4.6, 3.2)
    base = variants["base"].mode(mode) if "base" in variants else None
    full_stats = variants[full].mode(mode) if full else None
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
                stats = [tunes[p["variant"]].metrics.get(metric) for p in line]
                ys = np.array([mean_of(s) for s in stats])
                err = np.array([half_of(s) for s in stats])
            color = SELECTION_COLORS.get(selection, "0.3")
            style = "s--" if selection == "random" else "o-"  # visible where the lines meet
            ax.errorbar(xs, ys, yerr=err, fmt=style, color=color, capsize=3, ms=5, lw=1.2,
                        label=selection, gid=f"selection-{selection}")  # fmt: skip
        if metric != "holdout_tv_fused":
            stat = full_stats.metrics.get(metric) if full_stats is not None else None
            mean = mean_of(stat)
            if math.isfinite(mean):
                half = half_of(stat)
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
    axes[0].legend(fontsize=7, title="selection", title_fontsize=7)
    fig.suptitle(
        f"Ablation of the feedback budget: {mode} mean and 95% CI per fine-tune; grey band: "
        "every state asked (no model); dashed: base",
        fontsize=9,
    )
    return fig


def _base_line(ax: Axes, base: ModeResult | None, metric: str, *, vertical: bool) -> None:
    value = mean_of(base.metrics.get(metric) if base is not None else None)
    if math.isfinite(value):
        line = ax.axvline if vertical else ax.axhline
        z = 5 if vertical else 0
        line(value, color=COLORS["reference"], ls="--", lw=1.1, zorder=z, gid="base-line")
