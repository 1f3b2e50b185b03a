"""The report's Markdown tables of results."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from amuled_ma.beliefs.types import FUSED_STATUSES
from amuled_ma.evaluate.evaluator import PAPER_METRICS
from amuled_ma.evaluate.numbers import format_count, markdown_table
from amuled_ma.evaluate.paper import (
    PAPER_COLUMNS,
    PAPER_MODE,
    PAPER_RECIPE,
    PAPER_SOURCE,
    paper_row,
)
from amuled_ma.evaluate.report.bars import budget_points, shown_metrics
from amuled_ma.evaluate.report.plotting import EQUAL_TOL, format_stat, mean_of
from amuled_ma.evaluate.results import ModeResult, Results, Stat
from amuled_ma.evaluate.stats import t_quantile


def diagnostics_table(results: Results, finetunes: int | None = None) -> str:
    """Mean per-cluster weight, conflict and miss rate per variant, or a note why there are none."""
    rows = {k: v.feedback for k, v in results.variants.items() if v.feedback is not None}
    if not rows:
        if finetunes:
            return (
                "_No fine-tune of this run recorded fused-belief diagnostics (a policy "
                "imported or trained elsewhere comes without its `feedback.json`)._\n"
            )
        return "_No fine-tuned variant in this run._\n"
    clusters = sorted({c for fb in rows.values() for c in fb.mean_weight})
    head = ["variant", *clusters, "mean conflict", "replay miss rate", "unique states"]
    lines = []
    for name, fb in rows.items():
        weights = fb.mean_weight
        conflict = fb.mean_conflict
        cells = [name]
        cells += [f"{weights[c]:.3f}" if c in weights else "" for c in clusters]
        cells.append("" if conflict is None else f"{conflict:.3f}")
        cells.append(f"{100 * fb.miss_rate:.1f}%")
        cells.append("" if fb.unique_states is None else format_count(fb.unique_states))
        lines.append(cells)
    return markdown_table(head, lines)


#: Columns of `agents_table`: (status key, heading).
_AGENT_COLUMNS = (
    ("repaired", "repaired"),
    ("abstained", "abstained"),
    ("replay_miss", "replay miss"),
    ("timeout", "timeout"),
    ("error", "error"),
)


#: Columns of `agents_table` for a distilled feedback: the model's answers (for states
#: not asked; for an asked state's miss) and the states it could not answer.
_MODEL_COLUMNS = (
    ("distilled", "by the model"),
    ("distilled_miss", "miss by the model"),
    ("unasked", "unasked"),
)


def agents_table(results: Results) -> str:
    """Per fine-tune and panel agent, the share of each belief status; ``""`` without counts.

    Not answered: every status but the fused ones; a distilled feedback adds the model's columns.
    """
    lines = []
    rows = [
        (name, agent, row)
        for name, entry in results.variants.items()
        if entry.feedback is not None
        for agent, row in entry.feedback.agents.items()
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
        lines.append(cells)
    head = ["variant", "agent", "beliefs", *(h for _, h in columns), "not answered"]
    return markdown_table(head, lines)


def servers_table(results: Results) -> str:
    """Per fine-tune and LLM server, what it was asked and did; ``""`` without servers."""
    lines = []
    for name, entry in results.variants.items():
        servers = entry.feedback.llm_servers if entry.feedback is not None else None
        for host, row in (servers or {}).items():
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
            lines.append(cells)
    head = ["variant", "server", "sent", "answered", "failed", "retried elsewhere",
            "out / back", "mean latency (s)", "p95 latency (s)"]  # fmt: skip
    return markdown_table(head, lines)


def _tv(value: float | None) -> str:
    return "-" if value is None else f"{float(value):.3f}"


def budget_table(results: Results) -> str:
    """The budget accounting of every distilled fine-tune (`DistilledSource.report`), or ``""``."""
    lines = []
    for name, entry in results.variants.items():
        d = entry.feedback.distill if entry.feedback is not None else None
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
        lines.append(cells)
    head = ["variant", "budget", "selection", "states visited", "asked", "answered by the model",
            "misses by the model", "requests forwarded / sent", "refits",
            "held-out TV, fused", "held-out TV per member"]  # fmt: skip
    return markdown_table(head, lines)


def budget_ablation_table(results: Results, mode: str = "greedy") -> str:
    """The budget ablation's paper metrics against the budget, or ``""`` without one."""
    points, full = budget_points(results)
    if not points:
        return ""
    variants = results.variants
    data = {n: variants[n].mode(mode) or ModeResult()
            for n in [*(p["variant"] for p in points), full] if n}  # fmt: skip
    metrics = [m for m in PAPER_METRICS.get(results.task, [])
               if any(m in v.metrics for v in data.values())]  # fmt: skip
    head = ["selection", "budget", "variant", "asked", "requests sent", "held-out TV, fused",
            *metrics]  # fmt: skip
    lines = []
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
        cells += [format_stat(data[p["variant"]].metrics.get(m)) for m in metrics]
        lines.append(cells)
    if full:
        stats = data[full].metrics
        cells = ["full feedback", "100%", full, "every state", "-", "-"]
        lines.append(cells + [format_stat(stats.get(m)) for m in metrics])
    return markdown_table(head, lines)


