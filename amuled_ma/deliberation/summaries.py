"""Feedback diagnostics in words and figures: statuses per agent, the budget, the store, servers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from amuled_ma.beliefs.types import MODEL_STATUSES
from amuled_ma.deliberation.feedback_base import ANSWERED, REPORTED_STATUSES

if TYPE_CHECKING:
    from amuled_ma.beliefs.types import BeliefSource


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """Format a `Feedback.summary` for people: a headline, then a line per agent."""
    statuses = summary.get("statuses") or {}
    total = sum(statuses.values())
    failed = total - sum(n for s, n in statuses.items() if s in ANSWERED)
    others = [s for s in statuses if s not in REPORTED_STATUSES and s not in ANSWERED]
    parts = ", ".join(f"{s} {statuses.get(s, 0):,}" for s in (*REPORTED_STATUSES[2:], *others))
    rate = 100 * failed / total if total else 0.0
    lines = [f"beliefs not answered: {rate:.2f}% of {total:,} ({parts})"]
    distill = summary.get("distill")
    if distill:
        lines.append(distill_line(distill))
        model = sum(statuses.get(s, 0) for s in MODEL_STATUSES)
        share = 100 * model / total if total else 0.0
        cells = ", ".join(f"{s} {statuses.get(s, 0):,}" for s in MODEL_STATUSES)
        lines.append(f"  beliefs from the distilled model: {share:.2f}% of {total:,} ({cells})")
    for agent, row in (summary.get("agents") or {}).items():
        of = row.get("total") or 0
        agent_cells = [
            f"{status} {n:,}"
            + (f" ({100 * n / of:.2f}%)" if n and of and status not in ANSWERED else "")
            for status, n in row.items()
            if status not in ("total", "failed", "failure_rate")
        ]
        lines.append(f"  {agent}: {', '.join(agent_cells)}")
    lines += [f"  reading: {sentence}" for sentence in readings(summary)]
    servers = summary.get("llm_servers") or {}
    if servers:
        from amuled_ma.servers.pool import host_lines

        lines.append(f"LLM servers ({len(servers)}):")
        lines += [f"  {line}" for line in host_lines(servers)]
    return lines


#: An agent whose replies were repaired more often than this (of its answers) mostly did not
#: follow the requested format: past half, the parser's reading is the typical answer.
REPAIRED_MAJORITY = 0.5
#: Held-out total variation up to which the distilled model reads as close to the panel
#: (at most a tenth of the probability mass placed differently) ...
TV_CLOSE = 0.1
#: ... and above which it reads as far (over a third placed differently: its most likely
#: action can differ from the panel's).
TV_FAR = 1 / 3
#: Mean belief entropy, as a share of the maximum (log2 of the action count), at or above
#: which an agent's beliefs read as nearly flat (0.26/0.24/0.24/0.26 over four actions: 0.9994).
FLAT_ENTROPY = 0.95


def readings(summary: Mapping[str, Any]) -> list[str]:
    """One sentence per figure of a feedback summary that tells about the result."""
    out: list[str] = []
    for agent, row in (summary.get("agents") or {}).items():
        answered = row.get("ok", 0) + row.get("repaired", 0)
        repaired = row.get("repaired", 0)
        if answered and repaired / answered > REPAIRED_MAJORITY:
            out.append(
                f"{agent}: {100 * repaired / answered:.0f}% of answers needed a repair: the "
                "model rarely followed the requested format; its beliefs are the parser's "
                "reading of free text"
            )
    distill = summary.get("distill") or {}
    tv = distill.get("holdout_tv_fused")
    if tv is not None:
        verdict = (
            "close to the panel"
            if tv <= TV_CLOSE
            else "far from the panel: its most likely action can differ from the panel's"
            if tv > TV_FAR
            else "a rough stand-in for the panel"
        )
        out.append(
            f"held-out TV {tv:.2f}: on states it was not fit to, the distilled model places "
            f"{100 * tv:.0f}% of the probability mass differently from the panel; {verdict}"
        )
    statuses = summary.get("statuses") or {}
    total = sum(statuses.values())
    model = sum(statuses.get(s, 0) for s in MODEL_STATUSES)
    if distill and total and model:
        out.append(
            f"{100 * model / total:.0f}% of the beliefs came from the distilled model, not the "
            "panel: on those steps the reward is the distilled model's guess (its agreement "
            "is the held-out TV)"
        )
    weights = summary.get("mean_weight") or {}
    shares = summary.get("mean_entropy_share") or {}
    if weights and shares:
        top = max(weights, key=lambda a: weights[a])
        share = shares.get(top)
        if share is not None and share >= FLAT_ENTROPY and len(weights) > 1:
            out.append(
                f"{top}'s beliefs are nearly flat (entropy {share:.2f} of max) yet it carries "
                f"the largest weight ({weights[top]:.2f}): Xiao's weighting rewards information "
                "volume (Deng entropy), so a flat agent gains weight; consider dropping it or "
                "giving it a prior weight"
            )
    return out


def distill_line(report: Mapping[str, Any]) -> str:
    """One line of a distilled feedback's accounting (``Feedback.summary()["distill"]``)."""
    budget = report.get("budget")
    shown = f"{100 * budget:g}%" if isinstance(budget, float) else f"{budget} states"
    visited, asked = report.get("visited_states", 0), report.get("asked_states", 0)
    line = (
        f"  feedback budget {shown} ({report.get('selection')}): asked {asked:,} of "
        f"{visited:,} distinct states ({100 * report.get('asked_share', 0.0):.1f}%), the model "
        f"answered {report.get('model_states', 0):,}; {report.get('requests_sent', 0):,} "
        f"requests sent; {report.get('refits', 0)} refits"
    )
    if report.get("miss_answers"):
        line += f"; {report['miss_answers']:,} misses answered by the model"
    tv = report.get("holdout_tv_fused")
    if tv is not None:
        states = report.get("holdout_states")
        line += f"; held-out TV to the panel {tv:.3f} (fused, {states} states)"
    return line


