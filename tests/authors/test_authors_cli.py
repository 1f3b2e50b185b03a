"""``amuled import authors PATH`` on a folder laid out like the authors' checkout."""

import json
import os

import torch
from authors_fakes import (
    CLUSTERS,
    driving_cache,
    fake_checkout,
    findmilk_cache,
    write_pickle,
)

from amuled_ma.cli import main
from amuled_ma.learn.checkpoints import TRAINER_KEYS, read_checkpoint
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.scenario import scenario_from_dict


def run_import(checkout, tmp_path, *extra):
    args = ["import", "authors", str(checkout), "--runs", str(tmp_path / "runs"), *extra]
    return main(args)


def test_import_writes_recordings_and_run_folders(tmp_path, capsys):
    checkout = tmp_path / "moral_agent"
    made = fake_checkout(checkout)
    assert run_import(checkout, tmp_path, "--to", str(tmp_path / "rec")) == 0
    out = capsys.readouterr().out
    names = sorted(p.name for p in (tmp_path / "rec").iterdir())
    assert names == ["driving-gpt-4o-mini.json", "driving-llama-3_1-8b.json",
                     "findmilk-gpt-4o-mini.json"]  # fmt: skip
    # values as pickled
    cache = made["caches"]["models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle"]
    data = json.loads((tmp_path / "rec" / "findmilk-gpt-4o-mini.json").read_text())
    for (key, entry), state in zip(cache.items(), data["states"], strict=True):
        assert state["obs"] == [float(x) for x in key]
        assert state["beliefs"] == {c: entry[c].tolist() for c in CLUSTERS}
        assert state["fused_by_reference"] == [
            float(entry["rewards"][frozenset({str(a)})]) for a in range(4)
        ]
    fused_only = json.loads((tmp_path / "rec" / "driving-gpt-4o-mini.json").read_text())
    assert all(s["beliefs"] is None for s in fused_only["states"])
    assert [s.get("total_conflict", False) for s in fused_only["states"]] == [0, 0, 1, 0]
    # policies: base and the last fine-tune (ppo_100, not ppo_10 or ppo_5)
    run = tmp_path / "runs" / "authors" / "findmilk"
    assert sorted(p.name for p in run.iterdir()) == ["amuled-gpt-4o-mini", "base", "config.json"]
    tuned = read_checkpoint(run / "amuled-gpt-4o-mini" / "model_last.pt", need=TRAINER_KEYS)
    assert tuned["infos"]["authors"]["checkpoint"] == 100
    assert tuned["infos"]["authors"]["file"].endswith("moral_llm_gpt-4o-mini/ppo_100.cleanrl_model")
    config = json.loads((run / "amuled-gpt-4o-mini" / "config.json").read_text())
    assert config["scenario"]["feedback"]["recording"] == "findmilk-gpt-4o-mini"
    scenario = scenario_from_dict({k: v for k, v in config["scenario"].items() if k != "path"})
    actor = load_policy(run / "amuled-gpt-4o-mini" / "model_last.pt", scenario.ppo)
    agent = made["agents"]["models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_100.cleanrl_model"]
    obs = torch.rand(200, 8, generator=torch.Generator().manual_seed(3)) * 8
    with torch.no_grad():
        expected = torch.log_softmax(agent.actor(obs), dim=-1)
        torch.testing.assert_close(action_log_probs(actor, obs), expected, rtol=0, atol=1e-5)
    assert "evaluate with: amuled evaluate" in out and "ppo_100" in out

    # the converted run evaluates
    assert main(["evaluate", str(run), "--episodes", "2", "--no-progress"]) == 0
    results = json.loads((run / "results.json").read_text())
    assert set(results["variants"]) == {"base", "amuled-gpt-4o-mini"}

    # again: nothing changes
    before = (tmp_path / "rec" / "findmilk-gpt-4o-mini.json").stat().st_mtime_ns
    assert run_import(checkout, tmp_path, "--to", str(tmp_path / "rec")) == 0
    assert (tmp_path / "rec" / "findmilk-gpt-4o-mini.json").stat().st_mtime_ns == before
    assert capsys.readouterr().out.count("  = ") == 5


def test_other_content_is_not_overwritten_without_force(tmp_path, capsys):
    checkout = tmp_path / "moral_agent"
    fake_checkout(checkout)
    rec = tmp_path / "rec"
    rec.mkdir()
    mine = rec / "findmilk-gpt-4o-mini.json"
    mine.write_text("{}")
    assert run_import(checkout, tmp_path, "--to", str(rec)) == 1
    err = capsys.readouterr().err
    assert str(mine) in err and "--force" in err and "nothing was written" in err
    assert sorted(p.name for p in rec.iterdir()) == ["findmilk-gpt-4o-mini.json"]
    assert not (tmp_path / "runs").exists()
    assert run_import(checkout, tmp_path, "--to", str(rec), "--force") == 0
    assert "! findmilk-gpt-4o-mini.json" in capsys.readouterr().out
    assert json.loads(mine.read_text())["model"] == "gpt-4o-mini"


def test_default_folder_is_the_user_data_folder(tmp_path, monkeypatch):
    checkout = tmp_path / "moral_agent"
    write_pickle(checkout / "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle", findmilk_cache())
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "data"))
    assert run_import(checkout, tmp_path) == 0
    assert (tmp_path / "data" / "recordings" / "findmilk-gpt-4o-mini.json").is_file()
    monkeypatch.delenv("AMULED_DATA")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert run_import(checkout, tmp_path, "--only", "recordings") == 0
    assert (tmp_path / "xdg/amuled-ma/recordings/findmilk-gpt-4o-mini.json").is_file()


def test_a_full_and_a_fused_only_cache_of_one_model(tmp_path):
    checkout = tmp_path / "moral_agent"
    fake_checkout(checkout)
    write_pickle(checkout / "models/Driving_42/gpt-4o-mini_llm_cache.pickle", driving_cache())
    assert (
        run_import(checkout, tmp_path, "--to", str(tmp_path / "rec"), "--only", "recordings") == 0
    )
    full = json.loads((tmp_path / "rec" / "driving-gpt-4o-mini.json").read_text())
    assert full["states"][0]["beliefs"] is not None
    fused = json.loads((tmp_path / "rec" / "driving-gpt-4o-mini-fused-only.json").read_text())
    assert fused["states"][0]["beliefs"] is None
    assert not (tmp_path / "runs").exists()


def test_malicious_cache_refused_nothing_runs_nothing_written(tmp_path, capsys):
    checkout = tmp_path / "moral_agent"
    fake_checkout(checkout)
    marker = tmp_path / "marker"

    class Exploit:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    cache = findmilk_cache(states=2)
    cache[next(iter(cache))]["virtue"] = Exploit()
    evil = write_pickle(checkout / "models/FindMilk-v4_42/mistral-nemo_llm_cache.pickle", cache)
    assert run_import(checkout, tmp_path, "--to", str(tmp_path / "rec")) == 1
    err = capsys.readouterr().err
    assert str(evil) in err and "posix.system" in err
    assert not marker.exists()
    assert not (tmp_path / "rec").exists() and not (tmp_path / "runs").exists()


def test_a_folder_without_the_authors_files(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert run_import(tmp_path / "empty", tmp_path) == 1
    err = capsys.readouterr().err
    assert "none of the authors' files found" in err and "temetski/moral_agent" in err
    assert run_import(tmp_path / "missing", tmp_path) == 1
    assert "not a folder" in capsys.readouterr().err
