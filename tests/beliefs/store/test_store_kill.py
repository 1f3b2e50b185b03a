"""A real ``kill -9`` of a process writing to the store leaves every committed row intact."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from amuled_ma.beliefs.store.database import BeliefStore

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs SIGKILL")

BATCH = 40

# Writes batches of BATCH rows, one transaction each, and prints "committed <b>" after
# each commit. With mode "hang", it then opens one more transaction, inserts five batches
# (the cache is tiny, so dirty pages spill into the WAL file), prints "inside", and waits
# to be killed in the middle of that transaction.
_CHILD = textwrap.dedent(
    """
    import sys, time, numpy as np
    from amuled_ma.beliefs.store.keys import request_key
    from amuled_ma.beliefs.store.database import BeliefStore, _UPSERT
    from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
    path, mode, batch = sys.argv[1], sys.argv[2], int(sys.argv[3])
    ident = {"source": "scripted", "model": "m"}
    s = BeliefStore(path)
    s._connect().execute("PRAGMA cache_size = 2")

    def item(i):
        r = BeliefRequest("findmilk", "care", (float(i), 0.5), ("a", "b", "c"),
                          (("system", "S" * 300), ("user", f"state {i}")))
        b = np.array([i % 5, i % 3, 1.0]); b = b / b.sum()
        raw = f"reply {i} " + "x" * (1000 + i % 500)
        return (request_key(ident, r), ident, r, BeliefResult(b, "ok", "scripted", raw=raw))

    i = b = 0
    limit = 25 if mode == "hang" else 10**9
    while b < limit:
        s.put_many([item(j) for j in range(i, i + batch)])
        i += batch; b += 1
        print("committed", b, flush=True)

    def body(conn):
        # obs "[]" marks these rows: if one ever showed up, the check would fail loudly
        for key, idn, r, res in [item(j) for j in range(i, i + 5 * batch)]:
            conn.execute(_UPSERT, (key, "scripted", "{}", r.task, r.cluster, "[]", "[]", None,
                                   res.raw, "[0]", "ok", 0.0, None, None, "{}", 1, 0.0, 0.0))
        print("inside", flush=True)
        time.sleep(600)
    s._write(body)
    """
)


def _uncommitted_wal_frames(path) -> int:
    """Frames at the end of the WAL written after its last commit frame (same salt).

    WAL layout (sqlite.org/fileformat.html#the_write_ahead_log): a 32-byte header (page
    size at bytes 8-12, salts at 16-24), then frames of a 24-byte header (bytes 4-8: the
    database size after a commit, 0 for a non-commit frame; bytes 8-16: the salts) + a page.
    """
    with open(str(path) + "-wal", "rb") as fp:
        data = fp.read()
    page = struct.unpack(">I", data[8:12])[0]
    salt = data[16:24]
    sizes, off = [], 32
    while off + 24 + page <= len(data) and data[off + 8 : off + 16] == salt:
        sizes.append(struct.unpack(">I", data[off + 4 : off + 8])[0])
        off += 24 + page
    last_commit = max((i for i, c in enumerate(sizes) if c), default=-1)
    return len(sizes) - 1 - last_commit


def _expected(i: int) -> np.ndarray:
    b = np.array([i % 5, i % 3, 1.0])
    return b / b.sum()


def _check(path, committed_batches: set[int]) -> int:
    with BeliefStore(path) as s:
        assert s.integrity_check() == ["ok"]
        rows = list(s.iter_rows())
        ids = sorted(int(r.obs[0]) for r in rows)
        # whole batches only: a transaction is all or nothing
        assert len(ids) % BATCH == 0
        assert ids == list(range(len(ids)))
        assert len(ids) // BATCH in committed_batches
        for r in rows:
            i = int(r.obs[0])
            np.testing.assert_allclose(r.belief, _expected(i), rtol=0, atol=1e-15)
            assert r.raw == f"reply {i} " + "x" * (1000 + i % 500)
            assert r.messages[1] == ("user", f"state {i}") and r.status == "ok"
        # the store still takes writes after the crash
        s.put_many([])
        return len(ids)


def _run_child(path, mode: str, stop_after: str) -> tuple[int, list[str]]:
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path), mode, str(BATCH)],
        stdout=subprocess.PIPE,
        text=True,
    )
    lines = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.strip())
            if line.strip() == stop_after:
                os.kill(proc.pid, signal.SIGKILL)  # a real kill -9
                break
        proc.wait(timeout=60)
        lines.extend(line.strip() for line in proc.stdout)  # printed before it died
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, lines


def test_kill_9_in_the_middle_of_a_transaction(tmp_path):
    path = tmp_path / "killed.sqlite"
    rc, lines = _run_child(path, "hang", "inside")
    assert rc == -signal.SIGKILL and lines[-1] == "inside"
    # the kill really landed mid-write: pages of the open transaction are in the WAL
    assert _uncommitted_wal_frames(path) > 0
    committed = sum(1 for line in lines if line.startswith("committed"))
    assert committed == 25
    assert _check(path, {committed}) == committed * BATCH


def test_kill_9_while_writing_continuously(tmp_path):
    path = tmp_path / "killed2.sqlite"
    rc, lines = _run_child(path, "loop", "committed 30")
    assert rc == -signal.SIGKILL
    # every batch it reported is there; the kill may have landed after one more commit
    # but before its line was printed
    printed = max(int(line.split()[1]) for line in lines if line.startswith("committed"))
    assert printed >= 30
    assert _check(path, {printed, printed + 1}) >= printed * BATCH
