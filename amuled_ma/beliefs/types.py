"""The interface of every belief source: `BeliefRequest` batches in, `BeliefResult` out in order."""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Parse / answer statuses a `BeliefResult` may carry.
STATUSES = ("ok", "repaired", "abstained", "replay_miss", "timeout", "error")
#: Statuses of beliefs a distilled reward model gave in the panel's place
#: (`distill`): ``"distilled"`` (a state that was not asked) and
#: ``"distilled_miss"`` (an asked state's replay miss or abstention, answered by the model).
#: They are answers for the fusion, reported apart from the panel's, and never stored.
MODEL_STATUSES = ("distilled", "distilled_miss")
#: Status of a state that was not asked and whose agent the distilled model cannot answer
#: yet (no asked state has that agent's answer): a failure, the agent abstains.
UNASKED = "unasked"
#: Statuses fused as an agent's answer: the panel's (``ok``, ``repaired``) and the model's.
FUSED_STATUSES = frozenset({"ok", "repaired", *MODEL_STATUSES})


@dataclass(frozen=True)
class BeliefRequest:
    """One question to one moral-cluster agent about one task state.

    Attributes:
        task: Task name (``"findmilk"``, ``"driving"``).
        cluster: Cluster (agent) name, e.g. ``"care"`` or ``"moral_agent"``.
        obs: The task observation the belief is asked for (the replay key).
        action_names: Names of the task's actions; index = action id.
        messages: The full chat sent to an LLM (system, few-shot, state prompt) as
            ``((role, content), ...)`` pairs (hashable, so identical requests in a batch
            are recognised); empty for sources that need none.

    """

    task: str
    cluster: str
    obs: tuple[float, ...]
    action_names: tuple[str, ...]
    messages: tuple[tuple[str, str], ...] = ()

    @property
    def num_actions(self) -> int:
        """Number of task actions the belief ranges over."""
        return len(self.action_names)


@dataclass
class BeliefResult:
    """A source's answer to one `BeliefRequest`.

    Attributes:
        belief: Probability vector, shape ``(n_actions,)``, sums to 1.
        status: One of `STATUSES` (or, from a distilled model, of
            `MODEL_STATUSES` or `UNASKED`); anything but ``"ok"``/``"repaired"``
            and the model's answers means the belief is a fallback (uniform, ...).
        source: Name of the source that produced the belief.
        raw: The raw reply text, when there was one.
        cached: True when the answer came from the belief store without a request.
        latency_s: Wall-clock seconds spent answering (0 for cache hits).
        prompt_tokens: Prompt tokens reported by the backend, if any.
        completion_tokens: Completion tokens reported by the backend, if any.
        extra: Free-form diagnostics (retry count, error text, ...).

    """

    belief: np.ndarray
    status: str
    source: str
    raw: str | None = None
    cached: bool = False
    latency_s: float = 0.0
    prompt_tokens: int | None = None
    completion_tokens: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def copy(self, **changes: Any) -> BeliefResult:
        """Return an independent copy (own belief array and extra dict), with ``changes``.

        Duplicates of one request in a batch get copies, so that no two results share
        an array a caller might modify.
        """
        return dataclasses.replace(
            self, belief=self.belief.copy(), extra=dict(self.extra), **changes
        )


class BeliefSource(ABC):
    """Base class of belief sources; subclasses answer batches of requests.

    Optional protocol: a source may also define ``iter_beliefs(requests)`` yielding
    ``(index, result)`` pairs as answers complete (in any order); a caller such as
    `CachedSource` then stores each answer on arrival.
    """

    #: Short registry name of the source kind (``"ollama"``, ``"replay"``, ``"rules"``).
    name: str = "source"
    #: Whether the source reads `BeliefRequest.messages` (an LLM does; replay and
    #: rules do not, so callers may skip rendering prompts for them).
    needs_messages: bool = True

    @abstractmethod
    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer every request, one result each in order; never raise for one bad reply."""

    def identity(self) -> dict[str, Any]:
        """Describe what determines this source's answers (model, digest, options).

        The belief store hashes it into the cache key, so two sources with the same
        identity share cached answers and two different ones never do.
        """
        return {"source": self.name}

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release clients, threads or files held by the source."""


def every_answer(results: Sequence[BeliefResult | None], source: str) -> list[BeliefResult]:
    """A batch's results; a request left without one raises `RuntimeError` naming ``source``."""
    answered = [r for r in results if r is not None]
    if len(answered) != len(results):
        missing = len(results) - len(answered)
        raise RuntimeError(f"belief source {source!r} left {missing} request(s) without a result")
    return answered
