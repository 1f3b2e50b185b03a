"""The SQLite belief store: keys, round trips, upsert rule, export/import, several writers."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.interchange import export_jsonl, import_jsonl, row_json
from amuled_ma.beliefs.store.keys import canonical_json, request_key
from amuled_ma.beliefs.store.rows import BeliefStoreError
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult

ACTIONS = ("up", "down", "left", "right")
IDENT = {
    "source": "ollama",
    "model": "smollm2:135m",
    "digest": "sha256:abc",
    "options": {"seed": 0},
}


def req(i: int, cluster: str = "care", messages=(("system", "be good"), ("user", "state"))):
    return BeliefRequest("findmilk", cluster, (float(i), 2.0, 3.0), ACTIONS, tuple(messages))


def res(belief, status="ok", raw="{...}", **kw):
    return BeliefResult(np.asarray(belief, float), status, "ollama", raw=raw, **kw)


@pytest.fixture
def store(tmp_path):
    with BeliefStore(tmp_path / "b.sqlite") as s:
        yield s


def test_key_is_sha256_of_documented_canonical_json():
    r = req(1)
    # Hand-written canonical JSON of the documented recipe, hashed independently.
    text = (
        '{"identity":{"digest":"sha256:abc","model":"smollm2:135m","options":{"seed":0},'
        '"source":"ollama"},"request":{"actions":["up","down","left","right"],"cluster":"care",'
        '"messages":[["system","be good"],["user","state"]],"obs":[1.0,2.0,3.0],'
        '"task":"findmilk"},"v":1}'
    )
    assert request_key(IDENT, r) == hashlib.sha256(text.encode()).hexdigest()
    # the dict form and the pre-serialised identity give the same key
    assert request_key(canonical_json(IDENT), r) == request_key(IDENT, r)


def test_key_of_long_unicode_messages_is_canonical_json():
    long = 'Système "prompt" \\ with\nnewlines, émojis 🙂 and tabs\t. ' * 40
    r = BeliefRequest("driving", "care", (-1.0, 2.5), ("straight", "right", "left"),
                      (("system", long), ("user", "short"), ("user", long + "x")))  # fmt: skip
    whole = {
        "identity": IDENT,
        "request": {"actions": ["straight", "right", "left"], "cluster": "care",
                    "messages": [["system", long], ["user", "short"], ["user", long + "x"]],
                    "obs": [-1.0, 2.5], "task": "driving"},
        "v": 1,
    }  # fmt: skip
    expected = hashlib.sha256(canonical_json(whole).encode()).hexdigest()
    assert request_key(IDENT, r) == expected
    assert request_key(IDENT, r) == expected  # memoised pieces give the same bytes
    # no messages at all (sources that read none)
    bare = BeliefRequest("driving", "care", (-1.0, 2.5), ("straight", "right", "left"))
    whole["request"]["messages"] = []
    assert request_key(IDENT, bare) == hashlib.sha256(canonical_json(whole).encode()).hexdigest()


def test_key_changes_with_every_part():
    base = request_key(IDENT, req(1))
    variants = [
        request_key({**IDENT, "digest": "sha256:def"}, req(1)),
        request_key({**IDENT, "options": {"seed": 1}}, req(1)),
        request_key(IDENT, req(2)),
        request_key(IDENT, req(1, cluster="virtue")),
        request_key(IDENT, req(1, messages=(("system", "be good"), ("user", "state!")))),
        request_key(
            IDENT, BeliefRequest("driving", "care", (1.0, 2.0, 3.0), ACTIONS, req(1).messages)
        ),
    ]
    assert len({base, *variants}) == len(variants) + 1
    # int and float observations of the same value are the same state
    same = BeliefRequest("findmilk", "care", (1, 2, 3), ACTIONS, req(1).messages)
    assert request_key(IDENT, same) == base


def test_round_trip_all_fields(store):
    key = request_key(IDENT, req(1))
    result = res(
        [0.1, 0.2, 0.3, 0.4],
        raw='{"0": 0.1}',
        latency_s=1.5,
        prompt_tokens=120,
        completion_tokens=7,
        extra={"retries": 1},
    )
    assert store.put_many([(key, IDENT, req(1), result)]) == 1
    row = store.get(key)
    assert row is not None and row.status == "ok"
    np.testing.assert_array_equal(row.belief, [0.1, 0.2, 0.3, 0.4])
    assert (row.status, row.raw, row.latency_s, row.prompt_tokens, row.completion_tokens) == (
        "ok",
        '{"0": 0.1}',
        1.5,
        120,
        7,
    )
    assert row.identity == IDENT and row.request() == req(1) and row.extra == {"retries": 1}
    hit = store.lookup([key])[key]
    assert hit.cached and hit.latency_s == 0.0 and hit.extra["stored_latency_s"] == 1.5
    assert len(store) == 1 and key in store


def test_unserialisable_extra_is_kept_as_repr(store):
    key = request_key(IDENT, req(1))
    store.put_many(
        [(key, IDENT, req(1), res([1, 0, 0, 0], extra={"error": ValueError("boom"), "n": 2}))]
    )
    assert store.get(key).extra == {"error": "ValueError('boom')", "n": 2}


def test_answers_are_never_replaced_failures_are(store):
    key = request_key(IDENT, req(1))
    store.put_many([(key, IDENT, req(1), res([0.25] * 4, status="abstained", raw="no json here"))])
    assert store.get(key) is None  # not served
    assert store.get(key, cacheable_only=False).status == "abstained"
    assert store.put_many([(key, IDENT, req(1), res([1, 0, 0, 0], status="repaired"))]) == 1
    row = store.get(key)
    assert row.status == "repaired" and row.attempts == 2
    # a later answer (or failure) never overwrites an answer
    assert store.put_many([(key, IDENT, req(1), res([0, 1, 0, 0]))]) == 0
    assert store.put_many([(key, IDENT, req(1), res([0.25] * 4, status="timeout"))]) == 0
    np.testing.assert_array_equal(store.get(key).belief, [1, 0, 0, 0])


def test_message_bodies_are_stored_once(store):
    items = [(request_key(IDENT, req(i)), IDENT, req(i), res([1, 0, 0, 0])) for i in range(20)]
    assert store.put_many(items) == 20
    # two distinct message bodies ("be good", "state") for 20 rows
    assert store.stats()["distinct_texts"] == 2
    rows = store.get_many([k for k, *_ in items] + ["nope"], with_messages=True)
    assert len(rows) == 20 and all(r.messages == req(0).messages for r in rows.values())
    fast = store.get_many([k for k, *_ in items])
    assert all(r.messages is None for r in fast.values())


def test_stats(store):
    ok = res([1, 0, 0, 0], latency_s=2.0, prompt_tokens=10, completion_tokens=3)
    abstained = res([1, 0, 0, 0], status="abstained", latency_s=4.0, prompt_tokens=5)
    store.put_many(
        [(request_key(IDENT, req(i)), IDENT, req(i), r) for i, r in ((1, ok), (2, abstained))]
    )
    s = store.stats()
    assert s["rows"] == 2 and s["cacheable_rows"] == 1
    assert s["by_status"] == {"ok": 1, "abstained": 1}
    assert s["by_model"] == [{"source": "ollama", "model": "smollm2:135m", "rows": 2}]
    assert s["latency_s"]["mean"] == pytest.approx(3.0) and s["tokens"] == {
        "prompt": 15,
        "completion": 3,
    }


def test_export_import_round_trip(tmp_path, store):
    items = []
    for i in range(30):
        status = ["ok", "repaired", "abstained"][i % 3]
        msgs = req(i).messages if i % 2 else ()
        r = BeliefRequest("findmilk", f"c{i % 5}", (float(i), -1.0), ACTIONS, msgs)
        items.append(
            (
                request_key(IDENT, r),
                IDENT,
                r,
                res(
                    np.eye(4)[i % 4],
                    status=status,
                    raw=f"reply {i} ünïcode",
                    latency_s=i / 10,
                    prompt_tokens=i,
                    extra={"i": i},
                ),
            )
        )
    store.put_many(items)
    buf = io.StringIO()
    assert export_jsonl(store, buf) == 30
    lines = buf.getvalue().splitlines()
    assert len(lines) == 30 and json.loads(lines[0])["belief"] == [1.0, 0.0, 0.0, 0.0]

    with BeliefStore(tmp_path / "laptop.sqlite") as other:
        assert import_jsonl(other, io.StringIO(buf.getvalue())) == {"read": 30, "written": 30}
        a = {r.key: row_json(r) for r in store.iter_rows()}
        b = {r.key: row_json(r) for r in other.iter_rows()}
        assert a == b
        # importing again changes nothing (answers are never replaced; failures are
        # replaced by the same failure, which counts an attempt)
        again = import_jsonl(other, io.StringIO(buf.getvalue()))
        assert again == {"read": 30, "written": 10}
        assert other.integrity_check() == ["ok"]
    buf2 = io.StringIO()
    export_jsonl(store, buf2, status=["ok"])
    assert len(buf2.getvalue().splitlines()) == 10


def test_import_rejects_bad_rows(store):
    good = {
        "key": "k",
        "source": "s",
        "identity": IDENT,
        "task": "findmilk",
        "cluster": "care",
        "obs": [1.0],
        "actions": list(ACTIONS),
        "belief": [1, 0, 0, 0],
        "status": "ok",
    }
    with pytest.raises(BeliefStoreError, match=r"f.jsonl:1: key"):
        import_jsonl(store, io.StringIO(json.dumps(good)), name="f.jsonl")
    import_jsonl(store, io.StringIO(json.dumps(good)), verify=False)
    assert "k" in store
    for bad, match in [
        ({**good, "status": "great"}, "status"),
        ({**good, "belief": [1]}, "belief"),
        ({k: v for k, v in good.items() if k != "task"}, "missing field"),
    ]:
        with pytest.raises(BeliefStoreError, match=match):
            import_jsonl(store, io.StringIO("\n" + json.dumps(bad)), name="x", verify=False)
    with pytest.raises(BeliefStoreError, match="x:1: not JSON"):
        import_jsonl(store, io.StringIO("{oops"), name="x")


def test_not_a_store(tmp_path):
    path = tmp_path / "junk.sqlite"
    path.write_bytes(b"this is not a database" * 100)
    with pytest.raises(BeliefStoreError, match=r"junk\.sqlite"):
        BeliefStore(path)


_WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from amuled_ma.beliefs.store.keys import request_key
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
    path, wid, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    ident = {"source": "scripted"}
    s = BeliefStore(path, timeout_s=60)
    for i in range(n):
        # even i: shared by every writer (same content); odd i: this writer's own rows
        tag = "shared" if i % 2 == 0 else f"w{wid}"
        r = BeliefRequest("findmilk", tag, (float(i),), ("a", "b"), (("user", f"state {i}"),))
        b = np.array([i % 7, 1.0]) / (i % 7 + 1.0)
        answer = BeliefResult(b, "ok", "scripted", raw=f"r{i}")
        s.put_many([(request_key(ident, r), ident, r, answer)])
    """
)


