"""The panel plan of every shipped scenario and example, and the preflight through the CLI.

Expected members and sources are read from the TOML files and the recordings themselves
(``tomllib``, ``json``), not from the code under test.
"""

from __future__ import annotations

import json
import time
import tomllib
from pathlib import Path

import pytest

from amuled_ma.cli import main
from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.scenario import PAPER_CLUSTERS, load_scenario

try:  # the shared real-server fixtures
    from ollama_server_fixture import ollama_host, ollama_model
except ImportError:  # pragma: no cover - only without tests/ on sys.path
    ollama_host = ollama_model = None

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted((ROOT / "scenarios").glob("*.toml")) + sorted((ROOT / "examples").glob("*.toml"))
WELFARE = (ROOT / "examples" / "my_clusters" / "animal_welfare.toml").read_text()


def _fused_only(path: Path) -> bool:
    """Whether a recording holds no per-agent belief at all (read with json, not our code)."""
    states = json.loads(path.read_text())["states"]
    return all(not s.get("beliefs") and s.get("moral_agent") is None for s in states)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_the_plan_of_every_shipped_scenario_and_example(path, recordings_dir):
    data = tomllib.loads(path.read_text())
    feedback = data.get("feedback", {})
    clusters = feedback.get("clusters", list(PAPER_CLUSTERS))
    tables = feedback.get("agents", {})
    default = feedback.get("source", "replay")
    recording = feedback.get("recording", "")
    scenario = load_scenario(path)
    plan = plan_panel("amuled", scenario)
    assert plan.agents == clusters
    assert plan.rule == feedback.get("fusion", "bjs-dst")
    fused = (
        default == "replay"
        and not tables
        and _fused_only(recordings_dir / f"{Path(recording).stem}.json")
    )
    assert (plan.fused_recording is not None) is fused
    for agent in plan.agents:
        source = plan.source_of(agent)
        expected = tables.get(agent, {}).get("source", default)
        assert (source.kind if source is not None else "replay") == expected, agent
        if agent in tables:
            assert source is not None
            assert source.label.startswith(f"[feedback.agents.{agent}]")
    if default == "replay":
        replayed = [
            plan.fused_recording or Path(s.options["paths"])
            for s in [plan.source_of(a) for a in plan.agents]
            if s is None or s.kind == "replay"
        ]
        assert replayed[0].name == f"{Path(recording).stem}.json"


def _scenario(tmp_path: Path, feedback: str) -> Path:
    """A FindMilk scenario with a tiny fine-tune and ``feedback`` as its [feedback] body."""
    path = tmp_path / "s.toml"
    path.write_text(
        'name = "s"\n[task]\nname = "findmilk"\n[finetune]\niterations = 1\n'
        f"[output]\ntensorboard = false\n[feedback]\n{feedback}"
    )
    return path


def _stops_before_training(tmp_path, capsys, path: Path, *more: str) -> str:
    """Run ``amuled finetune``: it fails in under 10 s, with one line, leaving no folder."""
    run_dir = tmp_path / "run"
    # CPU seconds of this process: the 10 s budget, whatever else loads the machine (its
    # first call includes importing torch for the trainer)
    start = time.process_time()
    code = main(["finetune", str(path), "--run-dir", str(run_dir), "--no-progress", *more])
    elapsed = time.process_time() - start
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert elapsed < 10, elapsed
    assert len(err.splitlines()) == 1, err
    assert not run_dir.exists()  # not even a folder holding only .amuled.lock
    return err