def _percent(count: float, total: float) -> str:
    return f"{100 * count / total:.1f}%" if total else "-"


#: Metrics left out of the tables (``return_shaping`` stays, unlike in the figures).
_NOT_TABULATED = ("terminated", "return")


def metrics_table(results: Results, mode: str) -> str:
    """Markdown table: one row per variant, one column per metric, ``mean ± 95% CI``."""
    variants = results.in_mode(mode)
    if not variants:
        return ""
    metrics = shown_metrics(results, variants, _NOT_TABULATED)
    rows = [
        [name, str(data.n_seeds), *(format_stat(data.metrics.get(m)) for m in metrics)]
        for name, data in variants.items()
    ]
    return markdown_table(["variant", "seeds", *metrics], rows)


def base_differences(
    results: Results, mode: str, base: str = "base"
) -> dict[str, dict[str, float]]:
    """``{variant: {metric: mean - base mean}}`` where both are finite; ``{}`` without ``base``."""
    variants = results.in_mode(mode)
    if base not in variants:
        return {}
    ref = variants[base].metrics
    out: dict[str, dict[str, float]] = {}
    for name, data in variants.items():
        if name == base:
            continue
        row = {}
        for metric, stat in data.metrics.items():
            mine, theirs = mean_of(stat), mean_of(ref.get(metric))
            if math.isfinite(mine) and math.isfinite(theirs):
                row[metric] = mine - theirs
        out[name] = row
    return out


def same_as_base(
    results: Results, mode: str = "greedy", finetunes: Iterable[str] | None = None
) -> list[str]:
    """The fine-tunes whose every metric equals the base's within 1e-9, in results order.

    ``finetunes`` defaults to the variants with a ``panel`` entry or named ``finetune*``; a
    variant sharing no metric with base is not listed.
    """
    if finetunes is None:
        finetunes = [
            n
            for n, v in results.variants.items()
            if v.panel is not None or n.startswith("finetune")
        ]
    tunes = set(finetunes)
    return [
        name
        for name, row in base_differences(results, mode).items()
        if name in tunes and row and all(abs(d) <= EQUAL_TOL for d in row.values())
    ]


def differences_table(results: Results, mode: str) -> str:
    """Markdown table of `base_differences`: ``+1.20``, ``-0.40``, ``=`` (equal)."""
    diffs = base_differences(results, mode)
    if not diffs:
        return ""
    variants = results.in_mode(mode)
    metrics = shown_metrics(results, variants, _NOT_TABULATED)
    rows = [
        [
            name,
            *(
                "" if m not in row else "=" if abs(row[m]) <= EQUAL_TOL else f"{row[m]:+.2f}"
                for m in metrics
            ),
        ]
        for name, row in diffs.items()
    ]
    return markdown_table(["variant", *metrics], rows)


#: How a metric's difference to the base reads: (verb phrase before, noun after).
_PHRASES: dict[str, tuple[str, str]] = {
    "steps_to_milk": ("takes", "steps to the milk"),
    "crying_pacified": ("pacifies", "crying babies"),
    "sleeping_woken": ("wakes", "sleeping babies"),
    "collisions": ("has", "collisions"),
    "rescues": ("rescues", "grandmas"),
    "lane_changes": ("makes", "lane changes"),
    "non_straight_steps": ("takes", "non-straight steps (the authors' lane-change count)"),
}