def test_several_processes_write_at_once(tmp_path):
    path = tmp_path / "shared.sqlite"
    n, writers = 120, 3
    procs = [
        subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(w), str(n)])
        for w in range(writers)
    ]
    assert [p.wait(timeout=120) for p in procs] == [0] * writers
    with BeliefStore(path) as s:
        assert s.integrity_check() == ["ok"]
        # n/2 shared rows + n/2 own rows per writer
        assert len(s) == n // 2 + writers * (n // 2)
        for row in s.iter_rows():
            i = int(row.obs[0])
            np.testing.assert_allclose(row.belief, np.array([i % 7, 1.0]) / (i % 7 + 1.0))
            assert row.raw == f"r{i}" and row.attempts == 1


def _child_write(store, i):
    r = req(100 + i)
    store.put_many([(request_key(IDENT, r), IDENT, r, res([0, 0, 1, 0], raw=f"child {i}"))])


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_forked_child_reopens_its_own_connection(store):
    import multiprocessing

    store.put_many([(request_key(IDENT, req(1)), IDENT, req(1), res([1, 0, 0, 0]))])
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_child_write, args=(store, i)) for i in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(30)
    assert [p.exitcode for p in procs] == [0, 0]
    assert len(store) == 3 and store.integrity_check() == ["ok"]
    assert store.get(request_key(IDENT, req(101))).raw == "child 1"


