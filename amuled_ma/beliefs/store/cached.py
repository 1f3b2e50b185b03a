"""`CachedSource`: a belief source behind the store; answers written as they arrive, none lost.

Only misses are sent, each distinct request once; an invalid answer is written as ``"error"``,
never served.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from amuled_ma.beliefs.replies.validate import checked_result
from amuled_ma.beliefs.store.keys import identity_json, request_key
from amuled_ma.beliefs.store.rows import CACHEABLE
from amuled_ma.beliefs.store.service import StoreService
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, ask, in_order

#: Statuses never written to the store.
NOT_STORED = frozenset({"replay_miss"})


@dataclass
class CacheStats:
    """Counters of a `CachedSource` since creation (or `CachedSource.reset_stats`).

    ``requests`` (duplicates included), ``unique`` (per batch), ``misses`` (distinct, not found),
    ``sent`` (to the source), ``not_cached`` (never served back), ``invalid`` (made ``error``).
    """

    requests: int = 0
    unique: int = 0
    store_hits: int = 0
    misses: int = 0
    sent: int = 0
    written: int = 0
    not_cached: int = 0
    invalid: int = 0

    @property
    def hits(self) -> int:
        """Distinct requests answered without asking the wrapped source."""
        return self.store_hits

    @property
    def hit_rate(self) -> float:
        """``hits / unique`` (1.0 for no lookups)."""
        return self.hits / self.unique if self.unique else 1.0

    def as_dict(self) -> dict[str, Any]:
        """All counters plus ``hits`` and ``hit_rate``."""
        return {**asdict(self), "hits": self.hits, "hit_rate": self.hit_rate}


class CachedSource(BeliefSource):
    """A belief source that looks every request up in a store before sending it.

    ``chunk_size`` and ``flush_every``: ``docs/store.md`` ("Writing as answers arrive");
    ``identity``: one the store recorded (`identities`), so that hits never touch the source.
    """

    def __init__(
        self,
        source: BeliefSource,
        store: StoreService,
        *,
        chunk_size: int = 256,
        flush_every: int = 1,
        identity: Mapping[str, Any] | None = None,
    ) -> None:
        self.source = source
        self.store = store
        self.chunk_size = max(1, int(chunk_size))
        self.flush_every = max(1, int(flush_every))
        self.stats = CacheStats()
        self._identity = dict(identity) if identity is not None else None
        self._identity_json: str | None = None

    @property
    def name(self) -> str:  # type: ignore[override]  # property over an attribute
        """The wrapped source's name (a cache is transparent)."""
        return self.source.name

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]  # property over an attribute
        """Whether the wrapped source reads ``BeliefRequest.messages`` (default True)."""
        return bool(getattr(self.source, "needs_messages", True))

    def identity(self) -> dict[str, Any]:
        """Return the identity the store is keyed with (the source's, asked once)."""
        if self._identity is None:
            self._identity = dict(self.source.identity())
        return dict(self._identity)

    def refresh_identity(self) -> None:
        """Ask the source for its identity again at the next batch (a model re-pulled...)."""
        self._identity = None
        self._identity_json = None

    def _ident(self) -> str:
        if self._identity_json is None:
            self._identity_json = identity_json(self.identity())
        return self._identity_json

    def close(self) -> None:
        """Close the wrapped source (the store is left open: it may be shared)."""
        self.source.close()

    def reset_stats(self) -> None:
        """Zero the counters."""
        self.stats = CacheStats()

    def keys(self, requests: Sequence[BeliefRequest]) -> list[str]:
        """Return the store keys of ``requests`` for the wrapped source."""
        ident = self._ident()
        return [request_key(ident, r) for r in requests]

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer from the store, then the wrapped source (misses only), one result a request.

        Hits have ``cached=True``; a request repeated in the batch gets its own copy.
        """
        ident = self._ident()
        positions: dict[str, list[int]] = {}
        for i, key in enumerate(self.keys(requests)):
            positions.setdefault(key, []).append(i)

        stats = self.stats
        stats.requests += len(requests)
        stats.unique += len(positions)

        answers = dict(self.store.lookup(list(positions)))
        stats.store_hits += len(answers)
        missing = [k for k in positions if k not in answers]
        stats.misses += len(missing)
        if missing:
            answers.update(self._ask(ident, [(k, requests[positions[k][0]]) for k in missing]))

        pairs = [
            (i, answers[key] if n == 0 else answers[key].copy())
            for key, idx in positions.items()
            for n, i in enumerate(idx)
        ]
        return in_order(pairs, len(requests), self.name)

    def _ask(self, ident: str, todo: list[tuple[str, BeliefRequest]]) -> dict[str, BeliefResult]:
        """Send the misses and write each answer as soon as it is back."""
        answers: dict[str, BeliefResult] = {}
        pending: list[tuple[str, str, BeliefRequest, BeliefResult]] = []

        def flush() -> None:
            if pending:
                self.stats.written += self.store.put_many(pending)
                pending.clear()

        def take(key: str, request: BeliefRequest, result: BeliefResult) -> None:
            if not isinstance(result, BeliefResult):
                raise RuntimeError(
                    f"belief source {self.source.name!r} answered {type(result).__name__}, "
                    "expected BeliefResult"
                )
            checked_result(result, request.num_actions)
            if "invalid_belief" in result.extra:
                self.stats.invalid += 1
            answers[key] = result
            if result.status not in CACHEABLE:
                self.stats.not_cached += 1
            if result.status not in NOT_STORED:
                pending.append((key, ident, request, result))

        requests = [r for _, r in todo]
        iter_beliefs = getattr(self.source, "iter_beliefs", None)
        try:
            if callable(iter_beliefs):
                self.stats.sent += len(requests)
                for index, result in iter_beliefs(requests):
                    key, request = todo[index]
                    take(key, request, result)
                    if len(pending) >= self.flush_every:
                        flush()
            else:
                for start in range(0, len(todo), self.chunk_size):
                    chunk = todo[start : start + self.chunk_size]
                    self.stats.sent += len(chunk)
                    results = ask(self.source, [r for _, r in chunk])
                    for (key, request), result in zip(chunk, results, strict=True):
                        take(key, request, result)
                    flush()
        finally:
            flush()  # keep whatever arrived, even when the source raised half-way
        return answers


def requests_sent(source: object) -> int | None:
    """Requests the belief caches inside ``source`` sent on (None: it keeps no cache)."""
    stats = getattr(source, "stats", None)
    if stats is not None and hasattr(stats, "sent"):
        return int(stats.sent)
    members = getattr(source, "members", None)
    if not members:
        return None
    counts = [requests_sent(member) for member, _agents in members]
    if any(c is None for c in counts):
        return None
    return sum(c for c in counts if c is not None)
