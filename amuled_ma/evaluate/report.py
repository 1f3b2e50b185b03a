"""The run report: ``report.md`` with PNG figures (matplotlib, headless).

Figures: learning curves with 95% bands per variant, bar charts of the paper's metrics
with 95% CIs per variant (and per cluster in the cluster ablation), one FindMilk greedy
trajectory on the grid per variant, one Driving greedy episode per variant, and a table
of the fused belief's diagnostics (mean weight of each cluster, mean conflict, replay
miss rate) for every fine-tuned variant.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.evaluate.evaluator import metric_order
from amuled_ma.evaluate.stats import t_quantile
from amuled_ma.learn.experiments import split_replica

#: Curve keys plotted per task (the first that exists in a curve is used).
_CURVE_KEYS = {
    "findmilk": ["episode/return_env", "episode/steps_to_milk", "episode/crying_pacified",
                 "episode/sleeping_woken"],
    "driving": ["episode/return_env", "episode/collisions", "episode/rescues",
                "episode/lane_changes"],
}  # fmt: skip
_FT_KEYS = ["feedback/feedback_reward", "feedback/kl"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


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


def _finite_or_zero(value: float | None) -> float:
    """An error bar's half width; an undefined interval (one value) draws none."""
    return value if value is not None and math.isfinite(value) else 0.0


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


