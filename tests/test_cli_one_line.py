"""Every expected failure prints one line, not a traceback.

Bad task options, a negative step limit, an unknown PPO key, a scenario or ``--set`` value
nested 10,000 levels deep, ``beliefs import`` of a lone surrogate or into a damaged store,
``view --serve-seconds 1e12``, and a 10 GB recording (a sparse file: no disk is used).
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sparse_files import sparse
from tiny_cli import amuled, one_line

from amuled_ma.cli import build_parser, main


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ('task.options={layout="evil"}', "key [task].options of task 'findmilk'"),
        ("task.options={evil=1}", "unknown option 'evil'"),
        ("task.options={seed=3}", "seed cannot be a task option"),
        ("task.max_steps=-5", "key [task].max_steps expects a non-negative integer"),
        ("ppo.device=", "unknown key [ppo].device"),
        ("task.options=" + "[" * 10_000 + "]" * 10_000, "nested deeper than Python can read"),
    ],
)
def test_bad_overrides_are_one_line(tmp_path: Path, capsys, override: str, expected: str) -> None:
    run_dir = tmp_path / "run"
    args = ["train", "findmilk", "--variant", "base", "--run-dir", str(run_dir), "--no-progress"]
    assert main([*args, "--set", "base.total_steps=64", "--set", override]) == 1
    assert expected in one_line(capsys.readouterr().err)


def test_a_scenario_nested_10000_levels_is_one_line(tmp_path: Path, capsys) -> None:
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 10_000 + "]" * 10_000 + "\n")
    dotted = tmp_path / "dotted.toml"
    dotted.write_text("a." * 5_000 + "b = 1\n")
    for path in (deep, dotted):
        assert main(["train", str(path), "--run-dir", str(tmp_path / "run")]) == 1
        line = one_line(capsys.readouterr().err)
        assert f"{path}: the scenario nests values" in line


def test_view_serve_seconds_beyond_what_a_timer_holds_is_a_usage_error(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["view", "runs/x", "--serve", "--serve-seconds", "1e12"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "argument --serve-seconds: expected seconds in (0, 10,000,000], found 1e12" in err


def _store_with_rows(path: Path, n: int = 200) -> None:
    from amuled_ma.beliefs import BeliefRequest, BeliefResult
    from amuled_ma.beliefs.store.database import BeliefStore

    with BeliefStore(path) as store:
        for i in range(n):
            chat = (("user", f"state {i} " + "x" * 2000),)
            request = BeliefRequest("findmilk", "care", (float(i),), ("a", "b"), chat)
            result = BeliefResult(np.array([0.5, 0.5]), "ok", "rules", raw="r")
            store.put_many([(f"k{i}", {"source": "rules"}, request, result)])
        store.checkpoint()


def test_beliefs_import_of_a_lone_surrogate_is_one_line(tmp_path: Path) -> None:
    store = tmp_path / "old.sqlite"
    _store_with_rows(store, 2)
    export = amuled("beliefs", "export", "--store", str(store))
    assert export.returncode == 0, export.stderr
    row = json.loads(export.stdout.splitlines()[0])
    row["raw"] = "\ud800"
    jsonl = tmp_path / "rows.jsonl"
    jsonl.write_text(json.dumps(row) + "\n")  # ensure_ascii: the file holds \ud800
    done = amuled("beliefs", "import", "--store", str(tmp_path / "new.sqlite"), str(jsonl))
    assert done.returncode == 1
    line = one_line(done.stderr)
    assert f"{jsonl}:1: raw holds \\ud800 at character 0" in line


def test_beliefs_import_into_a_damaged_store_is_one_line(tmp_path: Path) -> None:
    store = tmp_path / "beliefs.sqlite"
    _store_with_rows(store)
    export = amuled("beliefs", "export", "--store", str(store))
    jsonl = tmp_path / "rows.jsonl"
    jsonl.write_text(export.stdout)
    noise = random.Random(24).randbytes(4096 * 5)
    with open(store, "r+b") as handle:  # overwrite five pages of the b-tree
        handle.seek(4096 * 3)
        handle.write(noise)
    done = amuled("beliefs", "import", "--no-verify", "--store", str(store), str(jsonl))
    assert done.returncode == 1
    line = one_line(done.stderr)
    assert f"{store}: cannot" in line and "malformed" in line


def test_a_10_gb_recording_is_refused_unread(tmp_path: Path) -> None:
    big = tmp_path / "big.json"
    subprocess.run(["truncate", "-s", "10G", str(big)], check=True)  # sparse: no disk used
    program = (
        "import sys\nfrom amuled_ma.beliefs.sources.replay import Recording\n"
        "from amuled_ma.errors import ScenarioError\n"
        "try:\n    Recording(sys.argv[1])\nexcept ScenarioError as e:\n    print(e)\n"
    )
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", program, str(big)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert time.perf_counter() - start < 60
    assert "the recording is 10,737,418,240 bytes, more than the 268,435,456" in done.stdout


def test_a_2_gb_line_of_jsonl_is_refused_unread_with_file_and_line(tmp_path: Path) -> None:
    from amuled_ma.beliefs.store.interchange import MAX_LINE_CHARS

    big = tmp_path / "big.jsonl"
    big.write_text("\n")  # line 1: blank (skipped); line 2: 2 GB of zeros, no newline
    sparse(big, 2 * 2**30)  # no disk used
    start = time.perf_counter()
    done = amuled("beliefs", "import", "--store", str(tmp_path / "s.sqlite"), str(big))
    assert time.perf_counter() - start < 30  # reading 2 GB would take longer, and 2 GB memory
    assert done.returncode == 1
    line = one_line(done.stderr)
    assert line.startswith(f"amuled: error: {big}:2: a line longer than the {MAX_LINE_CHARS:,}")
    assert "is it the right file?" in line


def test_a_billion_seeds_are_refused_before_any_job_is_planned(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    start = time.perf_counter()
    assert main(["run", "findmilk", "--seeds", "1000000000", "--run-dir", str(run_dir)]) == 1
    assert time.perf_counter() - start < 2.0
    assert "expected at most 10,000 training replicas" in one_line(capsys.readouterr().err)
    assert not run_dir.exists()


def test_a_misspelt_scenario_names_the_closest(tmp_path: Path, capsys) -> None:
    assert main(["run", "findmik", "--run-dir", str(tmp_path / "run")]) == 1
    assert "(did you mean findmilk?)" in one_line(capsys.readouterr().err)
