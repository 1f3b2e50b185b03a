"""CachedSource: hits, misses, dedup, write-on-arrival, caching policy per status."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource

ACTIONS = ("a", "b", "c")


class Scripted(BeliefSource):
    """Answers one-hot on ``obs[0] % 3``; status from ``statuses`` by obs[0]; logs calls."""

    name = "scripted"

    def __init__(self, statuses=None, model="m1", fail_after=None):
        self.calls: list[list[BeliefRequest]] = []
        self.statuses = statuses or {}
        self.model = model
        self.fail_after = fail_after

    def identity(self):
        return {"source": self.name, "model": self.model}

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        if self.fail_after is not None and sum(map(len, self.calls)) >= self.fail_after:
            raise ConnectionError("backend went away")
        self.calls.append(list(requests))
        out = []
        for r in requests:
            i = int(r.obs[0])
            status = self.statuses.get(i, "ok")
            belief = np.full(3, 1 / 3) if status != "ok" else np.eye(3)[i % 3]
            out.append(BeliefResult(belief, status, self.name, raw=f"reply {i}", latency_s=0.5))
        return out


class Streaming(Scripted):
    """Also offers iter_beliefs, answering in reverse order, and dies after ``die_at``."""

    def __init__(self, die_at=None, **kw):
        super().__init__(**kw)
        self.die_at = die_at

    def iter_beliefs(self, requests):
        results = Scripted.beliefs(self, requests)
        for n, i in enumerate(reversed(range(len(requests)))):
            if self.die_at is not None and n == self.die_at:
                raise KeyboardInterrupt
            yield i, results[i]


def req(i: int, cluster="care") -> BeliefRequest:
    return BeliefRequest("findmilk", cluster, (float(i), 0.0), ACTIONS, (("user", f"s{i}"),))


@pytest.fixture
def store(tmp_path):
    with BeliefStore(tmp_path / "c.sqlite") as s:
        yield s


def test_miss_then_hit_and_dedup(store):
    src = Scripted()
    cached = CachedSource(src, store)
    batch = [req(1), req(2), req(1), req(1), req(4)]
    out = cached.beliefs(batch)
    assert [int(np.argmax(r.belief)) for r in out] == [1, 2, 1, 1, 1]
    assert not any(r.cached for r in out)
    assert len(src.calls) == 1 and [int(r.obs[0]) for r in src.calls[0]] == [1, 2, 4]
    s = cached.stats
    assert (s.requests, s.unique, s.misses, s.sent, s.written, s.hits) == (5, 3, 3, 3, 3, 0)
    # duplicates are independent arrays
    out[0].belief[:] = 7
    assert out[2].belief[1] == 1.0

    cached.reset_stats()
    again = cached.beliefs(batch)
    assert len(src.calls) == 1  # nothing sent
    assert all(r.cached and r.latency_s == 0.0 for r in again)
    assert [r.raw for r in again] == ["reply 1", "reply 2", "reply 1", "reply 1", "reply 4"]
    assert cached.stats.as_dict() | {} == {
        "requests": 5, "unique": 3, "store_hits": 3, "misses": 0,
        "sent": 0, "written": 0, "not_cached": 0, "invalid": 0, "hits": 3, "hit_rate": 1.0,
    }  # fmt: skip


def test_every_hit_is_read_from_the_store(store):
    # no in-memory copy in front of the store (docs/beliefs.md, "Caches"): each result
    # handed out is the caller's own
    src = Scripted()
    cached = CachedSource(src, store)
    cached.beliefs([req(1), req(2), req(3)])
    cached.reset_stats()
    out = cached.beliefs([req(3), req(1)])
    assert cached.stats.store_hits == 2 and cached.stats.sent == 0
    assert all(r.cached for r in out)
    out[0].belief[:] = 0  # callers cannot corrupt what the next call reads
    assert cached.beliefs([req(3)])[0].belief.tolist() == [1.0, 0.0, 0.0]


def test_a_second_process_shares_the_answers(tmp_path):
    path = tmp_path / "shared.sqlite"
    with BeliefStore(path) as a:
        CachedSource(Scripted(), a).beliefs([req(i) for i in range(10)])
    src = Scripted()
    with BeliefStore(path) as b:
        c = CachedSource(src, b)
        c.beliefs([req(i) for i in range(10)])
        assert src.calls == [] and c.stats.hit_rate == 1.0
        # another model is another identity: no sharing
        other = Scripted(model="m2")
        CachedSource(other, b).beliefs([req(0)])
        assert len(other.calls) == 1


def test_policy_per_status(store):
    statuses = {1: "abstained", 2: "timeout", 3: "replay_miss", 4: "repaired"}
    src = Scripted(statuses=statuses)
    cached = CachedSource(src, store)
    out = cached.beliefs([req(i) for i in range(5)])
    assert [r.status for r in out] == ["ok", "abstained", "timeout", "replay_miss", "repaired"]
    assert cached.stats.not_cached == 3
    rows = {int(r.obs[0]): r.status for r in store.iter_rows()}
    assert rows == {0: "ok", 1: "abstained", 2: "timeout", 4: "repaired"}  # no replay_miss row
    # next run: only ok/repaired are hits; failures are asked again
    src.statuses = {}
    cached.reset_stats()
    out = cached.beliefs([req(i) for i in range(5)])
    assert [int(r.obs[0]) for r in src.calls[-1]] == [1, 2, 3]
    assert [r.status for r in out] == ["ok"] * 4 + ["repaired"]
    row = store.get_many([cached.keys([req(1)])[0]])
    assert next(iter(row.values())).attempts == 2


def test_chunks_are_written_before_a_failure(store):
    src = Scripted(fail_after=4)
    cached = CachedSource(src, store, chunk_size=2)
    with pytest.raises(ConnectionError):
        cached.beliefs([req(i) for i in range(10)])
    assert len(store) == 4  # the two chunks answered before the backend died are kept
    src.fail_after = None
    cached.beliefs([req(i) for i in range(10)])
    assert [int(r.obs[0]) for r in src.calls[-1]] == [8, 9]
    assert sum(len(c) for c in src.calls) == 10  # nothing asked twice


def test_iter_beliefs_writes_each_answer_on_arrival(store):
    src = Streaming(die_at=3)
    cached = CachedSource(src, store)
    with pytest.raises(KeyboardInterrupt):
        cached.beliefs([req(i) for i in range(6)])
    assert sorted(int(r.obs[0]) for r in store.iter_rows()) == [3, 4, 5]
    src.die_at = None
    out = cached.beliefs([req(i) for i in range(6)])
    assert [int(np.argmax(r.belief)) for r in out] == [0, 1, 2, 0, 1, 2]
    assert [r.cached for r in out] == [False] * 3 + [True] * 3


def test_transparent_identity_and_name(store):
    src = Scripted()
    cached = CachedSource(src, store)
    assert cached.name == "scripted" and cached.identity() == src.identity()
    assert cached.needs_messages is True
    src.needs_messages = False
    assert cached.needs_messages is False


class Offline(Scripted):
    """A source whose backend is gone: identity() and beliefs() both fail."""

    def identity(self):
        raise ConnectionError("no server")

    def beliefs(self, requests):
        raise ConnectionError("no server")


def test_replay_a_store_without_the_backend(tmp_path):
    path = tmp_path / "gpu.sqlite"
    with BeliefStore(path) as gpu:
        CachedSource(Scripted(), gpu).beliefs([req(i) for i in range(4)])
    with BeliefStore(path) as laptop:
        (entry,) = laptop.identities()
        assert entry == {"identity": {"source": "scripted", "model": "m1"}, "rows": 4,
                         "answers": 4}  # fmt: skip
        cached = CachedSource(Offline(), laptop, identity=entry["identity"])
        out = cached.beliefs([req(i) for i in range(4)])
        assert [int(np.argmax(r.belief)) for r in out] == [0, 1, 2, 0]
        assert cached.stats.sent == 0
        with pytest.raises(ConnectionError):  # only a miss needs the backend
            cached.beliefs([req(9)])


def test_identity_is_asked_once(store):
    class Counting(Scripted):
        asked = 0

        def identity(self):
            Counting.asked += 1
            return super().identity()

    cached = CachedSource(Counting(), store)
    for i in range(3):
        cached.beliefs([req(i)])
    assert Counting.asked == 1
    cached.refresh_identity()
    cached.beliefs([req(0)])
    assert Counting.asked == 2
