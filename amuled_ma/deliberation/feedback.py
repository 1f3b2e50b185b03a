"""Feedback for fine-tuning: a belief over actions for every environment copy, each step.

The fine-tuning reward is ``f(B)[a_t]``, the feedback's probability of the action the
agent took (paper, eq. "feedback"). A :class:`Feedback` answers a whole batch (all
environment copies at once) and memoises by observation, so a repeated state costs one
dictionary lookup; underneath, panel feedback goes through the belief store, so a state
seen in an earlier run costs no LLM call either.

Variants (``--feedback``):

- ``amuled``: the five moral clusters fused with ``bjs-dst`` (or the scenario's rule);
- ``human``: the authors' synthetic human, a demonstrator's action counts
  (:class:`DemonstratorFeedback`, :mod:`amuled_ma.tasks.demonstrators`);
- ``human:rules``: our rule-based human source (:func:`amuled_ma.tasks.human.human_belief`,
  through :class:`CallableFeedback`);
- ``cluster:<name>``: one moral cluster alone;
- ``moral``: the unprompted "behave as a moral agent" agent;
- ``agg:mean|max|vote``: the five clusters fused with another rule.

Every call counts, per agent (cluster), the status of the belief each rewarded step was
given: ``ok`` / ``repaired`` (an answer), ``abstained`` / ``timeout`` / ``error`` (a
failure: the fused reward used a uniform fallback for that agent) and ``replay_miss``;
with ``[feedback.distill]`` also ``distilled`` / ``distilled_miss`` (the distilled
model's answers, reported apart from the panel's) and ``unasked`` (a failure).
:meth:`Feedback.summary` holds them (``"agents"``, JSON-ready, for ``feedback.json`` and
``results.json``), :meth:`Feedback.agent_report` returns them on their own, and
:func:`summary_lines` prints them, so a server that always fails or answers NaN reads
"error 100.00%", not "miss rate 0.00%".
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.beliefs.types import MODEL_STATUSES, UNASKED
from amuled_ma.deliberation.state_key import freeze
from amuled_ma.errors import ClusterDefinitionError, ScenarioError
from amuled_ma.learn.variants import parse_feedback

#: Name of the unprompted moral agent in recordings and the cluster prompts.
MORAL_AGENT = "moral_agent"
#: Statuses reported per agent, in this order (any other status a source gives is added).
REPORTED_STATUSES = ("ok", "repaired", "abstained", "timeout", "error", "replay_miss")
#: Statuses that are answers (the panel's, and the distilled model's); every other one is a
#: failure (a fallback belief was used).
ANSWERED = frozenset({"ok", "repaired", *MODEL_STATUSES})
#: Statuses of beliefs a distilled model gave (or could not give): a memo entry holding one
#: is refreshed after the model's next refit (:meth:`Feedback._memo_generation`).
_VOLATILE = frozenset({*MODEL_STATUSES, UNASKED})
#: Statuses that are a feedback's documented answer, not an agent's failure: the authors'
#: fusion met total conflict (reward 0), a demonstrator never visited the state (reward 0).
DOCUMENTED_ZERO = frozenset({"total_conflict", "unseen"})
#: Distinct states an agent must have been asked before its abstention rate is judged.
MIN_STATES_JUDGED = 20
#: Calls between two abstention checks when no new state was asked.
CHECK_EVERY = 16


class Feedback(ABC):
    """A batched, memoised source of feedback beliefs."""

    #: Variant name (``amuled``, ``human``, ``cluster:care``, ...).
    name: str = "feedback"

    def __init__(self) -> None:
        # observation bytes -> (belief, diagnostics, the diagnostics prepared for _account)
        self._memo: dict[bytes, tuple[np.ndarray, dict[str, Any], tuple]] = {}
        self.steps = 0
        self.calls = 0
        self.lookups = 0
        self.statuses: Counter[str] = Counter()
        #: ``(agent, status)`` -> rewarded steps whose belief of that agent had that status.
        self.agent_statuses: Counter[tuple[str, str]] = Counter()
        #: The same, counted once per distinct state asked (not per step).
        self.agent_statuses_unique: Counter[tuple[str, str]] = Counter()
        self._weight_sum: dict[str, float] = {}
        self._conflict_sum = 0.0
        self._diag_count = 0
        # memo keys whose belief a distilled model gave; stale ones are answered again
        self._volatile: set[bytes] = set()
        self._stale: set[bytes] = set()
        self._generation: Any = None

    #: Largest share of rewarded steps one agent may leave unanswered (None: no limit),
    #: ``[feedback].max_abstention``; see :meth:`check_abstention`.
    max_abstention: float | None = None

    #: Whether a state is the observation *and* the task's prompt variables (a source that
    #: reads prompts: on FindMilk the number of crying babies is in the prompt, not in the
    #: observation); the in-process memo and the panel then key alike.
    keyed_by_prompt: bool = False

    def _memo_generation(self) -> Any:
        """A value that changes when memoised model answers must be asked again (None: never)."""
        return None

    def progress(self) -> dict[str, str]:
        """Short fields for the training progress bar (none by default)."""
        return {}

    @abstractmethod
    def _compute(
        self,
        obs: np.ndarray,
        task: Any,
        env_ids: Sequence[int],
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> list[tuple]:
        """Return ``(belief [A], diagnostics)`` for each new state (row of ``obs``)."""

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
        prompt_vars = None
        if self.keyed_by_prompt and hasattr(task, "prompt_variables"):
            prompt_vars = task.prompt_variables(ids)
            keys = [row.tobytes() + freeze(v) for row, v in zip(array, prompt_vars, strict=True)]
        else:
            keys = [row.tobytes() for row in array]
        memo = self._memo
        generation = self._memo_generation()
        if generation != self._generation:
            # a distilled model was refitted: its memoised answers are asked again
            self._generation = generation
            self._stale |= self._volatile
            self._volatile = set()
        stale = self._stale
        missing: dict[bytes, int] = {}
        for i, key in enumerate(keys):
            if (key not in memo or (stale and key in stale)) and key not in missing:
                missing[key] = i
        if missing:
            rows = list(missing.values())
            results = self._compute(
                array[rows],
                task,
                [ids[i] for i in rows],
                None if prompt_vars is None else [prompt_vars[i] for i in rows],
            )
            self.lookups += len(rows)
            for key, result in zip(missing, results, strict=True):
                diag = result[1]
                prepared = _prepare(diag, self.name)
                if key in stale:  # counted once per distinct state: drop the old answer's
                    stale.discard(key)
                    self.agent_statuses_unique.subtract(memo[key][2][0])
                    self.agent_statuses_unique = +self.agent_statuses_unique
                memo[key] = (np.asarray(result[0], dtype=np.float64), diag, prepared)
                self.agent_statuses_unique.update(prepared[0])
                if any(pair[1] in _VOLATILE for pair in prepared[0]):
                    self._volatile.add(key)
            generation = self._memo_generation()
            if generation != self._generation:
                # refitted during this call: its answers are the new model's, older ones stale
                self._generation = generation
                self._stale |= self._volatile.difference(missing)
                self._volatile.intersection_update(missing)
        entries = [memo[key] for key in keys]
        out = np.stack([entry[0] for entry in entries]) if entries else np.empty((0, 0))
        for entry in entries:
            self._account(entry[2])
        self.steps += len(array)
        # judged on new states, and every CHECK_EVERY calls (a policy that keeps visiting
        # states an agent cannot answer raises the share without asking anything new)
        if self.max_abstention is not None and (missing or self.calls % CHECK_EVERY == 0):
            self.check_abstention()
        self.calls += 1
        return out

    def _account(self, prepared: tuple) -> None:
        """Add one row's diagnostics (as :func:`_prepare` returns them) to the totals."""
        pairs, weights, conflict = prepared
        statuses, agent_statuses = self.statuses, self.agent_statuses
        for pair in pairs:
            agent_statuses[pair] += 1
            statuses[pair[1]] += 1
        if weights:
            weight_sum = self._weight_sum
            for name, value in weights:
                weight_sum[name] = weight_sum.get(name, 0.0) + value
            self._diag_count += 1
            self._conflict_sum += conflict

    def agent_report(self, *, per: str = "steps") -> dict[str, dict[str, Any]]:
        """Per agent: how many beliefs had each status, and the share that failed.

        Args:
            per: ``"steps"`` (each rewarded env step counts: the share of the reward
                built on fallbacks) or ``"states"`` (each distinct state asked counts once).

        Returns:
            ``{agent: {"ok": n, "repaired": n, "abstained": n, "timeout": n, "error": n,
            "replay_miss": n, (any other status), "total": n, "failed": n,
            "failure_rate": failed / total}}``, agents in the order first seen. ``failed``
            counts every status but the answers (:data:`ANSWERED`: ``ok``, ``repaired``
            and the distilled model's ``distilled``, ``distilled_miss``); a future
            stopping threshold can compare ``failure_rate`` with a limit.

        Raises:
            ValueError: ``per`` is neither ``"steps"`` nor ``"states"``.

        """
        if per not in ("steps", "states"):
            raise ValueError(f"per must be 'steps' or 'states', got {per!r}")
        counts = self.agent_statuses if per == "steps" else self.agent_statuses_unique
        report: dict[str, dict[str, Any]] = {}
        for (agent, status), n in counts.items():
            row = report.setdefault(agent, dict.fromkeys(REPORTED_STATUSES, 0))
            row[status] = row.get(status, 0) + n
        for row in report.values():
            total = sum(row.values())
            failed = total - sum(n for status, n in row.items() if status in ANSWERED)
            row.update(total=total, failed=failed, failure_rate=failed / total if total else 0.0)
        return report

    def agent_source(self, agent: str) -> str:
        """A short description of where ``agent``'s beliefs come from (for messages)."""
        return self.name

    def check_abstention(self) -> None:
        """Stop when an agent left too much of the reward without its answer.

        The share is over rewarded steps (how much of the feedback the agent's failures
        touched), judged once the agent was asked :data:`MIN_STATES_JUDGED` distinct
        states: a few rarely visited states the agent could not answer do not stop a run,
        an agent that fails on the states the policy keeps visiting does.

        Raises:
            AbstentionError: An agent failed to answer (abstained, timeout, error, replay
                miss) on more than :attr:`max_abstention` of the rewarded steps; the
                message names the agent, its source, the counts and the fix.

        """
        from amuled_ma.errors import AbstentionError

        limit = self.max_abstention
        if limit is None:
            return
        states = self.agent_report(per="states")
        for agent, row in self.agent_report(per="steps").items():
            if states.get(agent, {}).get("total", 0) < MIN_STATES_JUDGED:
                continue
            total = row["total"]
            failures = {
                status: n
                for status, n in row.items()
                if status not in ANSWERED
                and status not in DOCUMENTED_ZERO
                and status not in ("total", "failed", "failure_rate")
                and n
            }
            failed = sum(failures.values())
            if failed <= limit * total:
                continue
            parts = ", ".join(f"{status} {n:,}" for status, n in failures.items())
            raise AbstentionError(
                f"agent {agent!r} (source: {self.agent_source(agent)}) left {failed:,} of "
                f"{total:,} rewarded steps unanswered ({parts}; {states[agent]['total']:,} "
                f"distinct states asked): {failed / total:.0%}, above "
                f"[feedback].max_abstention = {limit:g}; feedback that is mostly missing is "
                "noise. Check that the recording holds this agent (a user cluster needs a "
                "live source, see docs/clusters.md), that the server answers ('amuled ollama "
                "status') and that the model exists; or allow more with --set "
                "feedback.max_abstention=..."
            )

    def failure_rate(self) -> float:
        """Share of all agents' beliefs over rewarded steps that were not answers (0..1)."""
        total = sum(self.statuses.values())
        answered = sum(n for status, n in self.statuses.items() if status in ANSWERED)
        return (total - answered) / total if total else 0.0

    def summary(self) -> dict[str, Any]:
        """Diagnostics so far, JSON-ready (``feedback.json``, ``results.json``).

        Returns:
            ``feedback`` (variant), ``steps``, ``unique_states``, ``mean_weight`` and
            ``mean_conflict`` (fusion), ``statuses`` (all agents, per step),
            ``miss_rate`` (replay misses / beliefs), ``failure_rate`` (beliefs that were
            not answers / beliefs), ``agents`` (:meth:`agent_report` per step),
            ``agents_per_state`` (per distinct state) and, for a distilled feedback,
            ``distill`` (:meth:`distill_report`: the budget's accounting).

        """
        total = sum(self.statuses.values())
        n = max(1, self._diag_count)
        out = {
            "feedback": self.name,
            "steps": self.steps,
            "unique_states": len(self._memo),
            "mean_weight": {k: v / n for k, v in self._weight_sum.items()},
            "mean_conflict": self._conflict_sum / n if self._diag_count else None,
            "statuses": dict(self.statuses),
            "miss_rate": (self.statuses.get("replay_miss", 0) / total) if total else 0.0,
            "failure_rate": self.failure_rate(),
            "agents": self.agent_report(per="steps"),
            "agents_per_state": self.agent_report(per="states"),
        }
        distill = self.distill_report()
        if distill:
            out["distill"] = distill
        return out

    def distill_report(self) -> dict[str, Any] | None:
        """The budget's accounting of a distilled feedback (None: not distilled)."""
        return None

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the underlying source."""


def _prepare(diag: dict[str, Any], default_agent: str = "feedback") -> tuple:
    """Return ``(((agent, status), ...), ((cluster, weight), ...) or None, conflict)``.

    The agents are ``diag["agents"]`` (one name per status), else the weights' names when
    they match the statuses one to one, else ``default_agent`` (the variant's name).
    Done once per distinct state, so the per-row accounting of every step is a few
    additions, in the same order and with the same floats as reading the dict each time.
    """
    weights = diag.get("weights")
    pairs = tuple((name, float(value)) for name, value in weights.items()) if weights else None
    conflict = float(diag.get("conflict", 0.0)) if weights else 0.0
    statuses = tuple(str(s) for s in diag.get("statuses", ()))
    agents = tuple(diag.get("agents") or (weights or {}))
    if len(agents) != len(statuses):
        agents = (default_agent,) * len(statuses)
    return tuple(zip(agents, statuses, strict=True)), pairs, conflict


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """Format a :meth:`Feedback.summary` for people: one headline, one line per agent.

    Works on summaries written before per-agent counts existed (headline only).

    Args:
        summary: The dict of :meth:`Feedback.summary` (or a ``feedback.json``).

    Returns:
        Lines without trailing newlines, e.g.::

            beliefs not answered: 50.00% of 800 (abstained 0, timeout 0, error 400, ...)
              care: ok 400, repaired 0, abstained 0, timeout 0, error 0, replay_miss 0
              virtue: ok 0, repaired 0, abstained 0, timeout 0, error 400 (100.00%), ...

    """
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
        agent_total = row.get("total") or 0
        cells = []
        for status, n in row.items():
            if status in ("total", "failed", "failure_rate"):
                continue
            share = f" ({100 * n / agent_total:.2f}%)" if n and agent_total else ""
            cells.append(f"{status} {n:,}{share if status not in ANSWERED else ''}")
        lines.append(f"  {agent}: {', '.join(cells)}")
    servers = summary.get("llm_servers") or {}
    if servers:
        from amuled_ma.beliefs.host_pool import host_lines

        lines.append(f"LLM servers ({len(servers)}):")
        lines += [f"  {line}" for line in host_lines(servers)]
    return lines


def distill_line(report: Mapping[str, Any]) -> str:
    """One line of a distilled feedback's accounting (``Feedback.summary()["distill"]``).

    E.g. ``feedback budget 10%: asked 13 of 131 distinct states (9.9%), the model
    answered 118; 65 requests sent; 4 refits; held-out TV to the panel 0.123 (fused,
    4 states)``.
    """
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


class CallableFeedback(Feedback):
    """Feedback from a plain function ``obs [N, D] -> beliefs [N, A]`` (tests, scripts)."""

    def __init__(self, fn: Callable[[np.ndarray], np.ndarray], name: str = "scripted") -> None:
        super().__init__()
        self.fn = fn
        self.name = name

    def _compute(
        self,
        obs: np.ndarray,
        task: Any,
        env_ids: Sequence[int],
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> list[tuple]:
        beliefs = np.asarray(self.fn(obs), dtype=np.float64)
        return [(b, {"statuses": ("ok",)}) for b in beliefs]


class DemonstratorFeedback(Feedback):
    """The authors' synthetic human (Wu & Lin 2018 style): a demonstrator's action counts.

    A simulated demonstrator played the task and every (observation, action) it took was
    counted (:mod:`amuled_ma.tasks.demonstrators`); a state's belief is
    ``p(a) ∝ 0.6^c_a 0.4^(n - c_a)``. A state the demonstrator never visited rewards 0
    (the authors' ``finetune_moral_human.py``), counted as ``unseen``.

    Args:
        task_name: The task.
        seed: Seed of the demonstrator's episodes.
        cache_dir: Folder caching the counts (the run folder).

    """

    name = "human"
    #: the one "agent" of this feedback in the per-agent report
    agent = "demonstrator"

    def __init__(self, task_name: str, *, seed: int, cache_dir: Path | None = None) -> None:
        super().__init__()
        from amuled_ma.tasks.demonstrators import demonstrator_belief

        self.table = demonstrator_belief(task_name, seed=seed, cache_dir=cache_dir)

    def _compute(
        self,
        obs: np.ndarray,
        task: Any,
        env_ids: Sequence[int],
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> list[tuple]:
        beliefs, seen = self.table.lookup(torch.as_tensor(obs))
        beliefs = np.asarray(beliefs, dtype=np.float64)
        return [
            (row, {"statuses": ("ok" if known else "unseen",), "agents": (self.agent,)})
            for row, known in zip(beliefs, np.asarray(seen).tolist(), strict=True)
        ]


class PanelFeedback(Feedback):
    """Beliefs of a panel of moral-cluster agents, fused (:class:`MoralPanel`)."""

    def __init__(
        self, name: str, panel: Any, source: Any | None = None, *, miss_zero: bool = False
    ) -> None:
        super().__init__()
        self.name = name
        self.panel = panel
        self.source = source
        #: a state every agent missed in the recording rewards 0 (the authors' scripts)
        self.miss_zero = miss_zero
        # a source that reads no messages (replay, rules) needs no prompt variables
        self.keyed_by_prompt = bool(getattr(panel, "with_messages", True))
        self._distilled_of: Any = object()
        self._distilled: Any = None

    @property
    def distilled(self) -> Any:
        """The :class:`~amuled_ma.distill.DistilledSource` of the panel, if it has one."""
        source = self.source
        if self._distilled_of is not source:  # looked up once per source, not every step
            from amuled_ma.distill import DistilledSource

            self._distilled_of = source
            self._distilled = source if isinstance(source, DistilledSource) else None
        return self._distilled

    def _memo_generation(self) -> Any:
        """The distilled source's number of refits (None without one)."""
        distilled = self.distilled
        return None if distilled is None else distilled.generation

    def distill_report(self) -> dict[str, Any] | None:
        """The distilled source's accounting (None when the panel answers every state)."""
        distilled = self.distilled
        return None if distilled is None else distilled.report()

    def progress(self) -> dict[str, str]:
        """``asked``: distinct states asked / visited, with a distilled source."""
        distilled = self.distilled
        if distilled is None:
            return {}
        return {"asked": f"{distilled.ledger.asked_count}/{distilled.ledger.visited_count}"}

    def _compute(
        self,
        obs: np.ndarray,
        task: Any,
        env_ids: Sequence[int],
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> list[tuple]:
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
                if len(clusters) == len(diag["statuses"]):
                    diag["agents"] = tuple(clusters)
            if self.miss_zero and _all_missed(diag.get("statuses", ())):
                results.append((np.zeros_like(fused[i]), diag))
                continue
            results.append((fused[i], diag))
        return results

    def summary(self) -> dict[str, Any]:
        """As :meth:`Feedback.summary`, plus the belief store's figures and the servers'.

        ``store`` is :func:`store_stats`: beliefs wanted, found in memory or in the store,
        and asked of the source.

        ``llm_servers`` is ``{host: figures}`` (:func:`llm_server_stats`): requests sent,
        answered and failed (by kind), retried from, latencies, per server.
        """
        out = super().summary()
        servers = llm_server_stats(self.source)
        if servers:
            out["llm_servers"] = servers
        if self.source is not None:
            out["store"] = store_stats(self.source)
        return out

    def agent_source(self, agent: str) -> str:
        """The source answering ``agent``: its kind and model or recording."""
        source = self.source
        per_agent = getattr(source, "source_for", None)
        if callable(per_agent):
            source = per_agent(agent)
        return describe_identity(source.identity()) if source is not None else self.name

    def close(self) -> None:
        """Close the belief source, if it has ``close``."""
        for obj in (self.panel, self.source):
            closer = getattr(obj, "close", None)
            if callable(closer):
                closer()


def nested_sources(source: Any) -> list[Any]:
    """A belief source and every source inside it, each once.

    Walks a :class:`~amuled_ma.beliefs.cached.CachedSource` (``.source``), a
    :class:`~amuled_ma.beliefs.routing.RoutedSource` (``.members``), fallbacks and defaults.
    """
    found: list[Any] = []
    seen: set[int] = set()

    def walk(obj: Any) -> None:
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


def llm_server_stats(source: Any) -> dict[str, dict[str, Any]]:
    """Each LLM server's figures over a belief source and the sources inside it.

    Adds up every ``server_stats()`` found (:class:`~amuled_ma.beliefs.ollama.OllamaSource`)
    among :func:`nested_sources` with :func:`~amuled_ma.beliefs.host_pool.merge_host_stats`.

    Args:
        source: The belief source (``None``: no figures).

    Returns:
        ``{host: figures}``; empty without an LLM server.

    """
    found = [
        obj.server_stats()
        for obj in nested_sources(source)
        if callable(getattr(obj, "server_stats", None))
    ]
    if not found:
        return {}
    from amuled_ma.beliefs.host_pool import merge_host_stats

    return merge_host_stats(found)


def store_stats(source: Any) -> dict[str, int]:
    """The belief store's figures over a source: requests, hits, and those asked.

    Adds up the :class:`~amuled_ma.beliefs.cached.CacheStats` of every cached source among
    :func:`nested_sources`: ``requests`` (beliefs wanted), ``unique`` (distinct ones per
    batch), ``memory_hits``, ``store_hits`` and ``asked`` (sent to the source behind the
    store: for an LLM, the requests it was sent).
    """
    from amuled_ma.beliefs.cached import CacheStats

    total = {"requests": 0, "unique": 0, "memory_hits": 0, "store_hits": 0, "asked": 0}
    for obj in nested_sources(source):
        stats = getattr(obj, "stats", None)
        if isinstance(stats, CacheStats):
            total["requests"] += stats.requests
            total["unique"] += stats.unique
            total["memory_hits"] += stats.memory_hits
            total["store_hits"] += stats.store_hits
            total["asked"] += stats.misses
    return total


def describe_identity(identity: Mapping[str, Any]) -> str:
    """``replay (findmilk-gpt-4o-mini.json)``, ``ollama (llama3.1:8b)``: a source in words."""
    kind = str(identity.get("source", "source"))
    files = [r.get("file") for r in identity.get("recordings") or () if isinstance(r, dict)]
    detail = ", ".join(str(f) for f in files if f) or identity.get("model") or ""
    return f"{kind} ({detail})" if detail else kind


def _all_missed(statuses: Sequence[str]) -> bool:
    return bool(statuses) and all(status == "replay_miss" for status in statuses)


class FusedReplayFeedback(Feedback):
    """The AMULED feedback replayed from a recording that keeps only the fused belief.

    The authors' Driving cache of gpt-4o-mini stored, per state, only the fused belief
    their AMULED agent was trained on (``fused_by_reference``); the five clusters'
    beliefs are lost, so this feedback *is* that fused belief, not a fusion of ours. A
    state missing from the recording follows ``miss_policy`` (``zero``: reward 0, as the
    authors' scripts; ``uniform``; ``error``), counted as ``replay_miss``; a recorded
    all-zero belief (their fusion's total conflict) rewards 0 and is counted as
    ``total_conflict``.

    Args:
        recording: The fused-only :class:`~amuled_ma.beliefs.replay.Recording`.
        miss_policy: ``zero``, ``uniform`` or ``error``.

    """

    name = "amuled"
    #: the one "agent" of this feedback in the per-agent report
    agent = "fused (recorded)"

    def __init__(self, recording: Any, miss_policy: str) -> None:
        super().__init__()
        if miss_policy not in ("zero", "uniform", "error"):
            raise ScenarioError(
                f"[feedback].miss_policy = {miss_policy!r} cannot serve the fused-only "
                f"recording {recording.path}: use zero, uniform or error"
            )
        self.recording = recording
        self.miss_policy = miss_policy

    def agent_source(self, agent: str) -> str:
        """The fused-only recording."""
        return f"replay ({self.recording.path.name}, fused beliefs only)"

    def _compute(
        self,
        obs: np.ndarray,
        task: Any,
        env_ids: Sequence[int],
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> list[tuple]:
        from amuled_ma.errors import ReplayMiss

        n = len(self.recording.actions)
        results = []
        for row in obs:
            fused = self.recording.fused(row)
            status = "ok"
            if fused is None:
                if self.miss_policy == "error":
                    raise ReplayMiss(
                        f"{self.recording.path}: no fused belief for obs {row.tolist()} "
                        "([feedback].miss_policy = 'error')"
                    )
                fused = np.zeros(n) if self.miss_policy == "zero" else np.full(n, 1.0 / n)
                status = "replay_miss"
            elif not fused.any():
                status = "total_conflict"
            else:
                fused = fused / fused.sum()
            results.append((fused, {"statuses": (status,), "agents": (self.agent,)}))
        return results


def make_source(scenario: Any, run_dir: Path | None = None, *, agents: Any = None) -> Any:
    """Create the scenario's belief source(s), wrapped in the belief store cache.

    Without a ``[feedback.agents.<name>]`` table for any of ``agents``: the source of
    ``[feedback].source`` behind the store, as always. With some: a
    :class:`~amuled_ma.beliefs.routing.RoutedSource` sending each agent's requests to its
    own source, each distinct source behind the one store in its own
    :class:`~amuled_ma.beliefs.cached.CachedSource` (so every store key holds the identity
    of the source that answered), agents without a table on ``[feedback].source``.

    Preflight, before anything is written: every source is built (a recording read, a
    policy file loaded, a plug-in resolved) and checked (an Ollama server and model
    reachable); a problem fails here, naming the agent's table, the source and the fix,
    and leaves the run directory untouched.

    Args:
        scenario: The :class:`~amuled_ma.scenario.Scenario`.
        run_dir: Run directory (a relative belief store path is resolved against it).
        agents: The panel's agents (names or cluster objects); default
            ``[feedback].clusters`` and ``moral_agent``.

    Returns:
        A ``CachedSource`` over the scenario's source, or a ``RoutedSource`` of them.

    Raises:
        AmuledError: A source cannot be built or checked (see
            :func:`amuled_ma.beliefs.routing.build_members`).

    """
    from amuled_ma.beliefs import make_source as build
    from amuled_ma.beliefs.cached import CachedSource
    from amuled_ma.beliefs.routing import (
        RoutedSource,
        build_members,
        default_spec,
        match_agents,
        panel_specs,
    )
    from amuled_ma.beliefs.store import BeliefStore
    from amuled_ma.beliefs.store_service import open_store

    fb = scenario.feedback
    if agents is None:
        agents = [*fb.clusters, *([MORAL_AGENT] if MORAL_AGENT not in fb.clusters else [])]
    agents = list(agents)

    def store() -> BeliefStore:
        return open_store(store_path(scenario, run_dir))

    if not match_agents(list(fb.agents), agents):
        spec = default_spec(scenario, _ollama_options)
        source = build(spec.kind, **spec.options)
        # Preflight before anything is written: an unreachable server or a missing model
        # fails here, with the source's own message, and leaves the run directory untouched.
        check = getattr(source, "check", None)
        if callable(check):
            try:
                check()
            except BaseException:
                source.close()
                raise
        return CachedSource(source, store())

    specs, default, problems = panel_specs(scenario, agents, _ollama_options)
    routes, default_source = build_members(
        specs, default, where=str(scenario.path or scenario.name), build=build, problems=problems
    )
    shared = store()
    cached: dict[int, CachedSource] = {}
    kinds = {id(routes[a]): specs[a] for a in routes}

    def wrap(source: Any) -> CachedSource:
        if id(source) not in cached:
            spec = kinds.get(id(source))
            identity = None
            if spec is not None and spec.kind == "entry-point":
                # a plug-in's own identity may be the bare default ({"source": name}):
                # the entry point and its options keep two plug-ins' answers apart
                identity = {"source": "entry-point", **spec.options, "plugin": source.identity()}
            cached[id(source)] = CachedSource(source, shared, identity=identity)
        return cached[id(source)]

    return RoutedSource(
        {agent: wrap(source) for agent, source in routes.items()},
        wrap(default_source) if default_source is not None else None,
    )


def store_path(scenario: Any, run_dir: Path | None = None) -> Path:
    """The belief store file of a scenario's run.

    ``[feedback].store``; a relative path is resolved against the run folder (or the
    scenario's folder without one).
    """
    path = Path(scenario.feedback.store)
    return path if path.is_absolute() else (run_dir or scenario.base_dir) / path


def _ollama_options(scenario: Any) -> dict[str, Any]:
    """Return ``[feedback].ollama``, checked against :class:`OllamaSource`'s keywords."""
    from amuled_ma.beliefs.routing import scenario_ollama_options

    return scenario_ollama_options(scenario)


def make_feedback(
    variant: str,
    scenario: Any,
    run_dir: Path | None = None,
    *,
    state_dir: Path | None = None,
    resume: bool = False,
    seed: int | None = None,
) -> Feedback:
    """Build the feedback of one variant for a scenario.

    Args:
        variant: The feedback (see :func:`~amuled_ma.learn.variants.parse_feedback`).
        scenario: The scenario (task, clusters, fusion rule, source).
        run_dir: Run directory holding the belief store.
        state_dir: The fine-tune's folder. With ``[feedback.distill].enabled``, panel
            feedback is distilled there (:class:`~amuled_ma.distill.DistilledSource`, its
            budget kept in the folder's state files); without a folder the panel answers
            every state (the viewer, ``amuled explain``).
        resume: Continue the budget kept in ``state_dir`` (a resumed fine-tune);
            otherwise it starts afresh.
        seed: The job's training seed, the distilled model's seed unless
            ``[feedback.distill].seed`` is set (default: ``[task].seed``).

    Returns:
        The feedback, ready to be called every step.

    Raises:
        ScenarioError: ``[feedback.distill]`` is enabled on a recording that keeps only
            fused beliefs (see :func:`check_distillable`).

    """
    kind, arg = parse_feedback(variant)
    task_name = scenario.task.name
    if kind == "human" and arg == "rules":
        from amuled_ma.tasks.human import human_belief

        return CallableFeedback(
            lambda obs: np.asarray(human_belief(task_name, obs)).reshape(len(obs), -1),
            name="human:rules",
        )
    if kind == "human":
        return DemonstratorFeedback(task_name, seed=scenario.task.seed, cache_dir=run_dir)
    fused_only = _fused_only_recording(scenario)
    if fused_only is not None and scenario.feedback.agents:
        from amuled_ma.beliefs.routing import match_agents

        # agents with their own source are a panel of their own: no fused-only shortcut
        # (a replay member on the fused-only recording is refused by the preflight)
        agents, _ = panel_of(variant, scenario)
        if match_agents(list(scenario.feedback.agents), agents):
            fused_only = None
    if fused_only is not None:
        check_distillable(scenario, fused_only)
        if kind != "amuled" or scenario.feedback.fusion != "bjs-dst":
            raise ScenarioError(
                f"{fused_only.path} keeps only the authors' fused belief per state "
                f"('beliefs': null), so it can serve the amuled variant (bjs-dst) only, not "
                f"{variant!r} with fusion {scenario.feedback.fusion!r}; use a recording with "
                'per-cluster beliefs, e.g. recording = "driving-llama-3_1-70b"'
            )
        fused = FusedReplayFeedback(fused_only, scenario.feedback.miss_policy)
        fused.max_abstention = scenario.feedback.max_abstention
        return fused
    from amuled_ma.clusters import build_messages
    from amuled_ma.deliberation.panel import MoralPanel

    registry = cluster_registry(scenario)
    clusters, rule = panel_of(variant, scenario, registry)
    scenario = with_cluster_sources(scenario, clusters)
    source = make_source(scenario, run_dir, agents=clusters)
    distill = scenario.feedback.distill
    if distill.enabled and state_dir is not None:
        from amuled_ma.distill import DistilledSource

        try:
            source = DistilledSource.from_config(
                source,
                distill,
                seed=scenario.task.seed if seed is None else seed,
                fusion_rule=rule,
                state_dir=state_dir,
                resume=resume,
            )
        except BaseException:
            source.close()
            raise
    panel = MoralPanel(
        task_name,
        clusters,
        source,
        rule,
        build_messages=functools.partial(build_messages, registry=registry),
    )
    replays = scenario.feedback.source == "replay" or any(
        table.get("source") == "replay" for table in scenario.feedback.agents.values()
    )
    miss_zero = replays and scenario.feedback.miss_policy == "zero"
    feedback = PanelFeedback(variant, panel, source, miss_zero=miss_zero)
    feedback.max_abstention = scenario.feedback.max_abstention
    return feedback


def check_distillable(scenario: Any, fused_only: Any | None = None) -> None:
    """Refuse ``[feedback.distill]`` on a recording that keeps only the fused belief.

    The distilled model learns each panel member's belief; the authors' Driving
    gpt-4o-mini cache kept only the fused one per state.

    Args:
        scenario: The scenario.
        fused_only: Its fused-only recording, if already read (else looked up).

    Raises:
        ScenarioError: Distillation is enabled and the replayed recording is fused-only;
            the message names the file and the fix.

    """
    if not scenario.feedback.distill.enabled:
        return
    if fused_only is None:
        fused_only = _fused_only_recording(scenario)
    if fused_only is None:
        return
    other = scenario.feedback.cluster_recording or "driving-llama-3_1-70b"
    raise ScenarioError(
        f"{fused_only.path} keeps only the authors' fused belief per state ('beliefs': null), "
        "so [feedback.distill] cannot learn each panel member's belief from it; replay a "
        f'recording with per-cluster beliefs (--set feedback.recording="{other}") or '
        "turn distillation off (--set feedback.distill.enabled=false)"
    )


def cluster_registry(scenario: Any) -> Any:
    """The shipped clusters plus the scenario's ``[feedback].clusters_dirs`` (later win).

    Raises:
        ClusterDefinitionError: A folder is missing or a file is malformed or collides.

    """
    dirs = [scenario.resolve(d) for d in scenario.feedback.clusters_dirs]
    return _registry_cached(tuple(str(d) for d in dirs))


@functools.lru_cache(maxsize=8)
def _registry_cached(dirs: tuple[str, ...]) -> Any:
    from amuled_ma.clusters import ClusterRegistry

    return ClusterRegistry.load(list(dirs))


def panel_of(variant: str, scenario: Any, registry: Any | None = None) -> tuple[list, str]:
    """The panel of a feedback variant: its agents (cluster objects) and fusion rule.

    Raises:
        ClusterDefinitionError: A named cluster is in no loaded cluster file; the message
            lists the known ones (a user cluster needs ``--clusters-dir``).

    """
    kind, arg = parse_feedback(variant)
    registry = registry or cluster_registry(scenario)
    names, rule = list(scenario.feedback.clusters), scenario.feedback.fusion
    if kind == "cluster":
        names, rule = [arg], "mean"
    elif kind == "moral":
        names, rule = [MORAL_AGENT], "mean"
    elif kind == "agg":
        rule = arg
    clusters = []
    for name in names:
        if name not in registry:
            dirs = ", ".join(scenario.feedback.clusters_dirs) or "none"
            raise ClusterDefinitionError(
                f"feedback {variant!r}: no moral cluster {name!r} in the shipped cluster files "
                f"or the user folders ({dirs}); known: {', '.join(registry.names())}; put its "
                "TOML file in a folder and pass --clusters-dir FOLDER (docs/clusters.md)"
            )
        clusters.append(registry.get(name))
    return clusters, rule


def with_cluster_sources(scenario: Any, clusters: Sequence[Any]) -> Any:
    """The scenario with each cluster file's default ``[source]`` as an agent table.

    A cluster file may name where its beliefs come from (``[source]``); the scenario's own
    ``[feedback.agents.<name>]`` table for that agent wins.
    """
    from amuled_ma.beliefs.routing import match_agents

    tables = dict(scenario.feedback.agents)
    named = match_agents(list(tables), clusters)
    defaults = {
        c.name: dict(c.source)
        for c in clusters
        if getattr(c, "source", None) and c.name not in named
    }
    if not defaults:
        return scenario
    return scenario.replace("feedback", agents={**defaults, **tables})


def _fused_only_recording(scenario: Any) -> Any | None:
    """The scenario's replayed recording when it holds only fused beliefs, else None."""
    if scenario.feedback.source != "replay":
        return None
    path = scenario.recording_path(required=True)
    recording = _recording_cached(str(path), path.stat().st_mtime_ns)
    return recording if recording.fused_only else None


@functools.lru_cache(maxsize=4)
def _recording_cached(path: str, mtime_ns: int) -> Any:
    from amuled_ma.beliefs.replay import Recording

    return Recording(path)
