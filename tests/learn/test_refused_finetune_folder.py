"""A fine-tune refused for its base leaves no variant folder behind.

A base trained with ``[ppo].hidden_dims = [64, 64]`` cannot anchor a fine-tune whose
networks are ``[8, 8]``: the refusal is one line, made while planning, so neither the
variant folder nor its record is written (a half-made folder would hold a record that the
next fine-tune of that name is compared against).
"""

from __future__ import annotations

from pathlib import Path

from tiny_cli import RULES, TINY, one_line

from amuled_ma.cli import main


def test_a_base_of_other_networks_is_refused_before_the_variant_folder(tmp_path: Path, capsys):
    run = tmp_path / "run"
    assert main(["train", "findmilk", "--run-dir", str(run), *TINY]) == 0
    before = sorted(p.name for p in run.iterdir())
    capsys.readouterr()
    argv = ["finetune", "findmilk", "--run-dir", str(run), "--name", "narrow", *TINY, *RULES]
    assert main([*argv, "--set", "ppo.hidden_dims=[8, 8]"]) == 1
    line = one_line(capsys.readouterr().err)
    assert line.startswith(
        f"amuled: error: base checkpoint {run / 'base' / 'model_last.pt'}: its networks do not "
        "fit this scenario's ([ppo].hidden_dims = [8, 8], task 'findmilk')"
    ), line
    assert sorted(p.name for p in run.iterdir()) == before  # no finetune-narrow
