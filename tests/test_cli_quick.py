"""``amuled run --quick`` and ``amuled ablate --quick``: the documented short form."""

import json

import pytest
from tiny_cli import RULES, TINY

from amuled_ma.cli import build_parser, main
from amuled_ma.commands.run import request_of
from amuled_ma.scenario import load_scenario

#: What the short form's output and report must say (the README promises it).
NOT_PAPER = "NOT the paper's length (500,000 / 1,000 / 50)"


@pytest.mark.parametrize("command", ["run", "ablate"])
def test_help_shows_the_quick_form(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--quick" in text
    assert "65,536 base env steps, 50 fine-tuning iterations, 10 evaluation episodes" in text


def test_quick_budget_and_run_folder_and_title(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["ablate", "findmilk", "--what", "kl", "--quick"])
    request = request_of(args)
    # findmilk.toml: 500,000 base steps, 1,000 iterations, 50 episodes; the short form's own
    assert load_scenario("findmilk").base.total_steps == 500_000
    assert request.scenario.base.total_steps == 65_536
    assert request.scenario.finetune.iterations == 50
    assert request.episodes == 10
    assert str(request.run_dir) == "runs/findmilk-quick"  # never the full run's folder
    assert request.title.startswith("findmilk: ablation of kl, quick form")
    assert NOT_PAPER in request.title
    assert request.hint.endswith("--quick") or " --quick " in request.hint


def test_a_set_and_episodes_win_over_the_quick_form(tmp_path):
    args = build_parser().parse_args(
        ["run", "findmilk", "--quick", "--set", "finetune.iterations=7", "--episodes", "4",
         "--run-dir", str(tmp_path / "r")]
    )  # fmt: skip
    request = request_of(args)
    assert request.scenario.finetune.iterations == 7
    assert request.scenario.base.total_steps == 65_536
    assert request.episodes == 4
    assert request.run_dir == tmp_path / "r"


def test_quick_run_says_so_in_its_output_and_report(tmp_path, capsys):
    run_dir = tmp_path / "run"
    args = ["run", "findmilk", "--quick", "--run-dir", str(run_dir), *TINY, *RULES]
    assert main([*args, "--jobs", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert NOT_PAPER in lines[0] and NOT_PAPER in lines[-1]  # first and last line
    report = (run_dir / "report.md").read_text()
    assert NOT_PAPER in report.splitlines()[0]
    results = json.loads((run_dir / "results.json").read_text())
    # the short form's 10 evaluation episodes (TINY sets no episodes)
    assert results["variants"]["base"]["greedy"]["metrics"]["steps_to_milk"]["n"] == 10
