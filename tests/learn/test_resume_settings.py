"""A resume or a skip never passes off a variant trained with other settings."""

from __future__ import annotations

import json

import pytest
from job_settings import settings, train_variant

from amuled_ma.errors import AmuledError
from amuled_ma.experiments.jobs import run_jobs
from amuled_ma.experiments.plans import plan_run
from amuled_ma.learn.checkpoints import checkpoint_infos
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

TINY = {
    "base": {"total_steps": 1024, "num_envs": 16, "num_steps_per_env": 16},  # 4 iterations
    "finetune": {"iterations": 3, "num_envs": 4, "num_steps_per_env": 8},
    "output": {"tensorboard": False},
    "feedback": {"source": "rules"},
}


def tiny(**finetune):
    scenario = load_scenario("findmilk")
    for section, values in TINY.items():
        scenario = scenario.replace(section, **values)
    return scenario.replace("finetune", **finetune) if finetune else scenario


def test_training_config_holds_what_a_variant_learns():
    sc = tiny()
    base = settings(sc, "base")
    assert base["seed"] == 1 and base["iterations"] == 1024 // (16 * 16)
    assert set(base) == {"variant", "seed", "iterations", "task", "ppo", "base"}
    # a fine-tuning or feedback setting does not touch the base ...
    assert settings(sc.replace("finetune", lambda_kl=0.5), "base") == base
    assert settings(sc.replace("feedback", model="other"), "base") == base
    # ... a PPO setting and the seed do
    assert settings(sc.replace("ppo", learning_rate=1e-3), "base") != base
    assert settings(sc, "base", seed=2)["seed"] == 2

    amuled = settings(sc, "finetune:amuled")
    assert amuled["iterations"] == 3 and amuled["finetune"]["lambda_kl"] == 2.5
    assert settings(sc.replace("finetune", lambda_kl=0.5), "finetune:amuled") != amuled
    assert settings(sc.replace("feedback", model="other"), "finetune:amuled") != amuled
    # service keys, checkpoint cadence, the recording's folder and the length are not settings
    same = sc.replace("feedback", host="http://elsewhere:1", concurrency=1, timeout_s=5.0)
    same = same.replace("finetune", save_interval=7, iterations=9)
    moved = str(sc.recording_path().parent / "elsewhere" / sc.recording_path().name)
    same = same.replace("feedback", recording=moved)
    other = settings(same, "finetune:amuled")
    assert other.pop("iterations") == 9 and {**other, "iterations": 3} == amuled
    # the rule-based human feedback reads no [feedback] key
    human = settings(sc, "finetune:human")
    assert "feedback" not in human
    assert settings(sc.replace("feedback", model="other"), "finetune:human") == human


def _checkpoint_bytes(path):
    return (path / "model_last.pt").read_bytes()


