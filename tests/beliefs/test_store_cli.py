"""``amuled beliefs stats|export|import``: a store moved between machines round-trips."""

from __future__ import annotations

import json

import numpy as np

from amuled_ma.beliefs.store import BeliefStore, request_key
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
from amuled_ma.cli import main

IDENT = {"source": "ollama", "model": "llama3.1:70b", "digest": "sha256:1234"}


def fill(path, n=12):
    with BeliefStore(path) as s:
        items = []
        for i in range(n):
            r = BeliefRequest("driving", ["care", "virtue"][i % 2], (float(i), -1.0),
                              ("straight", "right", "left"),
                              (("system", "S" * 500), ("user", f"state {i}")))  # fmt: skip
            status = "abstained" if i == 5 else "ok"
            result = BeliefResult(
                np.eye(3)[i % 3], status, "ollama", raw=f"r{i}",
                latency_s=0.25, prompt_tokens=100, completion_tokens=9,
            )  # fmt: skip
            items.append((request_key(IDENT, r), IDENT, r, result))
        s.put_many(items)


def test_export_import_round_trip_cli(tmp_path, capsys):
    gpu, laptop, dump = tmp_path / "gpu.sqlite", tmp_path / "laptop.sqlite", tmp_path / "b.jsonl"
    fill(gpu)
    assert main(["beliefs", "export", "--store", str(gpu), "-o", str(dump)]) == 0
    assert len(dump.read_text().splitlines()) == 12
    assert main(["beliefs", "import", "--store", str(laptop), str(dump)]) == 0
    assert "read 12 rows, wrote 12" in capsys.readouterr().out
    with BeliefStore(gpu) as a, BeliefStore(laptop) as b:
        assert [r.to_json() for r in a.iter_rows()] == [r.to_json() for r in b.iter_rows()]
    # only answers, one task
    ok = tmp_path / "ok.jsonl"
    assert main(["beliefs", "export", "--store", str(gpu), "-o", str(ok), "--status", "ok"]) == 0
    assert len(ok.read_text().splitlines()) == 11

    capsys.readouterr()
    assert main(["beliefs", "stats", "--store", str(laptop), "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["rows"] == 12 and figures["cacheable_rows"] == 11
    assert figures["by_status"] == {"ok": 11, "abstained": 1}
    assert figures["tokens"] == {"prompt": 1200, "completion": 108}
    assert figures["integrity"] == ["ok"]
    assert figures["distinct_texts"] == 13  # one shared system prompt + 12 states
    assert main(["beliefs", "stats", "--store", str(laptop)]) == 0
    text = capsys.readouterr().out
    assert "rows: 12 (11 served as answers)" in text and "model llama3.1:70b" in text


def test_import_refuses_tampered_rows(tmp_path, capsys):
    gpu, dump = tmp_path / "gpu.sqlite", tmp_path / "b.jsonl"
    fill(gpu, 3)
    main(["beliefs", "export", "--store", str(gpu), "-o", str(dump)])
    rows = [json.loads(line) for line in dump.read_text().splitlines()]
    rows[1]["obs"][0] = 99.0  # the content no longer matches its key
    dump.write_text("".join(json.dumps(r) + "\n" for r in rows))
    capsys.readouterr()
    assert main(["beliefs", "import", "--store", str(tmp_path / "x.sqlite"), str(dump)]) == 1
    assert "b.jsonl:2: key" in capsys.readouterr().err
    assert main(["beliefs", "import", "--no-verify", "--store", str(tmp_path / "y.sqlite"),
                 str(dump)]) == 0  # fmt: skip


def test_missing_store_is_a_clear_error(tmp_path, capsys):
    assert main(["beliefs", "stats", "--store", str(tmp_path / "none.sqlite")]) == 1
    assert "no belief store at" in capsys.readouterr().err
    assert main(["beliefs", "import", "--store", str(tmp_path / "s.sqlite"), "nope.jsonl"]) == 1
    assert "nope.jsonl: cannot read" in capsys.readouterr().err