def test_the_value_cap_holds_every_line_an_import_accepts():
    from amuled_ma.beliefs.store import database, interchange

    assert database.MAX_VALUE_BYTES == 4 * interchange.MAX_LINE_CHARS == 2**26  # 64 MiB


def test_a_value_over_the_cap_is_refused_unread_naming_store_and_key(tmp_path, monkeypatch):
    import sqlite3

    from amuled_ma.beliefs.store import database as store_module

    monkeypatch.setattr(store_module, "MAX_VALUE_BYTES", 10_000)
    path = tmp_path / "b.sqlite"
    keys = [request_key(IDENT, req(i)) for i in range(3)]
    with BeliefStore(path) as s:
        s.put_many([(k, IDENT, req(i), res([1, 0, 0, 0])) for i, k in enumerate(keys)])
    with sqlite3.connect(path) as conn:  # edited with another program: no cap there
        conn.execute("UPDATE beliefs SET raw = ? WHERE key = ?", ("x" * 20_000, keys[1]))
    with BeliefStore(path) as s:
        assert set(s.lookup([keys[0], keys[2]])) == {keys[0], keys[2]}  # the others are read
        for read in (s.lookup, s.get_many):
            with pytest.raises(BeliefStoreError) as info:
                read(keys)
            message = str(info.value)
            assert "\n" not in message
            assert message.startswith(f"{path}: row {keys[1]}: a value longer than the 10,000 ")
            assert f"DELETE FROM beliefs WHERE key = '{keys[1]}'" in message
        with pytest.raises(BeliefStoreError, match=rf"^{path}: a row holds a value longer than"):
            list(s.iter_rows())
        # a write over the cap: one line, nothing of the batch written
        new = request_key(IDENT, req(9))
        with pytest.raises(BeliefStoreError, match="a value is longer than the 10,000 bytes"):
            s.put_many([(new, IDENT, req(9), res([1, 0, 0, 0], raw="y" * 20_000))])
        assert new not in s