def plot_curves(
    curves: dict[str, list[list[dict]]], keys: list[str], path: Path, title: str
) -> Path | None:
    """Plot one panel per key, one line (rolling mean, 95% band) per variant."""
    keys = [k for k in keys if any(k in row for cs in curves.values() for c in cs for row in c)]
    if not keys or not curves:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys, strict=True):
        for name, replicas in curves.items():
            if not any(key in row for c in replicas for row in c):
                continue
            x, mean, half = curve_band(replicas, key)
            label = name if len(replicas) == 1 else f"{name} ({len(replicas)} seeds)"
            (line,) = ax.plot(x, mean, label=label, lw=1.4)
            ax.fill_between(x, mean - half, mean + half, color=line.get_color(), alpha=0.2, lw=0)
        ax.set_title(key.split("/", 1)[-1].replace("_", " "))
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    several = any(len(r) > 1 for r in curves.values())
    band = "over seeds" if several else "over a 5% window of iterations"
    fig.suptitle(f"{title} (rolling mean over 5% of iterations, 95% band {band})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_bars(results: dict[str, Any], mode: str, path: Path, title: str = "") -> Path | None:
    """Bar chart per metric, one bar per variant, 95% CI error bars."""
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    metrics = metric_order(
        results.get("task", ""), sorted({m for v in variants.values() for m in v["metrics"]})
    )
    metrics = [m for m in metrics if m not in ("terminated", "return_shaping", "return")]
    plt = _plt()
    cols = min(4, len(metrics))
    rows = math.ceil(len(metrics) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), squeeze=False)
    names = list(variants)
    for ax, metric in zip(axes.flat, metrics, strict=False):
        means = [variants[n]["metrics"].get(metric, {}).get("mean", np.nan) for n in names]
        errs = [
            _finite_or_zero(variants[n]["metrics"].get(metric, {}).get("half_width")) for n in names
        ]
        ax.bar(
            range(len(names)),
            means,
            yerr=errs,
            capsize=3,
            color=[f"C{i}" for i in range(len(names))],
        )
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=40, ha="right", fontsize=7)
        ax.set_title(metric.replace("_", " "), fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    for ax in list(axes.flat)[len(metrics) :]:
        ax.axis("off")
    fig.suptitle(title or f"{results.get('scenario')}: {mode} policy, mean and 95% CI", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_findmilk(results: dict[str, Any], path: Path, mode: str = "greedy") -> Path | None:
    """One FindMilk greedy trajectory per variant on the 8x8 grid (babies, milk, path)."""
    variants = {k: v[mode]["trajectory"] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    plt = _plt()
    n = len(variants)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.4), squeeze=False)
    for ax, (name, traj) in zip(axes[0], variants.items(), strict=True):
        obs = np.array(traj["obs"])
        size = 8
        layout = traj.get("layout") or {}
        for x, y in layout.get("sleeping", []):
            ax.scatter(x, y, marker="s", s=160, color="tab:blue", alpha=0.6)
        for x, y in layout.get("crying", []):
            ax.scatter(x, y, marker="o", s=160, color="tab:red", alpha=0.6)
        ax.scatter(obs[0, 2], obs[0, 3], marker="*", s=260, color="gold", edgecolor="k", zorder=3)
        jitter = np.linspace(-0.12, 0.12, len(obs))
        ax.plot(obs[:, 0] + jitter, obs[:, 1] + jitter, "-", color="k", lw=1.2, zorder=4)
        ax.scatter(obs[0, 0], obs[0, 1], marker="^", s=80, color="green", zorder=5)
        ax.set_xlim(-0.5, size - 0.5)
        ax.set_ylim(-0.5, size - 0.5)
        ax.set_xticks(range(size))
        ax.set_yticks(range(size))
        ax.grid(alpha=0.3)
        ax.set_aspect("equal")
        ax.set_title(f"{name}\n{len(traj['actions'])} steps", fontsize=8)
    fig.suptitle(
        "FindMilk greedy trajectory (green ▲ start, ★ milk, red ● crying, blue ■ sleeping)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_driving(results: dict[str, Any], path: Path, mode: str = "greedy") -> Path | None:
    """One Driving greedy episode per variant: lane over time with the episode's events."""
    variants = {k: v[mode]["trajectory"] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return None
    plt = _plt()
    n = len(variants)
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.6 * n + 0.6), squeeze=False, sharex=True)
    markers = {"collision": ("x", "red"), "rescue": ("o", "green"), "grandma": ("o", "green")}
    for ax, (name, traj) in zip(axes[:, 0], variants.items(), strict=True):
        obs = np.array(traj["obs"])
        lane = obs[:, -5:].argmax(axis=1) if obs.shape[1] >= 5 else np.zeros(len(obs))
        steps = np.arange(len(lane))
        ax.step(steps, lane, where="post", color="k", lw=1.2)
        for key, values in traj.get("events", {}).items():
            style = next((v for k, v in markers.items() if k in key), None)
            if style is None or key.startswith("r_"):
                continue
            hits = [i + 1 for i, v in enumerate(values) if v]
            if hits:
                ax.scatter(
                    hits, lane[hits], marker=style[0], color=style[1], s=40, label=key, zorder=3
                )
        ax.set_ylabel(name, fontsize=7, rotation=0, ha="right")
        ax.set_yticks(range(5))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, loc="upper right")
    axes[-1, 0].set_xlabel("step")
    fig.suptitle("Driving greedy episode: lane (0-4) over time, with events", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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


def metrics_table(results: dict[str, Any], mode: str) -> str:
    """Markdown table: one row per variant, one column per metric, ``mean ± 95% CI``."""
    variants = {k: v[mode] for k, v in results["variants"].items() if mode in v}
    if not variants:
        return ""
    metrics = metric_order(
        results.get("task", ""), sorted({m for v in variants.values() for m in v["metrics"]})
    )
    metrics = [m for m in metrics if m not in ("terminated", "return")]
    head = "| variant | seeds | " + " | ".join(metrics) + " |"
    lines = [head, "|---|---|" + "---|" * len(metrics)]
    for name, data in variants.items():
        cells = [format_stat(data["metrics"].get(m)) for m in metrics]
        lines.append(f"| {name} | {data.get('n_seeds', 1)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


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
            f"{source}{f' ({detail})' if detail else ''} | {panel.get('fusion') or '-'} |"
        )
    if not rows:
        return ""
    head = (
        "| variant | feedback | recipe | lambda_KL | iterations | agents | source | fusion |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    return head + "\n" + "\n".join(rows) + "\n"


def write_report(run_dir: Path, results: dict[str, Any], *, title: str | None = None) -> Path:
    """Write ``report.md`` and its PNG figures into ``run_dir``.

    Args:
        run_dir: The run directory (curves are read from its variant folders).
        results: The evaluation results (:func:`~amuled_ma.evaluate.evaluator.evaluate_run`).
        title: Report title.

    Returns:
        Path of ``report.md``.

    """
    run_dir = Path(run_dir)
    task = results.get("task", "")
    curves = load_curves(run_dir)
    base_curves = {k: v for k, v in curves.items() if not k.startswith("finetune")}
    ft_curves = {k: v for k, v in curves.items() if k.startswith("finetune")}
    figures: list[tuple[str, Path | None]] = [
        (
            "Base training curves",
            plot_curves(base_curves, _CURVE_KEYS.get(task, ["episode/return_env"]),
                        run_dir / "curves_base.png", "base training"),
        ),
        (
            "Fine-tuning curves",
            plot_curves(ft_curves, _FT_KEYS + _CURVE_KEYS.get(task, [])[1:],
                        run_dir / "curves_finetune.png", "fine-tuning"),
        ),
    ]  # fmt: skip
    for mode in ("greedy", "sampled"):
        figures.append(
            (f"Metrics, {mode} policy", plot_bars(results, mode, run_dir / f"metrics_{mode}.png"))
        )
    if task == "findmilk":
        figures.append(
            ("A FindMilk trajectory", plot_findmilk(results, run_dir / "trajectory_findmilk.png"))
        )
    elif task == "driving":
        figures.append(
            ("A Driving episode", plot_driving(results, run_dir / "episode_driving.png"))
        )
    n = results.get("episodes")
    lines = [
        f"# {title or 'Run report: ' + str(results.get('scenario'))}",
        "",
        f"Task `{task}`; {n} evaluation episodes per variant and mode (seeds from "
        f"{results.get('seed')}); figures are mean ± half-width of the "
        f"{int(100 * results.get('confidence', 0.95))}% Student-t confidence interval. "
        "A variant trained with one seed has its interval over the evaluation episodes; "
        "one trained with several (column *seeds*) has the mean of its per-seed means and "
        "the interval over the seeds, so it covers the spread of training runs.",
        "",
    ]
    for mode in ("greedy", "sampled"):
        table = metrics_table(results, mode)
        if table:
            lines += [f"## Metrics, {mode} policy", "", table]
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
        "## Figures",
        "",
    ]
    for caption, path in figures:
        if path is not None:
            lines += [f"### {caption}", "", f"![{caption}]({path.name})", ""]
    report = run_dir / "report.md"
    report.write_text("\n".join(lines))
    return report
