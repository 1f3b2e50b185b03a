"""Evaluate trained policies: N episodes, greedy and sampled, paper metrics with 95% CIs.

Every episode runs in its own task copy (copy ``i`` seeded ``seed + i``), all stepped
together; each copy's first episode is recorded with the task's own ``info["episode"]``.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.beliefs.types import FUSED_STATUSES
from amuled_ma.errors import AmuledError, CheckpointError
from amuled_ma.evaluate.results import RESULTS_FILES, Results, write_results
from amuled_ma.evaluate.rollout import TrajectoryRecorder, rollout
from amuled_ma.evaluate.stats import mean_ci
from amuled_ma.files.safe import check_write_targets, checked_read_path
from amuled_ma.learn.checkpoints import LAST
from amuled_ma.learn.policies import load_policy
from amuled_ma.monitor.progress import Progress
from amuled_ma.records.run_record import RunRecord
from amuled_ma.scenario import EvaluationConfig, PPOConfig, TaskConfig

#: The paper's metrics per task, in report order (others follow alphabetically).
PAPER_METRICS = {
    "findmilk": ["steps_to_milk", "crying_pacified", "sleeping_woken", "reached_milk"],
    "driving": ["collisions", "rescues", "lane_changes", "non_straight_steps"],
}
#: A fine-tune's fused-belief diagnostics, in its variant folder.
FEEDBACK_FILE = "feedback.json"
#: Largest ``feedback.json`` read [bytes] (a fine-tune's is about 4 KB).
MAX_FEEDBACK_BYTES = 16 * 2**20


def read_feedback(folder: Path) -> dict[str, Any] | None:
    """A variant folder's ``feedback.json`` or None; AmuledError: too large, unsafe, not JSON."""
    from amuled_ma.files.limits import read_bounded_json

    path = checked_read_path(folder, FEEDBACK_FILE)
    if not path.is_file():
        return None
    fix = (
        "is it the right folder? It is written by 'amuled finetune'; fine-tune the variant "
        "again with --force, or delete the file (the report then has no diagnostics for it)"
    )
    data = read_bounded_json(
        path, MAX_FEEDBACK_BYTES, "diagnostics file", note="a fine-tune's is about 4 KB", fix=fix
    )
    if not isinstance(data, dict):
        raise AmuledError(f"{path}: expected a JSON object, found {type(data).__name__}; {fix}")
    return data


def run_episodes(
    actor: torch.nn.Module,
    task_config: TaskConfig,
    *,
    episodes: int,
    mode: str = "greedy",
    seed: int = 10_000,
    task_factory: Callable[..., Any] | None = None,
    record_trajectory: bool = True,
) -> tuple[list[dict[str, float]], dict[str, Any]]:
    """Per-episode metrics (`rollout`'s arguments) and copy 0's trajectory (if recorded)."""
    recorder = TrajectoryRecorder(0)
    records = rollout(
        actor,
        task_config,
        episodes=episodes,
        mode=mode,
        seed=seed,
        task_factory=task_factory,
        observers=(recorder,) if record_trajectory else (),
    )
    return [r for r in records if r is not None], recorder.trajectory


def summarize(records: list[dict[str, float]], confidence: float = 0.95) -> dict[str, dict]:
    """Mean and confidence interval of every metric over episodes."""
    keys = sorted({k for r in records for k in r})
    return {k: mean_ci([r[k] for r in records if k in r], confidence) for k in keys}


def combine_replicas(
    replicas: list[tuple[str, list[dict[str, float]], dict[str, Any]]], confidence: float
) -> dict[str, Any]:
    """One variant's evaluation over its seed replicas (``(folder, records, trajectory)``).

    With several replicas each metric is the mean of the per-seed means, its interval over the
    seeds; trajectory and episodes are the first replica's, each replica's summary under
    ``"replicas"``.
    """
    _first, records, trajectory = replicas[0]
    entry: dict[str, Any] = {
        "metrics": summarize(records, confidence),
        "ci_over": "episodes",
        "n_seeds": len(replicas),
        "trajectory": trajectory,
        "episodes": records,
    }
    if len(replicas) > 1:
        per_seed = {name: summarize(recs, confidence) for name, recs, _ in replicas}
        keys = sorted({k for s in per_seed.values() for k in s})
        entry["metrics"] = {
            k: mean_ci([s[k]["mean"] for s in per_seed.values() if k in s], confidence)
            for k in keys
        }
        entry["ci_over"] = "seeds"
        entry["replicas"] = per_seed
    return entry


