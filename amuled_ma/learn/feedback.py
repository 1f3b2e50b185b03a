"""Feedback for fine-tuning: a belief over actions for every environment copy, each step.

The fine-tuning reward is ``f(B)[a_t]``, the feedback's probability of the action the
agent took (paper, eq. "feedback"). A :class:`Feedback` answers a whole batch (all
environment copies at once) and memoises by observation, so a repeated state costs one
dictionary lookup; underneath, panel feedback goes through the belief store, so a state
seen in an earlier run costs no LLM call either.

Variants (``--feedback``):

- ``amuled``: the five moral clusters fused with ``bjs-dst`` (or the scenario's rule);
- ``human``: the rule-based human source (:func:`amuled_ma.tasks.human.human_belief`);
- ``cluster:<name>``: one moral cluster alone;
- ``moral``: the unprompted "behave as a moral agent" agent;
- ``agg:mean|max|vote``: the five clusters fused with another rule.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.errors import AmuledError, ScenarioError

#: Name of the unprompted moral agent in recordings and the cluster prompts.
MORAL_AGENT = "moral_agent"
#: Aggregation rules of the ``agg:`` variants.
AGGREGATIONS = ("mean", "max", "vote")


class Feedback(ABC):
    """A batched, memoised source of feedback beliefs."""

    #: Variant name (``amuled``, ``human``, ``cluster:care``, ...).
    name: str = "feedback"

    def __init__(self) -> None:
        # observation bytes -> (belief, diagnostics, the diagnostics prepared for _account)
        self._memo: dict[bytes, tuple[np.ndarray, dict[str, Any], tuple]] = {}
        self.steps = 0
        self.lookups = 0
        self.statuses: Counter[str] = Counter()
        self._weight_sum: dict[str, float] = {}
        self._conflict_sum = 0.0
        self._diag_count = 0

    @abstractmethod
    def _compute(self, obs: np.ndarray, task: Any, env_ids: Sequence[int]) -> list[tuple]:
        """Return ``(belief [A], diagnostics)`` for each new observation row."""

    def __call__(
        self, obs: torch.Tensor, task: Any, env_ids: Sequence[int] | None = None
    ) -> np.ndarray:
        """Return beliefs ``[N, A]`` for a batch of observations (one row per copy).

        Args:
            obs: Observations ``[N, obs_dim]`` (the states the actions were taken in).
            task: The batched task (for prompt variables or the human rule).
            env_ids: The copies the rows belong to (default: ``range(N)``).

        """
        array = obs.detach().cpu().numpy().astype(np.float32, copy=False)
        ids = list(range(len(array))) if env_ids is None else list(env_ids)
        keys = [row.tobytes() for row in array]
        memo = self._memo
        missing: dict[bytes, int] = {}
        for i, key in enumerate(keys):
            if key not in memo and key not in missing:
                missing[key] = i
        if missing:
            rows = list(missing.values())
            results = self._compute(array[rows], task, [ids[i] for i in rows])
            self.lookups += len(rows)
            for key, result in zip(missing, results, strict=True):
                diag = result[1]
                memo[key] = (np.asarray(result[0], dtype=np.float64), diag, _prepare(diag))
        entries = [memo[key] for key in keys]
        out = np.stack([entry[0] for entry in entries]) if entries else np.empty((0, 0))
        for entry in entries:
            self._account(entry[2])
        self.steps += len(array)
        return out

    def _account(self, prepared: tuple) -> None:
        """Add one row's diagnostics (as :func:`_prepare` returns them) to the totals."""
        statuses, weights, conflict = prepared
        for status in statuses:
            self.statuses[status] += 1
        if weights:
            weight_sum = self._weight_sum
            for name, value in weights:
                weight_sum[name] = weight_sum.get(name, 0.0) + value
            self._diag_count += 1
            self._conflict_sum += conflict

    def summary(self) -> dict[str, Any]:
        """Diagnostics so far: per-cluster mean weight, mean conflict, statuses, miss rate."""
        total = sum(self.statuses.values())
        n = max(1, self._diag_count)
        return {
            "feedback": self.name,
            "steps": self.steps,
            "unique_states": len(self._memo),
            "mean_weight": {k: v / n for k, v in self._weight_sum.items()},
            "mean_conflict": self._conflict_sum / n if self._diag_count else None,
            "statuses": dict(self.statuses),
            "miss_rate": (self.statuses.get("replay_miss", 0) / total) if total else 0.0,
        }

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the underlying source."""


def _prepare(diag: dict[str, Any]) -> tuple:
    """Return ``(statuses, ((cluster, weight), ...) or None, conflict)`` of a diagnostics dict.

    Done once per distinct state, so the per-row accounting of every step is a few
    additions, in the same order and with the same floats as reading the dict each time.
    """
    weights = diag.get("weights")
    pairs = tuple((name, float(value)) for name, value in weights.items()) if weights else None
    conflict = float(diag.get("conflict", 0.0)) if weights else 0.0
    return tuple(diag.get("statuses", ())), pairs, conflict


class CallableFeedback(Feedback):
    """Feedback from a plain function ``obs [N, D] -> beliefs [N, A]`` (tests, scripts)."""

    def __init__(self, fn: Callable[[np.ndarray], np.ndarray], name: str = "scripted") -> None:
        super().__init__()
        self.fn = fn
        self.name = name

    def _compute(self, obs: np.ndarray, task: Any, env_ids: Sequence[int]) -> list[tuple]:
        beliefs = np.asarray(self.fn(obs), dtype=np.float64)
        return [(b, {"statuses": ("ok",)}) for b in beliefs]


class HumanFeedback(Feedback):
    """The rule-based human source of the task (:mod:`amuled_ma.tasks.human`)."""

    name = "human"

    def __init__(self, task_name: str) -> None:
        super().__init__()
        self.task_name = task_name
        self._human_belief = importlib.import_module("amuled_ma.tasks.human").human_belief

    def _compute(self, obs: np.ndarray, task: Any, env_ids: Sequence[int]) -> list[tuple]:
        beliefs = np.asarray(self._human_belief(self.task_name, obs), dtype=np.float64)
        beliefs = beliefs.reshape(len(obs), -1)
        return [(b, {"statuses": ("ok",)}) for b in beliefs]


class PanelFeedback(Feedback):
    """Beliefs of a panel of moral-cluster agents, fused (:class:`MoralPanel`)."""

    def __init__(self, name: str, panel: Any, source: Any | None = None) -> None:
        super().__init__()
        self.name = name
        self.panel = panel
        self.source = source

    def _compute(self, obs: np.ndarray, task: Any, env_ids: Sequence[int]) -> list[tuple]:
        # a source that reads no messages (replay, rules) needs no prompt variables
        needs_prompts = bool(getattr(self.panel, "with_messages", True))
        prompt_vars = (
            task.prompt_variables(list(env_ids))
            if needs_prompts and hasattr(task, "prompt_variables")
            else None
        )
        out = self.panel.fused(obs, prompt_vars)
        fused = np.asarray(out.fused, dtype=np.float64).reshape(len(obs), -1)
        clusters = list(
            getattr(self.panel, "cluster_names", None) or getattr(self.panel, "clusters", [])
        )
        results = []
        weights = getattr(out, "weights", None)
        conflict = getattr(out, "conflict", None)
        statuses = getattr(out, "statuses", None)
        for i in range(len(obs)):
            diag: dict[str, Any] = {}
            if weights is not None:
                row = np.asarray(weights[i], dtype=np.float64).reshape(-1)
                names = clusters if len(clusters) == len(row) else [str(j) for j in range(len(row))]
                diag["weights"] = dict(zip(names, row.tolist(), strict=True))
            if conflict is not None:
                diag["conflict"] = float(np.asarray(conflict).reshape(-1)[i])
            if statuses is not None:
                row_status = statuses[i]
                diag["statuses"] = (
                    (row_status,) if isinstance(row_status, str) else tuple(row_status)
                )
            results.append((fused[i], diag))
        return results

    def close(self) -> None:
        """Close the belief source, if it has ``close``."""
        for obj in (self.panel, self.source):
            closer = getattr(obj, "close", None)
            if callable(closer):
                closer()


def parse_variant(variant: str) -> tuple[str, str | None]:
    """Split and check a feedback variant name.

    Args:
        variant: ``amuled``, ``human``, ``moral``, ``cluster:<name>`` or ``agg:<rule>``.

    Returns:
        ``(kind, argument)``.

    Raises:
        ScenarioError: The variant is not one of the above.

    """
    kind, _, arg = variant.partition(":")
    if kind in ("amuled", "human", "moral") and not arg:
        return kind, None
    if kind == "cluster" and arg:
        return kind, arg
    if kind == "agg" and arg in AGGREGATIONS:
        return kind, arg
    raise ScenarioError(
        f"unknown feedback variant {variant!r}; expected amuled, human, moral, cluster:<name> "
        f"or agg:{'|'.join(AGGREGATIONS)}"
    )


def make_source(scenario: Any, run_dir: Path | None = None) -> Any:
    """Create the scenario's belief source, wrapped in the belief store cache.

    Args:
        scenario: The :class:`~amuled_ma.scenario.Scenario`.
        run_dir: Run directory (a relative belief store path is resolved against it).

    Returns:
        A :class:`~amuled_ma.beliefs.cached.CachedSource` over the scenario's source.

    """
    from amuled_ma.beliefs import make_source as build
    from amuled_ma.beliefs.cached import CachedSource
    from amuled_ma.beliefs.store import BeliefStore

    fb = scenario.feedback
    options: dict[str, Any] = {}
    if fb.source == "replay":
        path = scenario.recording_path()
        if not path.exists():
            raise AmuledError(
                f"{scenario.path}: [feedback].recording {fb.recording!r} not found at {path} "
                "(set AMULED_RECORDINGS to the folder of the recordings)"
            )
        options.update(paths=path, miss_policy=fb.miss_policy)
    elif fb.source == "ollama":
        options.update(
            model=fb.model,
            host=fb.host or None,
            concurrency=fb.concurrency,
            timeout_s=fb.timeout_s,
            **_ollama_options(scenario),
        )
    source = build(fb.source, **options)
    # Preflight before anything is written: an unreachable server or a missing model
    # fails here, with the source's own message, and leaves the run directory untouched.
    check = getattr(source, "check", None)
    if callable(check):
        try:
            check()
        except BaseException:
            source.close()
            raise
    store_path = Path(fb.store)
    if not store_path.is_absolute():
        store_path = (run_dir or scenario.base_dir) / store_path
    store_path.parent.mkdir(parents=True, exist_ok=True)
    return CachedSource(source, BeliefStore(store_path))


def _ollama_options(scenario: Any) -> dict[str, Any]:
    """Return ``[feedback].ollama``, checked against :class:`OllamaSource`'s keywords."""
    import inspect

    from amuled_ma.beliefs.ollama import OllamaSource

    allowed = set(inspect.signature(OllamaSource).parameters) - {
        "model", "host", "concurrency", "timeout_s", "transport", "fallback"
    }  # fmt: skip
    unknown = sorted(set(scenario.feedback.ollama) - allowed)
    if unknown:
        raise ScenarioError(
            f"{scenario.path or scenario.name}: [feedback.ollama] unknown key(s) "
            f"{', '.join(unknown)}; expected some of {', '.join(sorted(allowed))}"
        )
    return dict(scenario.feedback.ollama)


def make_feedback(variant: str, scenario: Any, run_dir: Path | None = None) -> Feedback:
    """Build the feedback of one variant for a scenario.

    Args:
        variant: See :func:`parse_variant`.
        scenario: The scenario (task, clusters, fusion rule, source).
        run_dir: Run directory holding the belief store.

    Returns:
        The feedback, ready to be called every step.

    """
    kind, arg = parse_variant(variant)
    task_name = scenario.task.name
    if kind == "human":
        return HumanFeedback(task_name)
    clusters = list(scenario.feedback.clusters)
    rule = scenario.feedback.fusion
    if kind == "cluster":
        clusters, rule = [arg], "mean"
    elif kind == "moral":
        clusters, rule = [MORAL_AGENT], "mean"
    elif kind == "agg":
        rule = arg
    panel_mod = importlib.import_module("amuled_ma.deliberation.panel")
    source = make_source(scenario, run_dir)
    panel = panel_mod.MoralPanel(task_name, clusters, source, rule)
    return PanelFeedback(variant, panel, source)
