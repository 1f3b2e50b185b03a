"""``amuled beliefs stats|export|import``: a store moved between machines round-trips."""

from __future__ import annotations

import json

import numpy as np
import pytest

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.interchange import row_json
from amuled_ma.beliefs.store.keys import request_key
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
        assert [row_json(r) for r in a.iter_rows()] == [row_json(r) for r in b.iter_rows()]
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


# -- read-only stores ----------------------------------------------------------------


def _drop_write_override():
    """In the child: drop the capabilities that let root write a file it may not write.

    Tests run as root, where ``chmod 0o444`` stops nothing: without CAP_DAC_OVERRIDE and
    CAP_DAC_READ_SEARCH in the bounding set, the exec'ed child is held to the file modes
    like any user.
    """
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def _run_without_write_access(*args):
    import os
    import subprocess
    import sys

    preexec = _drop_write_override if os.geteuid() == 0 else None
    try:
        return subprocess.run(
            [sys.executable, *args],
            preexec_fn=preexec,
            capture_output=True,
            text=True,
            timeout=120,
        )
    except subprocess.SubprocessError as error:  # prctl refused (no CAP_SETPCAP)
        pytest.skip(f"cannot drop write access for a child process here: {error}")


@pytest.fixture
def read_only_store(tmp_path):
    """A store file (mode 0o444) in a folder (0o555) the test's children cannot write."""
    folder = tmp_path / "ro"
    folder.mkdir()
    path = folder / "beliefs.sqlite"
    fill(path, 6)  # closed cleanly: the WAL is folded in, no -wal/-shm left beside it
    path.chmod(0o444)
    folder.chmod(0o555)
    probe = _run_without_write_access("-c", f"open({str(path)!r}, 'a')")
    if probe.returncode == 0:
        folder.chmod(0o755)
        pytest.skip("cannot produce a read-only file here (the child could still write it)")
    assert "PermissionError" in probe.stderr
    yield path
    folder.chmod(0o755)
    path.chmod(0o644)


_CLI_RUNS = """
import contextlib, io, json, sys
from amuled_ma.cli import main
out = {}
for name, argv in json.loads(sys.argv[1]).items():
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(argv)
    out[name] = [rc, stdout.getvalue(), stderr.getvalue()]
print(json.dumps(out))
"""


def _cli_without_write_access(**runs):
    """Run ``amuled`` command lines in one child process without write access."""
    done = _run_without_write_access("-c", _CLI_RUNS, json.dumps(runs))
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[-1])


def test_stats_and_export_read_a_store_that_cannot_be_written(read_only_store, tmp_path):
    path, out = read_only_store, tmp_path / "out.jsonl"
    runs = _cli_without_write_access(
        stats=["beliefs", "stats", "--store", str(path), "--json"],
        export=["beliefs", "export", "--store", str(path), "-o", str(out)],
        write=["beliefs", "import", "--store", str(path), str(out)],
    )
    rc, stdout, stderr = runs["stats"]
    assert rc == 0, stderr
    figures = json.loads(stdout)
    assert figures["rows"] == 6 and figures["by_status"] == {"ok": 5, "abstained": 1}
    # mode=ro needs a -shm file it cannot create in this folder: immutable=1 it is
    assert figures["open_mode"] == "immutable" and figures["integrity"] == ["ok"]
    assert sorted(p.name for p in path.parent.iterdir()) == ["beliefs.sqlite"]  # nothing made
    assert runs["export"][0] == 0, runs["export"][2]
    assert len(out.read_text().splitlines()) == 6
    # writing into it is our error naming the store, not a traceback
    rc, _, stderr = runs["write"]
    assert rc == 1 and str(path) in stderr and "Traceback" not in stderr


def test_read_only_open_of_a_read_only_file_in_a_writable_folder(tmp_path):
    path = tmp_path / "b.sqlite"
    fill(path, 4)
    path.chmod(0o444)
    runs = _cli_without_write_access(stats=["beliefs", "stats", "--store", str(path), "--json"])
    rc, stdout, stderr = runs["stats"]
    assert rc == 0, stderr
    figures = json.loads(stdout)
    assert figures["rows"] == 4 and figures["open_mode"] == "read-only"  # SQLite mode=ro