def merge_feedback(summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """Fused-belief diagnostics of several seed replicas: means; statuses and servers summed."""
    if len(summaries) == 1:
        return summaries[0]
    statuses: Counter[str] = Counter()
    for s in summaries:
        statuses.update(s.get("statuses") or {})
    conflicts = [s["mean_conflict"] for s in summaries if s.get("mean_conflict") is not None]
    total = sum(statuses.values())
    servers = [s["llm_servers"] for s in summaries if s.get("llm_servers")]
    extra: dict[str, Any] = {}
    if servers:
        from amuled_ma.servers.pool import merge_host_stats

        extra["llm_servers"] = merge_host_stats(servers)
    distills = [s["distill"] for s in summaries if s.get("distill")]
    if distills:
        extra["distill"] = merge_distill(distills)
    answered = sum(n for key, n in statuses.items() if key in FUSED_STATUSES)
    return {
        "feedback": summaries[0].get("feedback"),
        "replicas": len(summaries),
        "steps": sum(s.get("steps", 0) for s in summaries),
        "unique_states": float(np.mean([s.get("unique_states", 0) for s in summaries])),
        "mean_weight": _mean_per_agent(summaries, "mean_weight"),
        "mean_entropy_share": _mean_per_agent(summaries, "mean_entropy_share"),
        "mean_conflict": float(np.mean(conflicts)) if conflicts else None,
        "statuses": dict(statuses),
        "miss_rate": statuses.get("replay_miss", 0) / total if total else 0.0,
        "failure_rate": (total - answered) / total if total else 0.0,
        "agents": _sum_agents([s.get("agents") or {} for s in summaries]),
        "agents_per_state": _sum_agents([s.get("agents_per_state") or {} for s in summaries]),
        **extra,
    }


def _mean_per_agent(summaries: list[dict[str, Any]], key: str) -> dict[str, float]:
    """Per agent, the mean of ``summary[key][agent]`` over the replicas that have it."""
    agents = sorted({a for s in summaries for a in (s.get(key) or {})})
    return {
        a: float(np.mean([s[key][a] for s in summaries if a in (s.get(key) or {})])) for a in agents
    }


#: Counters of a distilled feedback's accounting that add up over seed replicas.
_DISTILL_SUMS = (
    "visited_states",
    "asked_states",
    "model_states",
    "cap",
    "requests_forwarded",
    "requests_sent",
    "model_answers",
    "miss_answers",
    "unasked_answers",
    "refits",
    "holdout_states",
)


def merge_distill(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """Several seed replicas' budget accounting: counts summed, held-out distances averaged."""
    if len(reports) == 1:
        return reports[0]
    out = {k: v for k, v in reports[0].items() if k not in _DISTILL_SUMS}
    for key in _DISTILL_SUMS:
        out[key] = sum(int(r.get(key) or 0) for r in reports)
    visited = out["visited_states"]
    out["asked_share"] = out["asked_states"] / visited if visited else 0.0
    fused = [r["holdout_tv_fused"] for r in reports if r.get("holdout_tv_fused") is not None]
    out["holdout_tv_fused"] = float(np.mean(fused)) if fused else None
    out["holdout_tv"] = _mean_per_agent(reports, "holdout_tv")
    out["replicas"] = len(reports)
    return out


def _sum_agents(reports: list[dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Per-agent status counts of several replicas, summed; rates recomputed."""
    out: dict[str, dict[str, Any]] = {}
    for report in reports:
        for agent, row in report.items():
            merged = out.setdefault(agent, {})
            for status, count in row.items():
                if status != "failure_rate":
                    merged[status] = merged.get(status, 0) + count
    for row in out.values():
        total = row.get("total", 0)
        row["failure_rate"] = row.get("failed", 0) / total if total else 0.0
    return out


def variant_dirs(run_dir: Path) -> list[Path]:
    """Folders of a run that hold a final checkpoint, in pipeline order."""
    order = {"base": 0, "shaped": 1}
    dirs = [p.parent for p in Path(run_dir).glob(f"*/{LAST}")]

    def key(path: Path) -> tuple:
        # natural order: finetune-amuled-kl2.5 before finetune-amuled-kl10
        parts = re.split(r"(\d+(?:\.\d+)?)", path.name)
        return (
            order.get(path.name, 2),
            [(0, float(p)) if i % 2 else (1, p) for i, p in enumerate(parts)],
        )

    return sorted(dirs, key=key)


def evaluate_run(
    run_dir: Path,
    *,
    scenario_name: str,
    task_config: TaskConfig,
    evaluation: EvaluationConfig,
    ppo: PPOConfig,
    episodes: int | None = None,
    modes: list[str] | None = None,
    variants: list[str] | None = None,
    task_factory: Callable[..., Any] | None = None,
    progress: bool = False,
    extra_dirs: list[Path] | None = None,
    records: Mapping[str, RunRecord] | None = None,
) -> Results:
    """Evaluate every trained variant of a run; write ``results.json`` and ``results.csv``.

    ``variants`` keeps only those names; ``extra_dirs`` are more variant folders (an ablation's
    base); ``records`` (by folder) names a folder's variant (seed replicas grouped under it) and
    what a fine-tune was trained on. Before any episode: CheckpointError without a trained
    variant, AmuledError for a refused ``feedback.json`` or results file.
    """
    run_dir = Path(run_dir)
    check_write_targets(run_dir / name for name in RESULTS_FILES)
    records = records or {}
    ev = evaluation
    episodes = ev.episodes if episodes is None else episodes
    modes = modes or list(ev.modes)
    dirs = variant_dirs(run_dir)

    def name_of(folder: Path) -> str:
        record = records.get(folder.name)
        return record.name if record is not None and record.name else folder.name

    if variants:
        dirs = [d for d in dirs if d.name in variants or name_of(d) in variants]
    extra = [Path(d) for d in extra_dirs or [] if (Path(d) / LAST).is_file()]
    dirs = [d for d in extra if d.name not in {x.name for x in dirs}] + dirs
    if not dirs:
        raise CheckpointError(
            f"no trained variant (*/{LAST}) in {run_dir}; train one with "
            f"'amuled train {scenario_name} --run-dir {run_dir}'"
        )
    results: dict[str, Any] = {
        "scenario": scenario_name,
        "task": task_config.name,
        "episodes": episodes,
        "confidence": ev.confidence,
        "seed": ev.seed,
        "variants": {},
    }
    groups: dict[str, list[Path]] = {}
    for vdir in dirs:
        groups.setdefault(name_of(vdir), []).append(vdir)
    feedbacks = {vdir: read_feedback(vdir) for vdir in dirs}
    jobs = [(name, vdir, m) for name, members in groups.items() for vdir in members for m in modes]
    runs: dict[tuple[str, str], list[tuple[str, list, dict]]] = {}
    with Progress("evaluate", len(jobs), bar=progress, unit="policy") as bar:
        for name, vdir, mode in jobs:
            actor = load_policy(vdir / LAST, ppo)
            records_, trajectory = run_episodes(
                actor,
                task_config,
                episodes=episodes,
                mode=mode,
                seed=ev.seed,
                task_factory=task_factory,
            )
            runs.setdefault((name, mode), []).append((vdir.name, records_, trajectory))
            bar.update(1)
    for (name, mode), replicas in runs.items():
        entry = results["variants"].setdefault(name, {})
        entry[mode] = combine_replicas(replicas, ev.confidence)
    for name, members in groups.items():
        summaries = [summary for d in members if (summary := feedbacks[d]) is not None]
        if summaries:
            results["variants"][name]["feedback"] = merge_feedback(summaries)
        record = records.get(members[0].name)
        panel = panel_entry(record) if record is not None else None
        if panel is not None:
            results["variants"][name]["panel"] = panel
    typed = Results.model_validate(results)
    write_results(run_dir, typed)
    return typed


def panel_entry(record: RunRecord) -> dict[str, Any] | None:
    """A fine-tune's feedback as ``results.json`` keeps it under ``"panel"``; None if none."""
    variant = record.variant
    if variant is None or not variant.finetuning:
        return None
    training = record.training or {}
    finetune = training.get("finetune") or {}
    feedback = training.get("feedback") or {}
    entry: dict[str, Any] = {
        "feedback": variant.feedback,
        "recipe": finetune.get("recipe", "equation"),
        "lambda_kl": finetune.get("lambda_kl"),
        "iterations": training.get("iterations"),
        "seed": training.get("seed"),
    }
    if feedback:
        entry.update(
            agents=list(feedback.get("clusters") or []),
            source=feedback.get("source"),
            model=feedback.get("model"),
            recording=feedback.get("recording"),
            fusion=feedback.get("fusion"),
            agent_sources=feedback.get("agents") or {},
            clusters_dirs=list(feedback.get("clusters_dirs") or []),
        )
    if feedback.get("distill"):
        entry["distill"] = feedback["distill"]
    if training.get("inputs"):
        entry["inputs"] = training["inputs"]
    if record.base_checkpoint:
        entry["base_checkpoint"] = record.base_checkpoint
    return entry


def metric_order(task: str, metrics: list[str]) -> list[str]:
    """Paper metrics first, then the rest alphabetically."""
    first = [m for m in PAPER_METRICS.get(task, []) if m in metrics]
    return first + sorted(m for m in metrics if m not in first)
