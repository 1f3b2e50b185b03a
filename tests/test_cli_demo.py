"""``amuled demo``: its settings, argument handling, the no-server and no-recording paths.

The whole demo runs in ``tests/integration/test_live_demo.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from amuled_ma.cli import main
from amuled_ma.commands._demo_live import LIVE_CLUSTERS, LIVE_STATES
from amuled_ma.commands.demo import DEMO_NUM_PARALLEL, demo_scenario
from amuled_ma.scenario import load_scenario
from amuled_ma.scenario.overrides import parse_set
from amuled_ma.servers.hosts import TINY_MODEL


def test_demo_without_server_fails_fast_and_writes_nothing(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "demo"
    start = time.monotonic()
    code = main(["demo", "--host", "http://127.0.0.1:1", "--run-dir", str(run_dir)])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 1
    assert elapsed < 30.0  # no retry loop; the 5 s bound of preflight is tested with it
    assert "127.0.0.1:1" in err and "amuled ollama up" in err
    assert not run_dir.exists()


#: Each task's demo: the authors' scenario (scenarios/<task>-authors.toml, their
#: recipe, replay of their gpt-4o-mini recording, 50 sampled episodes) with a demo-sized
#: budget, and the live leg's model and reply options.
DEMO_SETS = (
    "base.total_steps=131_072",
    "base.num_envs=64",
    "base.num_steps_per_env=32",
    # rsl-rl's base loop at the demo's budget (scenarios/<task>-demo.toml says why)
    'base.grad_clip="per_network"',
    "base.reshuffle_each_epoch=false",
    "base.bootstrap_time_outs=true",
    "finetune.iterations=100",
    "finetune.save_interval=25",
    "feedback.model=amuled-tiny",
    "feedback.concurrency=1",
    "feedback.timeout_s=600.0",
    "feedback.ollama={reasoning = false, num_predict = 128}",
)
#: FindMilk's demo fine-tunes the authors' published base for 300 iterations; its own base
#: and shaped policies train at the paper's 500,000 steps (docs/reproduction.md, "The demo").
FINDMILK_SETS = (
    *DEMO_SETS,
    "base.total_steps=500_000",
    "finetune.iterations=300",
    "task.options={}",
)


@pytest.mark.parametrize(
    ("task", "source", "sets"),
    [
        ("driving", "driving-authors", DEMO_SETS),
        # FindMilk's demo keeps first-in-order ties (measured so; docs/reproduction.md)
        ("findmilk", "findmilk-authors", FINDMILK_SETS),
    ],
)
def test_demo_scenario_file_holds_the_settings_the_demo_set(task, source, sets) -> None:
    """``scenarios/<task>-demo.toml`` = its source scenario with the demo's ``--set``s."""
    host = "http://127.0.0.1:5"
    expected = load_scenario(source)
    for text in (*sets, f"feedback.host={host}"):
        section, name, value = parse_set(text)
        expected = expected.replace(section, **{name: value})
    demo = demo_scenario(task, model=TINY_MODEL, host=host, private=True)
    assert demo.settings() == expected.settings()
    assert demo.name == f"{task}-demo"
    assert demo.feedback.concurrency == DEMO_NUM_PARALLEL  # the private server's slots
    file = load_scenario(f"{task}-demo")
    assert file.feedback.model == TINY_MODEL and file.feedback.host == ""
    assert file.feedback.ollama == {"reasoning": False, "num_predict": 128}


@pytest.mark.parametrize("task", ["findmilk", "driving"])
def test_demo_replays_the_authors_recording_with_their_recipe(task) -> None:
    file = load_scenario(f"{task}-demo")
    assert file.feedback.source == "replay" and file.feedback.recording == f"{task}-gpt-4o-mini"
    assert file.finetune.recipe == "authors" and file.feedback.miss_policy == "zero"
    assert file.evaluation.modes[0] == "sampled"  # the paper's figures are sampled
    assert LIVE_STATES * len(LIVE_CLUSTERS) <= 6  # a handful of live requests


def test_demo_without_the_recording_says_where_to_put_it_in_one_line(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """Offline (tests/conftest.py sets AMULED_OFFLINE): one line naming both routes."""
    monkeypatch.setenv("AMULED_RECORDINGS", str(tmp_path / "none"))
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)  # in no checkout: nothing beside it
    start = time.monotonic()
    code = main(["demo", "--run-dir", str(tmp_path / "demo")])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 1 and elapsed < 10.0  # an input refused (docs/trust.md, exit codes)
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "findmilk-gpt-4o-mini" in err and "run without it to fetch" in err
    assert "AMULED_RECORDINGS" in err and "amuled import authors" in err
    assert not (tmp_path / "demo").exists()