def nested_sources(source: BeliefSource | None) -> list[Any]:
    """A belief source and every source inside it, each once."""
    found: list[Any] = []
    seen: set[int] = set()

    def walk(obj: object) -> None:
        if obj is None or id(obj) in seen:
            return
        seen.add(id(obj))
        found.append(obj)
        walk(getattr(obj, "source", None))
        walk(getattr(obj, "fallback", None))
        walk(getattr(obj, "default", None))
        for member in getattr(obj, "members", None) or ():
            walk(member[0] if isinstance(member, tuple) else member)

    walk(source)
    return found


def llm_server_stats(source: BeliefSource | None) -> dict[str, dict[str, Any]]:
    """``{host: figures}`` of every LLM server inside ``source``; empty without one."""
    found = [
        obj.server_stats()
        for obj in nested_sources(source)
        if callable(getattr(obj, "server_stats", None))
    ]
    if not found:
        return {}
    from amuled_ma.servers.pool import merge_host_stats

    return merge_host_stats(found)


def store_stats(source: BeliefSource | None) -> dict[str, int]:
    """The belief store's figures over a source: requests, unique, store_hits, asked."""
    from amuled_ma.beliefs.store.cached import CacheStats

    found = [getattr(obj, "stats", None) for obj in nested_sources(source)]
    stats = [s for s in found if isinstance(s, CacheStats)]
    total = {k: sum(getattr(s, k) for s in stats) for k in ("requests", "unique", "store_hits")}
    return {**total, "asked": sum(s.misses for s in stats)}


def describe_identity(identity: Mapping[str, Any]) -> str:
    """A source in words: ``replay (findmilk-gpt-4o-mini.json)``, ``ollama (llama3.1:8b)``."""
    kind = str(identity.get("source", "source"))
    if kind == "rules":  # never a model's name: the rule answers, no cluster text is read
        policy = identity.get("policy") or "human"
        return f"rules (the task's rule {policy!r}; the cluster's text is not read)"
    files = [r.get("file") for r in identity.get("recordings") or () if isinstance(r, dict)]
    detail = ", ".join(str(f) for f in files if f) or identity.get("model") or ""
    return f"{kind} ({detail})" if detail else kind