def test_read_only_store_in_process(tmp_path):
    from amuled_ma.beliefs.store.rows import BeliefStoreError

    missing = tmp_path / "sub" / "none.sqlite"
    with pytest.raises(
        BeliefStoreError, match=r"no belief store at .*none\.sqlite to open read-only"
    ):
        BeliefStore(missing, read_only=True)
    assert not missing.parent.exists()  # nothing created
    path = tmp_path / "b.sqlite"
    fill(path, 3)
    with BeliefStore(path, read_only=True) as store:
        assert store.open_mode == "read-only" and len(store) == 3
        row = next(store.iter_rows())
        with pytest.raises(BeliefStoreError, match="open read-only"):
            store.put_rows([row])
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"not a database " * 100)
    with pytest.raises(BeliefStoreError, match=r"junk\.sqlite: cannot open belief store read-only"):
        BeliefStore(junk, read_only=True)


def test_export_of_a_damaged_store_names_the_row_and_leaves_no_file(tmp_path, capsys):
    import sqlite3

    path = tmp_path / "gpu.sqlite"
    fill(path, 3)
    conn = sqlite3.connect(path)
    key = conn.execute("SELECT key FROM beliefs ORDER BY rowid LIMIT 1 OFFSET 1").fetchone()[0]
    conn.execute("UPDATE beliefs SET belief = '[NaN, 0, 1]' WHERE key = ?", (key,))
    conn.commit()
    conn.close()
    out = tmp_path / "dump.jsonl"
    capsys.readouterr()
    assert main(["beliefs", "export", "--store", str(path), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"row {key}: belief [nan, 0, 1] holds nan at index 0" in err
    assert f"DELETE FROM beliefs WHERE key = '{key}'" in err
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith((".tmp", ".part"))] == []
    # stats still works on it (it reads no belief)
    assert main(["beliefs", "stats", "--store", str(path)]) == 0


def test_import_cli_refuses_nan_with_file_and_line(tmp_path, capsys):
    gpu, dump = tmp_path / "gpu.sqlite", tmp_path / "b.jsonl"
    fill(gpu, 2)
    main(["beliefs", "export", "--store", str(gpu), "-o", str(dump)])
    lines = dump.read_text().splitlines()
    lines[1] = lines[1].replace('"belief": [', '"belief": [NaN, ', 1)
    dump.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    assert main(["beliefs", "import", "--store", str(tmp_path / "l.sqlite"), str(dump)]) == 1
    err = capsys.readouterr().err
    assert "b.jsonl:2: not JSON (NaN is not standard JSON" in err


def test_import_reads_a_line_up_to_the_cap_and_refuses_a_longer_one(tmp_path, capsys, monkeypatch):
    from amuled_ma.beliefs.store import interchange

    gpu, dump = tmp_path / "gpu.sqlite", tmp_path / "b.jsonl"
    fill(gpu, 2)
    main(["beliefs", "export", "--store", str(gpu), "-o", str(dump)])
    first, second = dump.read_text().splitlines()
    cap = 2_000
    monkeypatch.setattr(interchange, "MAX_LINE_CHARS", cap)
    at_cap = first + " " * (cap - len(first))  # JSON allows the spaces: one row, 2,000 long
    dump.write_text(at_cap + "\n" + second + " " * (cap + 1 - len(second)) + "\n")
    capsys.readouterr()
    assert main(["beliefs", "import", "--store", str(tmp_path / "x.sqlite"), str(dump)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"b.jsonl:2: a line longer than the {cap:,} characters a line may be" in err
    dump.write_text(at_cap)  # the last line, without its newline
    assert main(["beliefs", "import", "--store", str(tmp_path / "y.sqlite"), str(dump)]) == 0
    assert "read 1 rows, wrote 1" in capsys.readouterr().out
