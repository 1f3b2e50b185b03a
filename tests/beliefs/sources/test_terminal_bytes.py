"""Random bytes typed at the terminal source: refused and asked again, never a crash.

A real program reads a real stdin (bytes that are not UTF-8, decoded the way a C locale
does, with ``surrogateescape``, or strictly) and writes each answer to a real SQLite store.
"""

from __future__ import annotations

import io
import json
import os
import random
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest, BeliefResult
from amuled_ma.beliefs.sources.terminal import TerminalSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.rows import BeliefStoreError

REPO = Path(__file__).resolve().parents[3]
MILK = ("up", "down", "left", "right")

#: A TerminalSource on the real stdin, behind a real store; prints each result as JSON.
PROGRAM = textwrap.dedent(
    """
    import json, sys
    from amuled_ma.beliefs import BeliefRequest
    from amuled_ma.beliefs.store.cached import CachedSource
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.beliefs.sources.terminal import TerminalSource

    actions = ("up", "down", "left", "right")
    requests = [BeliefRequest("findmilk", "care", (float(i), 2.0), actions) for i in range(2)]
    store = BeliefStore(sys.argv[1])
    results = CachedSource(TerminalSource(person="ann"), store).beliefs(requests)
    rows = {row.key: row.raw for row in store.iter_rows()}
    print(json.dumps({
        "results": [[r.status, r.belief.tolist(), r.extra.get("error")] for r in results],
        "raws": sorted(str(raw) for raw in rows.values()),
    }))
    """
)


def run(stdin: bytes, store: Path, encoding: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONIOENCODING": encoding}
    return subprocess.run(
        [sys.executable, "-c", PROGRAM, str(store)],
        input=stdin,
        capture_output=True,
        cwd=REPO,
        env=env,
        timeout=120,
    )


def noise(seed: int) -> bytes:
    """A line of random bytes that is not UTF-8 (no newline inside)."""
    rng = random.Random(seed)
    data = bytes(rng.choice([b for b in range(256) if b != 10]) for _ in range(40))
    return b"\xff" + data + b"\xc3\n"


@pytest.mark.parametrize("encoding", ["utf-8:surrogateescape", "utf-8:strict"])
def test_random_bytes_are_refused_and_asked_again(tmp_path: Path, encoding: str) -> None:
    stdin = noise(1) + b"1\n" + noise(2) + noise(3) + noise(4)
    done = run(stdin, tmp_path / "beliefs.sqlite", encoding)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    out = json.loads(done.stdout)
    first, second = out["results"]
    # the bytes were refused and the person asked again: the next line answered
    assert first[0] == "ok" and first[1] == [0.0, 1.0, 0.0, 0.0]
    # three lines of bytes: the state abstains (stored, asked again in a later run)
    assert second[0] == "abstained" and "3 invalid answer(s)" in second[2]
    assert b"not UTF-8 text" in done.stderr
    # every stored raw line is text the store can hold
    for raw in out["raws"]:
        raw.encode("utf-8")


def test_the_store_refuses_text_it_cannot_encode_with_one_line(tmp_path: Path) -> None:
    store = BeliefStore(tmp_path / "beliefs.sqlite")
    request = BeliefRequest("findmilk", "care", (1.0, 2.0), MILK)
    good = BeliefResult(np.full(4, 0.25), "ok", "rules", raw="fine")
    bad = BeliefResult(np.full(4, 0.25), "ok", "rules", raw="typed \udcff bytes")
    with pytest.raises(BeliefStoreError) as caught:
        store.put_many([("k1", {"source": "rules"}, request, good), ("k2", {}, request, bad)])
    line = str(caught.value)
    assert "\n" not in line and "row k2" in line and "raw holds \\udcff" in line
    assert "nothing of this batch was written" in line
    assert len(store) == 0  # the transaction never started
    chat = BeliefRequest("findmilk", "care", (1.0, 2.0), MILK, (("user", "x\ud800"),))
    with pytest.raises(BeliefStoreError, match=r"row k3: messages\[0\]\[1\] holds \\ud800"):
        store.put_many([("k3", {}, chat, good)])
    store.put_many([("k1", {"source": "rules"}, request, good)])  # the store still works
    assert len(store) == 1


def test_a_line_the_decoder_refused_is_asked_again_in_process() -> None:
    class Strict(io.StringIO):
        calls = 0

        def readline(self, size: int = -1) -> str:
            Strict.calls += 1
            if Strict.calls == 1:
                raise UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte")
            return super().readline(size)

    out = io.StringIO()
    source = TerminalSource(stdin=Strict("2\n"), stdout=out)
    (result,) = source.beliefs([BeliefRequest("findmilk", "care", (1.0,), MILK)])
    assert result.status == "ok" and result.belief.tolist() == [0.0, 0.0, 1.0, 0.0]
    assert "not UTF-8 text" in out.getvalue() and not source.eof