def test_demo_with_a_real_model_keeps_the_tasks_ollama_options_and_asks_two_at_once() -> None:
    """As before: a model other than the tiny one, on a server the demo did not start."""
    demo = demo_scenario(
        "findmilk",
        model="llama3.1:8b",
        host="http://127.0.0.1:11434",
        private=False,
        overrides=["evaluation.episodes=3"],
    )
    assert demo.feedback.model == "llama3.1:8b"
    assert demo.feedback.ollama == load_scenario("findmilk").feedback.ollama == {}
    assert demo.feedback.concurrency == 2
    assert demo.evaluation.episodes == 3  # the user's --set comes last


def test_mini_batches_of_one_transition_are_refused_with_the_keys_named(tmp_path: Path, capsys):
    """Per-mini-batch advantage normalisation of one sample is NaN: a clear error instead."""
    code = main(
        ["train", "findmilk", "--run-dir", str(tmp_path / "r"), "--no-progress",
         "--set", "base.num_envs=1", "--set", "base.num_steps_per_env=4"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert "num_mini_batches = 4" in err and "mini-batches of 1" in err and "[base]" in err


def test_demo_with_a_real_model_looks_at_the_default_install(monkeypatch, capsys) -> None:
    """No host and a non-tiny model: the user's own server, not a private one."""
    from amuled_ma.servers import hosts
    from amuled_ma.servers import local_server as llm_server

    monkeypatch.delenv("OLLAMA_HOST", raising=False)
    monkeypatch.setattr(hosts, "DEFAULT_HOST", "http://127.0.0.1:1")
    started = []
    monkeypatch.setattr(llm_server, "up", lambda *a, **k: started.append(1))
    assert main(["demo", "--model", "llama3.1:8b"]) == 1
    assert not started
    assert "127.0.0.1:1" in capsys.readouterr().err


def _metric(mean: float, half: float) -> dict[str, float]:
    return {"mean": mean, "half_width": half}


def _variant(steps: float, pacified: float, woken: float, reached: float) -> dict:
    sampled = {
        "steps_to_milk": _metric(steps, 0.25),
        "crying_pacified": _metric(pacified, 0.5),
        "sleeping_woken": _metric(woken, 0.125),
    }
    return {
        "sampled": {"metrics": sampled},
        "greedy": {"metrics": {"reached_milk": _metric(reached, 0)}},
    }


def test_the_summary_puts_every_variant_beside_the_paper_first(tmp_path: Path, monkeypatch) -> None:
    import json

    from amuled_ma.commands.demo import SUMMARY_HEADING, put_summary

    monkeypatch.chdir(tmp_path)  # no runs/authors/findmilk/base here: the run's own base
    results = {"variants": {
        "base": _variant(14.0, 4.0, 3.5, 1.0),
        "shaped": _variant(14.0, 5.0, 0.0, 1.0),
        "finetune-human": _variant(14.5, 3.75, 1.5, 0.9),
        "finetune-amuled": _variant(14.25, 4.5, 1.0, 1.0),
    }}  # fmt: skip
    (tmp_path / "results.json").write_text(json.dumps(results))
    (tmp_path / "report.md").write_text("# title\n\n## What AMULED did\n\ntext\n")
    scenario = load_scenario("findmilk-demo")
    budget = (scenario.task.name, scenario.base.total_steps, scenario.finetune.iterations)
    put_summary(tmp_path, *budget, None)
    put_summary(tmp_path, *budget, None)  # a re-run replaces the section, never adds a second
    lines = (tmp_path / "report.md").read_text().splitlines()
    assert lines[:3] == ["# title", "", SUMMARY_HEADING]
    assert lines.count(SUMMARY_HEADING) == 1 and "## What AMULED did" in lines
    assert f"{scenario.finetune.iterations:,} fine-tuning iterations (the paper: 1,000)" in lines[4]
    assert "start from this run's own base" in lines[4]
    # the paper's rows (docs/reproduction.md), ours as mean ± half-width, greedy milk share
    assert lines[6:10] == [
        "- **base** (`base`): 14.00 ± 0.25 / 4.00 ± 0.50 / 3.50 ± 0.12; the paper 14 / 4 / 3.8; "
        "reaches the milk in 100% of greedy episodes.",
        "- **base + shaping** (`shaped`): 14.00 ± 0.25 / 5.00 ± 0.50 / 0.00 ± 0.12; the paper "
        "14 / 5 / 0; reaches the milk in 100% of greedy episodes.",
        '- **"human" feedback** (`finetune-human`): 14.50 ± 0.25 / 3.75 ± 0.50 / 1.50 ± 0.12; '
        "the paper 14.9 / 3 / 1.5; reaches the milk in 90% of greedy episodes.",
        "- **AMULED** (`finetune-amuled`): 14.25 ± 0.25 / 4.50 ± 0.50 / 1.00 ± 0.12; the paper "
        "14.2 / 4.9 / 0.6; reaches the milk in 100% of greedy episodes.",
    ]


def test_demo_without_the_authors_base_offline_says_so_and_goes_on_from_its_own(
    tmp_path: Path, monkeypatch, capsys, recordings_dir
) -> None:
    """The recording is there, the authors' base is not (runs/authors/findmilk/base)."""
    monkeypatch.setenv("AMULED_RECORDINGS", str(recordings_dir))
    monkeypatch.setenv("AMULED_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    code = main(["demo", "--offline", "--host", "http://127.0.0.1:1", "--run-dir", "demo"])
    err = capsys.readouterr().err
    assert code == 1  # it went on, to the server that is not there
    said = next(line for line in err.splitlines() if "authors' published one" in line)
    assert said.startswith("[demo] the fine-tunes start from this run's own base")
    assert "published findmilk base policy is not in runs/authors/findmilk/base" in said
    assert "run without it to fetch 43 kB" in said  # 42,882 bytes
    assert "'amuled import authors PATH --only policies'" in said
    assert not (tmp_path / "demo").exists() and not (tmp_path / "runs").exists()


def test_a_warm_up_cut_short_by_the_servers_stop_is_said_plainly() -> None:
    """A second demo stops its server while the warm-up is still in flight: no raw error."""
    import socket

    from amuled_ma.commands._demo_live import start_warmup

    listener = socket.create_server(("127.0.0.1", 0))  # accepts, never answers
    host = f"http://127.0.0.1:{listener.getsockname()[1]}"
    scenario = demo_scenario("findmilk", model=TINY_MODEL, host=host, private=True)
    warmup = start_warmup(host, TINY_MODEL, scenario.task.name, scenario.feedback, scenario.resolve)
    assert warmup is not None
    warmup.join(0.2)
    assert warmup.is_alive()
    warmup.cut = warmup.is_alive()
    listener.close()  # as the server's stop: the request fails
    warmup.join(5.0)
    line = warmup.describe()
    assert line.startswith("prefix warm-up: still running when the demo stopped its server")
    assert "Error" not in line and warmup.error is not None  # the failure is kept, not shown


def test_the_authors_base_is_the_base_row_when_the_fine_tunes_start_from_it(
    tmp_path: Path, monkeypatch
) -> None:
    """With ``runs/authors/findmilk/base`` there, its own evaluation is the base row.

    Its numbers are those ``amuled evaluate`` gives the same policy in a run folder of its
    own (same episodes and seed); the run's own base follows, named as such.
    """
    import json
    import shutil

    from amuled_ma.commands.demo import SUMMARY_HEADING, evaluate_folder, put_summary

    monkeypatch.chdir(tmp_path)
    imported = tmp_path / "runs" / "authors" / "findmilk"
    tiny = ["--set", "base.total_steps=512", "--set", "base.num_envs=16",
            "--set", "base.num_steps_per_env=16", "--set", "output.tensorboard=false",
            "--no-progress"]  # fmt: skip
    assert main(["train", "findmilk-demo", "--run-dir", str(imported), *tiny]) == 0
    alone = tmp_path / "alone"
    shutil.copytree(imported / "base", alone / "base")
    shutil.copy(imported / "config.json", alone / "config.json")
    assert main(["evaluate", str(alone), "--no-progress"]) == 0
    measured = json.loads((alone / "results.json").read_text())["variants"]["base"]
    cells = " / ".join(
        f"{measured['sampled']['metrics'][m]['mean']:.2f} ± "
        f"{measured['sampled']['metrics'][m]['half_width']:.2f}"
        for m in ("steps_to_milk", "crying_pacified", "sleeping_woken")
    )
    results = {"variants": {"base": _variant(14.0, 4.0, 3.5, 1.0)}}
    (tmp_path / "results.json").write_text(json.dumps(results))
    (tmp_path / "report.md").write_text("# title\n")
    scenario = load_scenario("findmilk-demo")
    start = Path("runs/authors/findmilk/base")
    ev = evaluate_folder(start, scenario.ppo, scenario.task, scenario.evaluation)
    budget = (scenario.task.name, scenario.base.total_steps, scenario.finetune.iterations)
    put_summary(tmp_path, *budget, start, ev)
    lines = (tmp_path / "report.md").read_text().splitlines()
    assert lines[2] == SUMMARY_HEADING
    assert (
        "start from the paper authors' published base policy (`runs/authors/findmilk/base`"
        in lines[4]
    )
    assert lines[6].startswith(
        "- **base** (`base`: the authors' published base the fine-tunes start from): "
        f"{cells}; the paper 14 / 4 / 3.8; reaches the milk in "
    )
    assert lines[7] == (
        f"- **base** (`base`: this run's own base, {scenario.base.total_steps:,} steps, the "
        "shaped policy's twin): 14.00 ± 0.25 / 4.00 ± 0.50 / 3.50 ± 0.12; the paper "
        "14 / 4 / 3.8; reaches the milk in 100% of greedy episodes."
    )
