"""``amuled run``, ``ablate`` and ``demo`` are one library call: :func:`run_pipeline`.

The commands only parse their arguments into a :class:`PipelineRequest` and print the
outcome; the real pipeline's runs are in ``tests/test_cli_run.py``. Its input checks run
before any folder is made.
"""

from __future__ import annotations

import ast
import time
from pathlib import Path

import pytest
from tiny_cli import RULES, TINY

from amuled_ma.cli import main
from amuled_ma.evaluate.results import Results
from amuled_ma.experiments import pipeline
from amuled_ma.experiments.jobs import JobsOutcome, RayTarget

COMMANDS = Path(__file__).resolve().parents[2] / "amuled_ma" / "commands"


@pytest.fixture
def requests(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list:
    """Replace :func:`run_pipeline` by a recorder; it returns an empty outcome."""
    seen: list = []

    def fake(request: pipeline.PipelineRequest, *, say=pipeline.say_line):
        seen.append(request)
        report = tmp_path / "report.md"
        return pipeline.PipelineOutcome(
            out_dir=tmp_path,
            variants=("base",),
            seeds=(request.seed or 1,),
            training=JobsOutcome(),
            results=Results(),
            report=report,
            wall_s=0.0,
        )

    monkeypatch.setattr(pipeline, "run_pipeline", fake)
    return seen


def test_run_reaches_the_pipeline_with_its_arguments(requests, tmp_path, capsys):
    run_dir = tmp_path / "run"
    argv = ["run", "findmilk", "--run-dir", str(run_dir), "--seed", "7", "--seeds", "2"]
    argv += ["--episodes", "3", "--jobs", "2", "--ray", "--resume", *TINY]
    assert main(argv) == 0
    (request,) = requests
    assert request.ablation is None and request.run_dir == run_dir
    assert (request.seed, request.seeds, request.episodes, request.jobs) == (7, 2, 3, 2)
    assert request.ray == RayTarget(None, None) and request.resume and not request.force
    assert request.scenario.finetune.iterations == 3  # the --set of TINY
    assert request.hint.startswith(f"amuled run findmilk --run-dir {run_dir} --set")
    assert "variants x 1 seed(s) done" in capsys.readouterr().out


def test_ablate_reaches_the_pipeline_with_its_ablation(requests, tmp_path, capsys):
    argv = ["ablate", "findmilk", "--what", "kl", "--run-dir", str(tmp_path), *TINY]
    assert main(argv) == 0
    (request,) = requests
    assert request.ablation == "kl" and request.ray is None and request.jobs == 0
    assert "--what kl" in request.hint
    assert "ablate findmilk --what kl: 1 variants" in capsys.readouterr().out


def test_demo_reaches_the_pipeline_with_its_scenario_file(requests, tmp_path, monkeypatch, capsys):
    from amuled_ma.commands import demo
    from amuled_ma.servers import hosts

    monkeypatch.setattr(hosts, "preflight", lambda host, model: None)
    monkeypatch.setattr(demo, "write_demo_view", lambda run_dir: None)
    run_dir = tmp_path / "demo"
    argv = ["demo", "--host", "http://127.0.0.1:9", "--run-dir", str(run_dir), "--no-progress"]
    assert main([*argv, "--set", "evaluation.episodes=2"]) == 0
    (request,) = requests
    assert request.scenario.name == "findmilk-demo" and request.resume
    assert request.scenario.feedback.host == "http://127.0.0.1:9"
    assert request.scenario.feedback.concurrency == 2  # a server the demo did not start
    assert request.scenario.evaluation.episodes == 2
    assert request.hint == (
        f"amuled demo --task findmilk --run-dir {run_dir} --host http://127.0.0.1:9 "
        "--set evaluation.episodes=2"
    )
    out = capsys.readouterr().out.splitlines()  # the summary of amuled run, as before
    assert out[-2] == "  greedy: " and out[-1].startswith("run findmilk-demo: 1 variants x 1 seed")


def test_no_command_calls_the_command_line():
    """A command reaches the pipeline as a library, never through ``cli.main`` and an argv."""
    for path in sorted(COMMANDS.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "amuled_ma.cli":
                assert "main" not in {alias.name for alias in node.names}, path.name
            if isinstance(node, ast.Attribute) and node.attr == "main":
                assert not (isinstance(node.value, ast.Name) and node.value.id == "cli"), path


def test_a_missing_recording_stops_before_any_folder_is_made(tmp_path, capsys):
    run_dir = tmp_path / "run"
    missing = tmp_path / "nowhere.json"
    argv = ["run", "findmilk", "--run-dir", str(run_dir), "--jobs", "1", *TINY]
    start = time.monotonic()
    assert main([*argv, "--set", f'feedback.recording="{missing}"']) == 1
    assert time.monotonic() - start < 10.0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(missing) in err
    assert not run_dir.exists()


def test_the_inputs_of_several_jobs_are_named_once_each(tmp_path):
    """Two seeds' AMULED fine-tunes lack the same recording: one line, said once."""
    from amuled_ma.errors import AmuledError
    from amuled_ma.experiments.plans import plan_jobs, plan_run
    from amuled_ma.scenario import load_scenario

    missing = tmp_path / "nowhere.json"
    scenario = load_scenario("findmilk").replace("feedback", recording=str(missing))
    jobs = plan_run(scenario, tmp_path / "run", [1, 2])
    with pytest.raises(AmuledError) as info:
        plan_jobs(jobs)
    assert str(missing) in str(info.value) and "\n" not in str(info.value)
    rules = scenario.replace("feedback", source="rules")
    planned = plan_jobs(plan_run(rules, tmp_path / "run", [1, 2]))  # nothing missing
    assert {job.action for job in planned} == {"new"}
    # each fine-tune carries its panel plan, settings and base, planned once
    tunes = [job for job in planned if job.variant.finetuning]
    assert [job.base_checkpoint for job in tunes] == [
        tmp_path / "run" / base / "model_last.pt"
        for base in ("base", "base", "base.seed2", "base.seed2")
    ]
    assert all(job.panel is not None and job.settings["seed"] == job.seed for job in tunes)
    assert not (tmp_path / "run").exists()


def test_a_request_refuses_an_unknown_ablation_and_a_base_with_an_ablation(tmp_path):
    from amuled_ma.errors import AmuledError, ScenarioError
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario("findmilk")
    with pytest.raises(ScenarioError, match="unknown ablation 'size'; expected one of"):
        pipeline.PipelineRequest(scenario, tmp_path, ablation="size")
    with pytest.raises(AmuledError, match="amuled run --base"):
        pipeline.PipelineRequest(scenario, tmp_path, ablation="kl", base=tmp_path / "base")


def test_rules_run_through_the_library(tmp_path):
    """The library alone, without the command line: the four variants, report written."""
    from amuled_ma.scenario import load_scenario
    from amuled_ma.scenario.overrides import parse_set

    scenario = load_scenario("findmilk")
    sets = [arg for arg in [*TINY, *RULES] if arg not in ("--set", "--no-progress")]
    for text in sets:
        section, name, value = parse_set(text)
        scenario = scenario.replace(section, **{name: value})
    lines: list[str] = []
    request = pipeline.PipelineRequest(
        scenario, tmp_path / "run", episodes=2, jobs=1, progress=False, hint="amuled run x"
    )
    outcome = pipeline.run_pipeline(request, say=lines.append)
    assert outcome.report == tmp_path / "run" / "report.md" and outcome.report.is_file()
    assert outcome.variants == ("base", "shaped", "finetune:human", "finetune:amuled")
    assert outcome.seeds == (1,) and len(outcome.training.results) == 4
    assert set(outcome.results.variants) == {
        "base",
        "shaped",
        "finetune-human",
        "finetune-amuled",
    }
    assert lines[0] == f"run findmilk -> {tmp_path / 'run'}"
    assert lines[1] == "  4 training jobs, 1 at a time"
    assert lines[2].startswith("  training done in ")
