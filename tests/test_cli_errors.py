"""Every expected failure is one line on stderr, ``amuled: error: ...``, and no traceback.

Each case is one of the attempts of the adversarial pass , run through
the real command line (``amuled_ma.cli.main``, the console script's entry point) with the
output captured; two cases run it as a child process, as a user does.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from amuled_ma.cli import main
from amuled_ma.monitor.progress import PLAIN_LINE

AMULED = [sys.executable, "-m", "amuled_ma"]
ENV = {**os.environ, "GIT_PYTHON_REFRESH": "quiet"}
TINY = [
    "--set", "base.total_steps=512",
    "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16",
    "--set", "output.tensorboard=false",
    "--no-progress",
]  # fmt: skip


def _child(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*AMULED, *args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=300
    )


@pytest.fixture
def _run(capsys, monkeypatch):
    """Run ``amuled ARGS`` in this process; returns what a child process would have."""

    def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
        if cwd is not None:
            monkeypatch.chdir(cwd)
        capsys.readouterr()
        try:
            code = main(list(args))
        except SystemExit as stop:  # argparse usage errors
            code = stop.code
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out, err)

    return run


def _one_line_error(done: subprocess.CompletedProcess, *needles: str) -> str:
    err = done.stderr
    assert done.returncode not in (0, None), (done.stdout, err)
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if not PLAIN_LINE.match(line)]  # progress aside
    assert len(lines) == 1 and lines[0].startswith("amuled: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A run folder with a finished tiny base, trained once through the real CLI."""
    path = tmp_path_factory.mktemp("cli-errors") / "run"
    assert main(["train", "findmilk", "--run-dir", str(path), *TINY]) == 0
    return path


def _store(path: Path, belief: str) -> Path:
    """A belief store with one row whose belief column holds ``belief`` (raw SQL)."""
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.beliefs.types import BeliefRequest, BeliefResult

    request = BeliefRequest("findmilk", "care", (0.0,) * 8, ("up", "down", "left", "right"))
    result = BeliefResult(belief=torch.full((4,), 0.25).numpy(), status="ok", source="rules")
    with BeliefStore(path) as store:
        store.put_many([("key-1", {"source": "rules"}, request, result)])
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE beliefs SET belief = ?", (belief,))
    return path


def test_non_utf8_scenario_in_a_child_process(tmp_path):
    bad = tmp_path / "mine.toml"
    bad.write_bytes(b'name = "caf\xe9"\n')
    _one_line_error(_child("train", str(bad)), str(bad), "not UTF-8", "save it as UTF-8")


def test_non_utf8_cluster_file(_run, tmp_path):
    (tmp_path / "care.toml").write_bytes(b'name = "care"\ntitle = "\xff"\n')
    done = _run("clusters", "list", "--clusters-dir", str(tmp_path))
    _one_line_error(done, "care.toml", "not UTF-8")


def test_unknown_task_of_a_prompt(_run, tmp_path):
    done = _run("clusters", "show", "care", "--task", "nosuchtask")
    _one_line_error(done, "nosuchtask", "known tasks")


def test_missing_scenario_file(_run, tmp_path):
    _one_line_error(_run("train", str(tmp_path / "absent.toml")), "absent.toml")