def paper_table(results: Results, recipes: Mapping[str, str | None] | None = None) -> str:
    """The paper's row (`PAPER_ROWS`, sampled policy) beside ours, or ``""`` without one.

    Ours are sampled when evaluated so (else greedy, said in the column); ``recipes`` gives
    each fine-tune's recipe (``-`` for the others).
    """
    columns = PAPER_COLUMNS.get(results.task)
    if not columns:
        return ""
    mode = PAPER_MODE if results.in_mode(PAPER_MODE) else "greedy"
    ours = results.in_mode(mode)
    lines = []
    for name, data in ours.items():
        row = paper_row(results.task, name)
        if row is None:
            continue
        paper = " / ".join(f"{row.values[m]:.1f}" for m in columns)
        mine = " / ".join(format_stat(data.metrics.get(m)) for m in columns)
        recipe = (recipes or {}).get(name) or "-"
        lines.append([name, row.label, paper, mine, recipe])
    head = [
        "variant",
        "the paper's row",
        f"the paper ({PAPER_RECIPE}' recipe, {PAPER_MODE})",
        f"ours ({mode}, mean ± 95% CI)",
        "our recipe",
    ]
    return (
        f"Columns: {' / '.join(columns)}. The paper's figures: {PAPER_SOURCE}.\n\n"
        + markdown_table(head, lines)
    )


def difference_ci(
    mine: Stat | None, base: Stat | None, confidence: float = 0.95
) -> tuple[float, float, float] | None:
    """A variant's mean minus the base's with a Welch interval; None without means, counts, spreads.

    The interval is the one of ``scipy.stats.ttest_ind(equal_var=False)``, which does not return
    it, so the Welch-Satterthwaite ``df`` is written out; with no spread on either side it is
    the difference itself.
    """
    if mine is None or base is None:
        return None
    a, b = mean_of(mine), mean_of(base)
    na, nb, sa, sb = mine.n, base.n, mine.std, base.std
    if not (math.isfinite(a) and math.isfinite(b)) or not na or not nb:
        return None
    if sa is None or sb is None or not (math.isfinite(sa) and math.isfinite(sb)) or min(na, nb) < 2:
        return None  # one value (or none): the spread is unknown, no interval is claimed
    va, vb = sa**2 / na, sb**2 / nb
    diff = a - b
    if va + vb <= 0:
        return diff, diff, diff
    df = (va + vb) ** 2 / (va**2 / (na - 1) + vb**2 / (nb - 1))  # Welch-Satterthwaite
    half = t_quantile(df, confidence) * math.sqrt(va + vb)
    return diff, diff - half, diff + half


def movement_sentence(
    results: Results, variant: str = "finetune-amuled", mode: str = "sampled", label: str = "AMULED"
) -> str:
    """One sentence: did the fine-tune move from the base beyond noise, which way (``""``: no data).

    A metric moved when `difference_ci` excludes 0; a fine-tune that misses the goal in some
    episodes says so.
    """
    modes = results.in_mode(mode)
    if variant not in modes or "base" not in modes:
        return ""
    mine, base = modes[variant].metrics, modes["base"].metrics
    level = f"{100 * results.confidence:g}% CI"
    moved, still = [], []
    for metric in PAPER_COLUMNS.get(results.task, tuple(sorted(set(mine) & set(base)))):
        found = difference_ci(mine.get(metric), base.get(metric), results.confidence)
        if found is None:
            continue
        diff, low, high = found
        verb, noun = _PHRASES.get(metric, ("has", metric))
        if low > EQUAL_TOL or high < -EQUAL_TOL:
            way = "more" if diff > 0 else "fewer"
            if low == high:
                ci = "in every episode: both policies are deterministic"
            else:
                near, far = sorted((abs(low), abs(high)))
                ci = f"{level} {near:.2f} to {far:.2f} {way}"
            moved.append(f"{verb} {abs(diff):.2f} {way} {noun} than the base ({ci})")
        else:
            still.append(noun)
    where = f"{label} ({variant}, {mode} policy)"
    if not moved:
        sentence = (
            f"{where} did not move from the base beyond noise: the {level} of every "
            "difference contains 0."
        )
    else:
        sentence = f"{where} " + "; ".join(moved)
        if still:
            sentence += f"; no difference beyond noise in {', '.join(still)}"
        sentence += "."
    reached = mine.get("reached_milk")
    share = mean_of(reached)
    if math.isfinite(share) and share < 1.0 - EQUAL_TOL:
        sentence += (
            f" It reaches the milk in only {100 * share:.0f}% of the episodes (an episode "
            "that misses it counts the step limit as its steps)."
        )
    return sentence
