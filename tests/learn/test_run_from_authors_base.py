"""``amuled run --recipe authors`` fine-tunes from the authors' imported base when it is there."""

import json

from amuled_ma.cli import main

TINY = [
    "--set", "base.total_steps=2048", "--set", "finetune.iterations=2",
    "--set", "feedback.max_abstention=1.0", "--set", "output.tensorboard=false",
    "--no-progress",
]  # fmt: skip


def test_run_with_the_authors_recipe_anchors_to_the_imported_base(tmp_path, capsys):
    runs = tmp_path / "runs"
    imported = runs / "authors" / "findmilk"  # where 'amuled import authors' puts it
    assert (
        main(["train", "findmilk", "--recipe", "authors", "--run-dir", str(imported), *TINY]) == 0
    )
    run_dir = runs / "findmilk-authors"
    argv = ["run", "findmilk", "--recipe", "authors", "--run-dir", str(run_dir), "--episodes",
            "2", "--jobs", "1", "--set", f'output.runs_dir="{runs}"', *TINY]  # fmt: skip
    capsys.readouterr()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"fine-tunes start from the authors' imported base {imported / 'base'}" in out
    for tune in ("finetune-amuled", "finetune-human"):
        config = json.loads((run_dir / tune / "config.json").read_text())
        assert config["base_checkpoint"] == str(imported / "base" / "model_last.pt")
    results = json.loads((run_dir / "results.json").read_text())
    panel = results["variants"]["finetune-amuled"]["panel"]
    assert panel["recipe"] == "authors" and panel["base_checkpoint"].startswith(str(imported))
    assert "authors/findmilk/base" in (run_dir / "report.md").read_text()
    # without the imported base: the run's own, said so
    other = tmp_path / "elsewhere"
    argv = ["run", "findmilk", "--recipe", "authors", "--run-dir", str(other), "--episodes", "2",
            "--jobs", "1", "--set", f'output.runs_dir="{tmp_path / "empty"}"', *TINY]  # fmt: skip
    assert main(argv) == 0
    assert "fine-tunes start from this run's own bases" in capsys.readouterr().out
    config = json.loads((other / "finetune-amuled" / "config.json").read_text())
    assert config["base_checkpoint"] == str(other / "base" / "model_last.pt")
