"""Feedback for fine-tuning: a belief over actions for every environment copy, each step.

The fine-tuning reward is ``f(B)[a_t]``. A `Feedback` answers a whole batch, memoises by
observation and counts, per agent, the status of each rewarded step's belief.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from amuled_ma.beliefs.types import MODEL_STATUSES, UNASKED
from amuled_ma.deliberation.state_key import freeze
from amuled_ma.errors import AbstentionError

if TYPE_CHECKING:
    from amuled_ma.deliberation.plan import PanelPlan

#: The prompt variables of each new state, or None (a feedback keyed by observation alone).
PromptVars = Sequence[Mapping[str, Any]] | None
#: Statuses reported per agent, in this order (any other status a source gives is added).
REPORTED_STATUSES = ("ok", "repaired", "abstained", "timeout", "error", "replay_miss")
#: Statuses that are answers (the panel's, and the distilled model's); every other one is a
#: failure (a fallback belief was used).
ANSWERED = frozenset({"ok", "repaired", *MODEL_STATUSES})
#: Statuses of beliefs a distilled model gave (or could not give): a memo entry holding one
#: is refreshed after the model's next refit (`Feedback._memo_generation`).
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
    #: The panel plan it was built from (`build_feedback`
    #: sets it); None for a feedback built directly.
    plan: PanelPlan | None = None

    def __init__(self) -> None:
        # state key -> (belief, its diagnostics as `_prepare` returns them)
        self._memo: dict[bytes, tuple[np.ndarray, tuple]] = {}
        self.steps = 0
        self.calls = 0
        self.statuses: Counter[str] = Counter()
        #: ``(agent, status)`` -> rewarded steps whose belief of that agent had that status.
        self.agent_statuses: Counter[tuple[str, str]] = Counter()
        #: The same, counted once per distinct state asked (not per step).
        self.agent_statuses_unique: Counter[tuple[str, str]] = Counter()
        self._weight_sum: dict[str, float] = {}
        #: agent -> [sum of its beliefs' entropy shares, rewarded steps it answered]
        self._entropy_sum: dict[str, list[float]] = {}
        self._conflict_sum = 0.0
        self._diag_count = 0
        # memo keys whose belief a distilled model gave; stale ones are answered again
        self._volatile: set[bytes] = set()
        self._stale: set[bytes] = set()
        self._generation: Any = None

    #: Largest share of rewarded steps one agent may leave unanswered (None: no limit),
    #: ``[feedback].max_abstention``; see `check_abstention`.
    max_abstention: float | None = None

    #: Whether a state is the observation *and* the task's prompt variables (a source that
    #: reads prompts: on FindMilk the number of crying babies is in the prompt, not in the
    #: observation); the in-process memo and the panel then key alike.
    keyed_by_prompt: bool = False

    def _memo_generation(self) -> Any:
        """A value that changes when memoised model answers must be asked again (None: never)."""
        return None

    @abstractmethod
    def _compute(self, obs: np.ndarray, prompt_vars: PromptVars) -> list[tuple]:
        """Return ``(belief [A], diagnostics)`` for each new state (row of ``obs``)."""

    def __call__(
        self, obs: torch.Tensor, task: object, env_ids: Sequence[int] | None = None
    ) -> np.ndarray:
        """Beliefs ``[N, A]`` for observations ``[N, obs_dim]``, one row per copy (``env_ids``)."""
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
                array[rows], None if prompt_vars is None else [prompt_vars[i] for i in rows]
            )
            for key, result in zip(missing, results, strict=True):
                prepared = _prepare(result[1], self.name)
                if key in stale:  # counted once per distinct state: drop the old answer's
                    stale.discard(key)
                    self.agent_statuses_unique.subtract(memo[key][1][0])
                    self.agent_statuses_unique = +self.agent_statuses_unique
                memo[key] = (np.asarray(result[0], dtype=np.float64), prepared)
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
            self._account(entry[1])
        self.steps += len(array)
        # judged on new states, and every CHECK_EVERY calls (a policy that keeps visiting
        # states an agent cannot answer raises the share without asking anything new)
        if self.max_abstention is not None and (missing or self.calls % CHECK_EVERY == 0):
            self.check_abstention()
        self.calls += 1
        return out

    def _account(self, prepared: tuple) -> None:
        """Add one row's diagnostics (as `_prepare` returns them) to the totals."""
        pairs, weights, conflict, entropies = prepared
        self.agent_statuses.update(pairs)
        self.statuses.update(status for _, status in pairs)
        for name, share in entropies or ():
            cell = self._entropy_sum.setdefault(name, [0.0, 0])
            cell[0] += share
            cell[1] += 1
        if weights:
            for name, value in weights:
                self._weight_sum[name] = self._weight_sum.get(name, 0.0) + value
            self._diag_count += 1
            self._conflict_sum += conflict

    def agent_report(self, *, per: str = "steps") -> dict[str, dict[str, Any]]:
        """Per agent: each status's count, ``total``, ``failed`` (not `ANSWERED`), ``failure_rate``.

        ``per``: ``"steps"`` (each rewarded step counts) or ``"states"`` (each distinct state once).
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
        """Raise `AbstentionError` when an agent failed on over `max_abstention` of its steps.

        Judged once the agent was asked `MIN_STATES_JUDGED` distinct states.
        """
        limit = self.max_abstention
        if limit is None:
            return
        states = self.agent_report(per="states")
        skip = ANSWERED | DOCUMENTED_ZERO | {"total", "failed", "failure_rate"}
        for agent, row in self.agent_report(per="steps").items():
            if states.get(agent, {}).get("total", 0) < MIN_STATES_JUDGED:
                continue
            total = row["total"]
            failures = {status: n for status, n in row.items() if n and status not in skip}
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

    def summary(self) -> dict[str, Any]:
        """Diagnostics so far, JSON-ready (``feedback.json``, ``results.json``)."""
        total = sum(self.statuses.values())
        answered = sum(n for status, n in self.statuses.items() if status in ANSWERED)
        n = max(1, self._diag_count)
        out = {
            "feedback": self.name,
            "steps": self.steps,
            "unique_states": len(self._memo),
            "mean_weight": {k: v / n for k, v in self._weight_sum.items()},
            "mean_conflict": self._conflict_sum / n if self._diag_count else None,
            "mean_entropy_share": {k: v[0] / v[1] for k, v in self._entropy_sum.items()},
            "statuses": dict(self.statuses),
            "miss_rate": (self.statuses.get("replay_miss", 0) / total) if total else 0.0,
            "failure_rate": (total - answered) / total if total else 0.0,
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
    """Return ``(((agent, status), ...), ((cluster, weight), ...) or None, conflict, entropies)``.

    Agents are ``diag["agents"]``, else the weights' names when they match the statuses one to
    one, else ``default_agent``. Done once per distinct state.
    """
    weights = diag.get("weights")
    pairs = tuple((name, float(value)) for name, value in weights.items()) if weights else None
    conflict = float(diag.get("conflict", 0.0)) if weights else 0.0
    statuses = tuple(str(s) for s in diag.get("statuses", ()))
    agents = tuple(diag.get("agents") or (weights or {}))
    if len(agents) != len(statuses):
        agents = (default_agent,) * len(statuses)
    shares = diag.get("entropy_share")
    entropies = tuple((name, float(v)) for name, v in shares.items()) if shares else None
    return tuple(zip(agents, statuses, strict=True)), pairs, conflict, entropies


class CallableFeedback(Feedback):
    """Feedback from a plain function ``obs [N, D] -> beliefs [N, A]`` (tests, scripts)."""

    def __init__(self, fn: Callable[[np.ndarray], np.ndarray], name: str = "scripted") -> None:
        super().__init__()
        self.fn = fn
        self.name = name

    def _compute(self, obs: np.ndarray, prompt_vars: PromptVars) -> list[tuple]:
        beliefs = np.asarray(self.fn(obs), dtype=np.float64)
        return [(b, {"statuses": ("ok",)}) for b in beliefs]


class DemonstratorFeedback(Feedback):
    """The authors' synthetic human: a demonstrator's action counts.

    A state's belief is ``p(a) ∝ 0.6^c_a 0.4^(n - c_a)``; a state the demonstrator never
    visited rewards 0 (the authors' ``finetune_moral_human.py``), counted as ``unseen``.
    """

    name = "human"
    #: the one "agent" of this feedback in the per-agent report
    agent = "demonstrator"

    def __init__(self, task_name: str, *, seed: int, cache_dir: Path | None = None) -> None:
        super().__init__()
        from amuled_ma.tasks.demonstrators import demonstrator_belief

        self.table = demonstrator_belief(task_name, seed=seed, cache_dir=cache_dir)

    def _compute(self, obs: np.ndarray, prompt_vars: PromptVars) -> list[tuple]:
        table_beliefs, seen = self.table.lookup(torch.as_tensor(obs))
        beliefs = np.asarray(table_beliefs, dtype=np.float64)
        return [
            (row, {"statuses": ("ok" if known else "unseen",), "agents": (self.agent,)})
            for row, known in zip(beliefs, np.asarray(seen).tolist(), strict=True)
        ]
