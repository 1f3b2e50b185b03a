"""The interface of every belief source: `BeliefRequest` batches in, `BeliefResult` out in order."""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from amuled_ma.beliefs.replies.validate import uniform_belief

K = TypeVar("K")

#: Parse / answer statuses a `BeliefResult` may carry (their meanings: ``docs/beliefs.md``).
STATUSES = ("ok", "repaired", "abstained", "replay_miss", "timeout", "error")
#: Statuses of a distilled reward model's beliefs (`distill`): fused, never stored.
MODEL_STATUSES = ("distilled", "distilled_miss")
#: Status of a state not asked whose agent the distilled model cannot answer yet: it abstains.
UNASKED = "unasked"
#: Statuses fused as an agent's answer: the panel's (``ok``, ``repaired``) and the model's.
FUSED_STATUSES = frozenset({"ok", "repaired", *MODEL_STATUSES})


@dataclass(frozen=True)
class BeliefRequest:
    """One question to one moral-cluster agent about one task state.

    ``obs`` is the replay key; ``messages`` the chat sent to an LLM as ``((role, content), ...)``
    (hashable: identical requests of a batch are recognised), empty for sources needing none.
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

    ``belief`` sums to 1; a status outside `FUSED_STATUSES` means a fallback (uniform, ...).
    ``cached``: read from the store (``latency_s`` 0); ``extra``: diagnostics (retries, errors).
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

    @classmethod
    def failed(
        cls,
        n_actions: int,
        status: str,
        source: str,
        error: str,
        *,
        raw: str | None = None,
        latency_s: float = 0.0,
        **extra: Any,
    ) -> BeliefResult:
        """No answer: a uniform belief with ``status``, the reason in ``extra["error"]``."""
        belief = uniform_belief(n_actions)
        return cls(
            belief, status, source, raw, latency_s=latency_s, extra={"error": error, **extra}
        )

    def copy(self, **changes: Any) -> BeliefResult:
        """An independent copy (own belief array and extra dict) with ``changes``."""
        return dataclasses.replace(
            self, belief=self.belief.copy(), extra=dict(self.extra), **changes
        )


class BeliefSource(ABC):
    """Base class of belief sources (an optional ``iter_beliefs`` yields ``(index, result)``)."""

    #: Short registry name of the source kind (``"ollama"``, ``"replay"``, ``"rules"``).
    name: str = "source"
    #: Whether the source reads `BeliefRequest.messages` (an LLM does; replay and
    #: rules do not, so callers may skip rendering prompts for them).
    needs_messages: bool = True

    @abstractmethod
    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer every request, one result each in order; never raise for one bad reply."""

    def identity(self) -> dict[str, Any]:
        """What decides the answers (model, digest, options): hashed into the store key."""
        return {"source": self.name}

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release clients, threads or files held by the source."""


def indices_by(
    requests: Sequence[BeliefRequest], key: Callable[[BeliefRequest], K]
) -> dict[K, list[int]]:
    """The indices of ``requests`` grouped by ``key(request)``, groups in order of first use."""
    groups: dict[K, list[int]] = {}
    for i, request in enumerate(requests):
        groups.setdefault(key(request), []).append(i)
    return groups


def in_order(
    pairs: Iterable[tuple[int, BeliefResult]], count: int, source: str
) -> list[BeliefResult]:
    """The results of ``(index, result)`` pairs by index; one missing raises `RuntimeError`."""
    out: list[BeliefResult | None] = [None] * count
    for index, result in pairs:
        out[index] = result
    answered = [r for r in out if r is not None]
    if len(answered) != count:
        missing = count - len(answered)
        raise RuntimeError(f"belief source {source!r} left {missing} request(s) without a result")
    return answered


def ask(source: BeliefSource, batch: Sequence[BeliefRequest]) -> list[BeliefResult]:
    """``source.beliefs(batch)``; `RuntimeError` when it answers another number of results."""
    results = source.beliefs(batch)
    if len(results) != len(batch):
        raise RuntimeError(
            f"belief source {getattr(source, 'name', '?')!r} answered {len(results)} results "
            f"for {len(batch)} requests"
        )
    return results
