"""Editing a cluster's text and resuming is refused like a changed recording."""

from __future__ import annotations

import hashlib
import json

import pytest
from job_settings import job_of, settings, train_variant

from amuled_ma.clusters import default_clusters_dir
from amuled_ma.errors import AmuledError
from amuled_ma.experiments.run_folder import training_differences
from amuled_ma.experiments.training_settings import training_config
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

TINY = {
    "base": {"total_steps": 1024, "num_envs": 16, "num_steps_per_env": 16},
    "finetune": {"iterations": 2, "num_envs": 4, "num_steps_per_env": 8},
    "output": {"tensorboard": False},
    "feedback": {"source": "rules"},
}


def tiny(clusters_dir):
    scenario = load_scenario("findmilk")
    for section, values in TINY.items():
        scenario = scenario.replace(section, **values)
    # the user's care asked by name: the rule answers (its text is still its prompt's)
    care = {"care": {"source": "rules"}}
    return scenario.replace("feedback", clusters_dirs=[str(clusters_dir)], agents=care)


def test_resume_refuses_an_edited_cluster_file(tmp_path):
    folder = tmp_path / "clusters"
    folder.mkdir()
    care = folder / "care.toml"
    care.write_text((default_clusters_dir() / "care.toml").read_text())
    sc = tiny(folder)
    config = settings(sc, "finetune:amuled")
    old = hashlib.sha256(care.read_bytes()).hexdigest()
    assert config["inputs"]["cluster_sha256[care]"] == old
    assert set(config["inputs"]) >= {f"cluster_sha256[{c}]" for c in sc.feedback.clusters}
    assert "inputs" not in settings(sc, "base")  # no panel, no clusters
    # the hashes come from the job's panel plan: settings without it are refused
    with pytest.raises(ValueError, match="panel plan"):
        training_config(job_of(sc, Variant.finetune("amuled")))

    run_dir = tmp_path / "run"
    train_variant(sc, run_dir, Variant("base"))
    train_variant(sc, run_dir, Variant.finetune("amuled"))
    tune = run_dir / "finetune-amuled"
    saved = json.loads((tune / "config.json").read_text())["training"]["inputs"]
    assert saved["cluster_sha256[care]"] == old

    care.write_text(care.read_text().replace("Care Ethics", "Care  Ethics"))
    new = hashlib.sha256(care.read_bytes()).hexdigest()
    assert new != old
    with pytest.raises(AmuledError) as err:
        longer = sc.replace("finetune", iterations=3)
        train_variant(longer, run_dir, Variant.finetune("amuled"), resume=True)
    text = str(err.value)
    assert f"inputs.cluster_sha256[care]: {old!r} -> {new!r}" in text and "--force" in text


def test_a_folder_saved_before_cluster_hashes_still_resumes(tmp_path):
    """A record with a recording hash but no cluster hashes (older version) is accepted."""
    folder = tmp_path / "clusters"
    folder.mkdir()
    sc = tiny(folder)
    training = settings(sc, "finetune:amuled")
    old = {k: v for k, v in training.items() if k != "inputs"}
    old["inputs"] = {"recording_sha256": None}
    out = tmp_path / "finetune-amuled"
    out.mkdir()
    current = {**training, "inputs": {**training["inputs"], "recording_sha256": None}}
    (out / "config.json").write_text(json.dumps({"training": old}))
    assert training_differences(out, current) == []  # no refusal