def test_a_cluster_absent_from_the_recording_stops_the_command(tmp_path, capsys, recordings_dir):
    clusters = tmp_path / "clusters"
    clusters.mkdir()
    (clusters / "animal_welfare.toml").write_text(WELFARE)
    panel = json.dumps([*PAPER_CLUSTERS, "animal_welfare"])
    path = _scenario(
        tmp_path,
        f'source = "replay"\nrecording = "{recordings_dir / "findmilk-gpt-4o-mini.json"}"\n'
        f'clusters = {panel}\nclusters_dirs = ["{clusters}"]\n',
    )
    err = _stops_before_training(tmp_path, capsys, path)
    assert 'cluster "animal_welfare" is not in recording findmilk-gpt-4o-mini' in err
    assert "(it holds: consequentialist, deontologist, virtue, care, social justice)" in err
    # the fix in the form a command line takes, short; the other sources are in the docs
    assert "--set 'feedback.agents={animal_welfare={source=\"terminal\"}}'" in err
    assert "(524 answers, or 20 with --set feedback.distill.enabled=true)" in err
    assert "drop it from feedback.clusters" in err
    assert "docs/clusters.md#a-cluster-no-recording-holds" in err
    assert "[feedback.agents." not in err  # no TOML table a command line cannot take
    fix = err[err.index("answer it") :]
    assert len(fix) < 300, len(fix)  # the ways were 650 characters of TOML tables


def test_a_recording_of_another_task_stops_the_command(tmp_path, capsys, recordings_dir):
    recording = recordings_dir / "driving-llama-3_1-70b.json"
    path = _scenario(tmp_path, f'source = "replay"\nrecording = "{recording}"\n')
    err = _stops_before_training(tmp_path, capsys, path)
    assert "no recording of task 'findmilk': driving-llama-3_1-70b (task 'Driving')" in err


def test_a_plug_in_that_does_not_load_stops_the_command(tmp_path, capsys):
    path = _scenario(
        tmp_path,
        'source = "rules"\n[feedback.agents.care]\nsource = "entry-point"\n'
        'name = "no_such_module_xyz:Agent"\n',
    )
    err = _stops_before_training(tmp_path, capsys, path)
    assert "[feedback.agents.care] (source 'entry-point', name 'no_such_module_xyz:Agent')" in err
    assert "--allow-plugin no_such_module_xyz:Agent" in err  # a file alone imports nothing
    assert "\n" not in err.strip()


def test_no_ollama_server_stops_the_command(tmp_path, capsys):
    path = _scenario(
        tmp_path,
        'source = "rules"\n[feedback.agents.care]\nsource = "ollama"\nmodel = "m"\n'
        'host = "http://127.0.0.1:9"\ncheck_timeout_s = 2.0\n',
    )
    err = _stops_before_training(tmp_path, capsys, path)
    assert "[feedback.agents.care] (source 'ollama', model 'm')" in err
    assert "no Ollama server answers at http://127.0.0.1:9" in err


@pytest.mark.ollama
def test_an_ollama_model_that_is_not_there_stops_the_command(tmp_path, capsys, ollama_host):
    path = _scenario(
        tmp_path,
        'source = "rules"\n[feedback.agents.care]\nsource = "ollama"\n'
        f'model = "no-such-model-xyz"\nhost = "{ollama_host}"\n',
    )
    err = _stops_before_training(tmp_path, capsys, path)
    assert "[feedback.agents.care] (source 'ollama', model 'no-such-model-xyz')" in err
    assert "model 'no-such-model-xyz' is not on the Ollama server" in err


def test_the_ollama_spec_declares_every_ollama_source_keyword():
    import inspect

    from amuled_ma.beliefs.sources.ollama import OllamaSource
    from amuled_ma.scenario import OllamaSpec

    keywords = {
        name: p.default
        for name, p in inspect.signature(OllamaSource).parameters.items()
        if name not in ("transport", "fallback")  # not TOML values
    }
    fields = {k: v.default for k, v in OllamaSpec.model_fields.items() if k != "source"}
    # the table's defaults are the source's ("" and [] stand for None: [feedback]'s value)
    assert set(fields) == set(keywords)
    for name, default in keywords.items():
        if default is not None and name not in ("model", "options"):
            assert fields[name] == default, name


def test_a_built_feedback_names_its_plan_and_a_hand_built_one_none():
    from amuled_ma.deliberation.build import build_feedback
    from amuled_ma.deliberation.feedback_base import CallableFeedback

    scenario = load_scenario(ROOT / "scenarios" / "findmilk.toml")
    plan = plan_panel("human:rules", scenario)
    feedback = build_feedback(plan, store=None)
    assert feedback.plan is plan
    assert feedback.plan.variant == "human:rules"
    assert CallableFeedback(lambda obs: obs, name="by hand").plan is None
