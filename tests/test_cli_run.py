"""End-to-end: amuled run / train / finetune / evaluate / ablate on tiny budgets."""

import json

import pytest
from tiny_cli import RULES, TINY

from amuled_ma.cli import main


def test_run_writes_run_dir_report_and_resumes(tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "run"
    args = ["run", "findmilk", "--run-dir", str(run_dir), "--episodes", "3", *TINY, *RULES]
    # in this process, every job alone (a Trainer), where the patched iteration below applies
    args += ["--jobs", "1", "--no-population"]

    # Ctrl-C in the middle of the first fine-tune: checkpoint + resume command
    from amuled_ma.learn import population as population_mod

    original = population_mod.PopulationTrainer.iterate
    calls = {"n": 0}

    def interrupt_second_finetune_iteration(self):
        if self.finetuning:
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(
        population_mod.PopulationTrainer, "iterate", interrupt_second_finetune_iteration
    )
    assert main(args) == 130
    out = capsys.readouterr().err
    assert "resume with: amuled run findmilk" in out and "--resume" in out
    assert (run_dir / "finetune-human" / "model_last.pt").is_file()

    # without --resume: a clear error naming --resume
    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", original)
    assert main(args) == 1
    assert "--resume" in capsys.readouterr().err

    assert main([*args, "--resume"]) == 0
    out = capsys.readouterr().out
    assert "base: already trained" in out and "finetune:amuled" in out
    assert "report" in out.splitlines()[-1]

    for variant in ("base", "shaped", "finetune-human", "finetune-amuled"):
        assert (run_dir / variant / "model_last.pt").is_file(), variant
        assert (run_dir / variant / "train_cfg.json").is_file(), variant
    curve = json.loads((run_dir / "finetune-human" / "curve.json").read_text())
    assert [row["iteration"] for row in curve] == [1, 2, 3]
    config = json.loads((run_dir / "config.json").read_text())
    assert config["scenario"]["finetune"]["iterations"] == 3
    assert config["scenario"]["feedback"]["source"] == "rules"
    results = json.loads((run_dir / "results.json").read_text())
    assert set(results["variants"]) == {"base", "shaped", "finetune-human", "finetune-amuled"}
    assert results["variants"]["base"]["greedy"]["metrics"]["steps_to_milk"]["n"] == 3
    report = (run_dir / "report.md").read_text()
    assert "Fused-belief diagnostics" in report and "trajectory_findmilk.png" in report
    assert (run_dir / "trajectory_findmilk.png").is_file()
    assert (run_dir / "results.csv").is_file()

    # resume on a finished run does nothing but re-evaluate
    assert main([*args, "--resume"]) == 0
    assert capsys.readouterr().out.count("already trained") == 4

    # amuled evaluate on the run dir
    assert (
        main(["evaluate", str(run_dir), "--episodes", "2", "--modes", "greedy", "--no-progress"])
        == 0
    )
    assert "report" in capsys.readouterr().out


def test_finetune_without_base_names_the_command(tmp_path, capsys):
    code = main(["finetune", "findmilk", "--run-dir", str(tmp_path), *TINY, *RULES])
    assert code == 1
    err = capsys.readouterr().err
    assert "amuled train" in err and "--variant base" in err


def test_bad_scenario_key_names_file_key_and_type(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[finetune]\nlambda_kl = 'big'\n")
    assert main(["train", str(bad), "--run-dir", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "[finetune].lambda_kl" in err and "float" in err


def test_bad_override(tmp_path, capsys):
    assert main(["train", "findmilk", "--set", "base.numenvs=3", "--run-dir", str(tmp_path)]) == 1
    assert "numenvs" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["train", "finetune", "run", "ablate", "evaluate"])
def test_help(command, capsys):
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    assert "usage: amuled" in capsys.readouterr().out


@pytest.mark.slow
def test_ablate_aggregation_with_replay_two_seeds_in_parallel(tmp_path, capsys, recordings_dir):
    run_dir = tmp_path / "run"
    args = ["ablate", "findmilk", "--what", "aggregation", "--run-dir", str(run_dir)]
    args += [
        "--episodes",
        "2",
        "--seeds",
        "2",
        "--jobs",
        "2",
        *TINY,
        "--set",
        f'feedback.recording="{recordings_dir}/findmilk-gpt-4o-mini.json"',
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "8 variants x 2 seed(s) done" in out and "on 2 worker(s)" in out
    abl = run_dir / "ablate-aggregation"
    rules = ("mean", "max", "vote", "mec", "nash-vote", "variance-vote", "borda")
    for name in (*(f"finetune-agg-{rule}" for rule in rules), "finetune-amuled"):
        for replica in (name, f"{name}.seed2"):
            assert (abl / replica / "model_last.pt").is_file(), replica
    assert (run_dir / "base.seed2" / "model_last.pt").is_file()
    results = json.loads((abl / "results.json").read_text())
    assert "base" in results["variants"] and "base.seed2" not in results["variants"]
    # two seeds: the figure is the mean of the two per-seed means, the interval is over
    # the seeds (t_{0.975,1} = 12.7062, from a t table)
    entry = results["variants"]["finetune-amuled"]["greedy"]
    assert entry["ci_over"] == "seeds" and entry["n_seeds"] == 2
    means = [r["return_env"]["mean"] for r in entry["replicas"].values()]
    stat = entry["metrics"]["return_env"]
    assert stat["n"] == 2 and stat["mean"] == pytest.approx(sum(means) / 2)
    spread = abs(means[0] - means[1]) / 2**0.5  # sample std of two values
    assert stat["half_width"] == pytest.approx(12.7062 * spread / 2**0.5, rel=1e-5)
    assert "| finetune-amuled | 2 |" in (abl / "report.md").read_text()

    # amuled evaluate on the ablation folder finds the base replicas beside it
    argv = ["evaluate", str(abl), "--episodes", "2", "--modes", "greedy", "--no-progress"]
    assert main([*argv, "--variants", "base", "finetune-amuled"]) == 0
    again = json.loads((abl / "results.json").read_text())["variants"]
    assert set(again) == {"base", "finetune-amuled"}
    assert again["base"]["greedy"]["n_seeds"] == 2
    assert again["finetune-amuled"]["greedy"]["n_seeds"] == 2
    fb = results["variants"]["finetune-amuled"]["feedback"]
    assert 0.0 <= fb["miss_rate"] < 0.5 and fb["mean_conflict"] is not None
    assert (abl / "ablation_aggregation.png").is_file()


def test_ablate_after_run_evaluates_the_runs_amuled_finetune_without_retraining(tmp_path, capsys):
    run_dir = tmp_path / "run"
    common = ["findmilk", "--run-dir", str(run_dir), "--episodes", "2", "--jobs", "1"]
    assert main(["run", *common, *TINY, *RULES]) == 0
    capsys.readouterr()
    assert main(["ablate", "--what", "aggregation", *common, *TINY, *RULES]) == 0
    out = capsys.readouterr().out
    assert f"finetune:amuled: already trained ({run_dir / 'finetune-amuled'})" in out
    abl = run_dir / "ablate-aggregation"
    assert not (abl / "finetune-amuled").exists()
    assert json.loads((abl / "config.json").read_text())["shared"] == ["base", "finetune-amuled"]
    results = json.loads((abl / "results.json").read_text())["variants"]
    assert {"base", "finetune-amuled", "finetune-agg-mean"} <= set(results)
    run_results = json.loads((run_dir / "results.json").read_text())["variants"]
    assert results["finetune-amuled"]["greedy"] == run_results["finetune-amuled"]["greedy"]

    # amuled evaluate on the ablation folder takes the same shared folders along
    argv = ["evaluate", str(abl), "--episodes", "2", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 0
    assert "finetune-amuled" in json.loads((abl / "results.json").read_text())["variants"]


def test_a_sweep_in_populations_stops_on_ctrl_c_and_resumes(tmp_path, capsys, monkeypatch):
    """In this process the two fine-tunes train as one population (the default)."""
    from amuled_ma.learn import population as population_mod
    from amuled_ma.learn.checkpoints import checkpoint_infos

    run_dir = tmp_path / "run"
    args = ["run", "findmilk", "--run-dir", str(run_dir), "--episodes", "2", *TINY, *RULES]
    args += ["--jobs", "1"]
    original = population_mod.PopulationTrainer._check_members
    calls = {"n": 0}

    def interrupt_the_second_iteration(self):
        if self.finetuning:
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(
        population_mod.PopulationTrainer, "_check_members", interrupt_the_second_iteration
    )
    assert main(args) == 130
    err = capsys.readouterr().err
    assert err.count("resume with:") == 1, err  # one command for the whole sweep
    assert "Traceback" not in err
    for tune in ("finetune-human", "finetune-amuled"):  # both members kept their work
        infos = checkpoint_infos(run_dir / tune / "model_last.pt")
        assert infos["iteration"] == 2 and not infos["completed"], tune
    monkeypatch.setattr(population_mod.PopulationTrainer, "_check_members", original)
    assert main([*args, "--resume"]) == 0
    for tune in ("finetune-human", "finetune-amuled"):
        curve = json.loads((run_dir / tune / "curve.json").read_text())
        assert [row["iteration"] for row in curve] == [1, 2, 3], tune