def test_output_folder_that_cannot_be_created(_run, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    done = _run("train", "findmilk", "--run-dir", str(blocker / "run"), *TINY)
    _one_line_error(done, str(blocker / "run"), "Not a directory", "--run-dir")


def test_full_device(_run, tmp_path):
    """/dev/full: a real write that fails with ENOSPC."""
    import stat

    full = Path("/dev/full")
    if not (full.exists() and stat.S_ISCHR(full.stat().st_mode)):
        pytest.skip("no /dev/full character device on this machine")
    store = _store(tmp_path / "beliefs.sqlite", "[0.25, 0.25, 0.25, 0.25]")
    done = _run("beliefs", "export", "--store", str(store), "-o", str(full))
    _one_line_error(done, "No space left on device", "free some disk space")
    assert stat.S_ISCHR(full.stat().st_mode), "the export replaced the device with a file"


def test_store_row_whose_belief_is_not_json(_run, tmp_path):
    store = _store(tmp_path / "beliefs.sqlite", "{not json")
    done = _run("beliefs", "export", "--store", str(store), "-o", str(tmp_path / "out.jsonl"))
    _one_line_error(done, "beliefs.sqlite")


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["train", "findmilk", "--seed", "-5"], ["--seed", "-5", "amuled train --help"]),
        (["train", "findmilk", "--seed", "x"], ["--seed", "'x'"]),
        (["evaluate", ".", "--episodes", "-3"], ["--episodes", "-3"]),
        (["run", "findmilk", "--jobs", "-1"], ["--jobs", "-1"]),
        (["ollama", "up", "--port", "99999"], ["--port", "99999", "1..65535"]),
    ],
)
def test_bad_arguments(_run, args, needles):
    done = _run(*args)
    assert done.returncode == 2
    _one_line_error(done, *needles)


@pytest.mark.parametrize(
    ("host", "needle"),
    [("http://127.0.0.1:99999", "'99999'"), ("http://127.0.0.1:abc", "'abc'"), ("ftp://x", "ftp")],
)
def test_bad_ollama_url(_run, run_dir, host, needle):
    done = _run(
        "finetune", "findmilk", "--run-dir", str(run_dir), "--set", 'feedback.source="ollama"',
        "--set", f'feedback.host="{host}"', *TINY,
    )  # fmt: skip
    _one_line_error(done, "[feedback].host", needle)


def test_checkpoint_without_the_expected_keys(_run, run_dir, tmp_path):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    torch.save({"weights": torch.zeros(3)}, copy / "base" / "model_last.pt")
    done = _run("evaluate", str(copy), "--episodes", "1", "--no-progress")
    _one_line_error(done, "model_last.pt", "lacks 'actor_state_dict'", "--force")


def test_deeply_nested_recording(_run, run_dir, tmp_path):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    recording = tmp_path / "findmilk-deep.json"
    recording.write_text('{"task": "FindMilk", "states": ' + "[" * 100_000 + "]" * 100_000 + "}")
    done = _run(
        "finetune", "findmilk", "--run-dir", str(copy),
        "--set", f'feedback.recording="{recording}"', "--set", "finetune.iterations=1", *TINY,
    )  # fmt: skip
    _one_line_error(done, str(recording))


def test_deeply_nested_import(_run, tmp_path):
    jsonl = tmp_path / "in.jsonl"
    jsonl.write_text("[" * 100_000 + "]" * 100_000 + "\n")
    done = _run("beliefs", "import", str(jsonl), "--store", str(tmp_path / "s.sqlite"))
    _one_line_error(done, "in.jsonl")


def test_scenario_values_that_cannot_work(_run, tmp_path):
    for text, needle in [
        ("[ppo]\ngamma = 5\n", "[ppo].gamma"),
        ("[base]\nsave_interval = 0\n", "[base].save_interval"),
        ("[ppo]\nclip_param = nan\n", "[ppo].clip_param"),
        ('name = "../../escaped"\n', "escaped"),
    ]:
        path = tmp_path / "s.toml"
        path.write_text(text)
        _one_line_error(_run("train", str(path)), needle)


def test_debug_shows_the_traceback(tmp_path):
    bad = tmp_path / "mine.toml"
    bad.write_bytes(b'name = "caf\xe9"\n')
    done = _child("--debug", "train", str(bad))
    assert done.returncode == 1
    assert "Traceback" in done.stderr and done.stderr.rstrip().endswith("save it as UTF-8")


def test_run_name_stays_inside_runs_dir(_run, tmp_path):
    """The name is refused before anything is written anywhere."""
    path = tmp_path / "deep" / "s.toml"
    path.parent.mkdir()
    path.write_text('name = "../../escaped"\n[output]\nruns_dir = "runs"\ntensorboard = false\n')
    done = _run("train", str(path), cwd=tmp_path / "deep")
    _one_line_error(done, "escaped")
    assert not (tmp_path / "escaped").exists() and not (tmp_path.parent / "escaped").exists()