def test_resume_refuses_other_settings_skips_same_and_lengthens(tmp_path):
    run_dir = tmp_path / "run"
    run_jobs(plan_run(tiny(), run_dir, [1]), describe=str)
    tune = run_dir / "finetune-amuled"
    saved = json.loads((tune / "config.json").read_text())["training"]
    assert saved["finetune"]["lambda_kl"] == 2.5 and saved["iterations"] == 3
    before = _checkpoint_bytes(tune)

    # other settings: refused before anything trains, naming folder, key, values, options
    with pytest.raises(AmuledError) as err:
        run_jobs(plan_run(tiny(lambda_kl=0.5), run_dir, [1], resume=True), describe=str)
    text = str(err.value)  # both fine-tunes, each with its folder, key and values
    assert text.startswith("2 of 4 jobs cannot start, nothing was trained")
    for folder in (run_dir / "finetune-human", tune):
        assert f"{folder} was trained with other settings" in text
    assert text.count("finetune.lambda_kl: 2.5 -> 0.5") == 2
    assert "--force" in text and "--run-dir" in text
    assert _checkpoint_bytes(tune) == before

    # the same settings: every finished variant is skipped
    outcome = run_jobs(plan_run(tiny(), run_dir, [1], resume=True), describe=str)
    assert [r.skipped for r in outcome.results] == [True] * 4
    assert _checkpoint_bytes(tune) == before

    # more iterations: the finished fine-tunes continue from 3 to 5, the bases are skipped
    outcome = run_jobs(plan_run(tiny(iterations=5), run_dir, [1], resume=True), describe=str)
    assert [r.skipped for r in outcome.results] == [True, True, False, False]
    assert checkpoint_infos(tune / "model_last.pt")["iteration"] == 5
    curve = json.loads((tune / "curve.json").read_text())
    assert [row["iteration"] for row in curve] == [1, 2, 3, 4, 5]

    # fewer iterations than the checkpoint holds: refused
    with pytest.raises(AmuledError, match="iteration 5, past the 2 iterations"):
        run_jobs(plan_run(tiny(iterations=2), run_dir, [1], resume=True), describe=str)

    # --force retrains with the new settings and records them
    train_variant(tiny(lambda_kl=0.5), run_dir, Variant.finetune("amuled"), force=True)
    assert (
        json.loads((tune / "config.json").read_text())["training"]["finetune"]["lambda_kl"] == 0.5
    )
    assert checkpoint_infos(tune / "model_last.pt")["iteration"] == 3


def test_unreadable_saved_settings_name_the_file(tmp_path):
    from amuled_ma.experiments.run_folder import finished_with

    run_dir = tmp_path / "run"
    sc = tiny()
    train_variant(sc, run_dir, Variant("base"))
    config = run_dir / "base" / "config.json"
    assert finished_with(run_dir / "base", settings(sc, "base"))
    config.write_text("{not json")
    with pytest.raises(AmuledError, match=f"{config}: not a readable config .*--force"):
        train_variant(sc, run_dir, Variant("base"), resume=True)
    assert not finished_with(run_dir / "base", settings(sc, "base"))


def test_resume_refuses_a_recording_replaced_under_the_same_name(tmp_path, recordings_dir):
    """Same file name, new content: the resume names the recording's changed SHA-256."""
    import hashlib

    recording = tmp_path / "findmilk-gpt-4o-mini.json"
    data = json.loads((recordings_dir / recording.name).read_text())
    recording.write_text(json.dumps(data))
    sc = tiny().replace("feedback", source="replay", recording=str(recording))
    run_dir = tmp_path / "run"
    train_variant(sc, run_dir, Variant("base"))
    train_variant(sc, run_dir, Variant.finetune("amuled"))
    tune = run_dir / "finetune-amuled"
    old = hashlib.sha256(recording.read_bytes()).hexdigest()
    inputs = json.loads((tune / "config.json").read_text())["training"]["inputs"]
    assert inputs["recording_sha256"] == old  # beside the cluster files' hashes
    before = _checkpoint_bytes(tune)

    # another LLM's answer for the first state, same file name
    data["states"][0]["beliefs"]["care"] = [0.25, 0.25, 0.25, 0.25]
    recording.write_text(json.dumps(data))
    new = hashlib.sha256(recording.read_bytes()).hexdigest()
    longer = sc.replace("finetune", iterations=5)
    with pytest.raises(AmuledError) as err:
        train_variant(longer, run_dir, Variant.finetune("amuled"), resume=True)
    assert f"inputs.recording_sha256: {old!r} -> {new!r}" in str(err.value)
    assert "--force" in str(err.value)
    assert _checkpoint_bytes(tune) == before

    # the original content back: the resume continues
    data["states"][0]["beliefs"]["care"] = [0.1, 0.0, 0.0, 0.9]
    recording.write_text(json.dumps(data))
    train_variant(longer, run_dir, Variant.finetune("amuled"), resume=True)
    assert checkpoint_infos(tune / "model_last.pt")["iteration"] == 5
