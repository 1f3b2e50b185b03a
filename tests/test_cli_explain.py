"""amuled explain: one state's beliefs, weights, reasoning and fusion, checked against fusion."""

from __future__ import annotations

import re

import numpy as np
import pytest
import tiny_cli
import torch
from scenario_feedback import make_feedback

from amuled_ma.beliefs.sources.replay import ReplaySource
from amuled_ma.beliefs.types import BeliefRequest
from amuled_ma.cli import main
from amuled_ma.experiments.run_folder import scenario_of_run
from amuled_ma.fusion import bjs_divergence, fuse
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.tasks import make_task

#: The tiny run, its fine-tunes 2 iterations long.
TINY = [*tiny_cli.TINY, "--set", "finetune.iterations=2"]
CLUSTERS = ["consequentialist", "deontological", "virtue", "care", "social_justice"]
NUMBER = r"-?\d+\.\d{4}"


def row_values(out: str, label: str, after: str | None = None) -> list[float]:
    """The numbers of the first table row starting with ``label`` (after a heading)."""
    text = out.split(after, 1)[1] if after else out
    for line in text.splitlines():
        if line.strip().startswith(label + " ") or line.strip() == label:
            values = [float(x) for x in re.findall(NUMBER, line.strip()[len(label) :])]
            if values:  # not a header row
                return values
    raise AssertionError(f"no row {label!r} in:\n{out}")


def test_explain_a_state_by_hand_on_the_shipped_scenario(recordings_dir, capsys):
    obs = [2, 3, 7, 7, 2, 2, 1, 1]
    argv = ["explain", "findmilk", "--obs", ",".join(map(str, obs)), "--prompt-var", "num_crying=4"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    # what the recording holds for this state, and its fusion computed here
    source = ReplaySource(recordings_dir / "findmilk-gpt-4o-mini.json")
    actions = ("up", "down", "left", "right")
    answers = [
        source.lookup(BeliefRequest("findmilk", c, tuple(map(float, obs)), actions))
        for c in CLUSTERS
    ]
    beliefs = np.stack([a[0] for a in answers])
    diag = fuse(beliefs[None], "bjs-dst", return_diagnostics=True)
    for c, cluster in enumerate(CLUSTERS):
        values = row_values(out, cluster, "beliefs:")
        np.testing.assert_allclose(values[:4], beliefs[c], atol=5e-5)
        np.testing.assert_allclose(values[4], diag.weights[0, c], atol=5e-5)
        np.testing.assert_allclose(row_values(out, cluster, "fusion (bjs-dst)")[1],
                                   diag.credibility[0, c], atol=5e-5)  # fmt: skip
    np.testing.assert_allclose(row_values(out, "fused (bjs-dst)"), diag.fused[0], atol=5e-5)
    np.testing.assert_allclose(row_values(out, "fused (recomputed)"), diag.fused[0], atol=5e-5)
    np.testing.assert_allclose(row_values(out, "WAE (weighted average evidence)"), diag.wae[0],
                               atol=5e-5)  # fmt: skip
    conflicts = [float(x) for x in re.findall(r"K\d=(\d\.\d{4})", out)]
    np.testing.assert_allclose(conflicts, diag.conflicts[0], atol=5e-5)
    pair = bjs_divergence(beliefs[0], beliefs[1])
    assert row_values(out, CLUSTERS[0], "pairwise BJS")[1] == pytest.approx(pair, abs=5e-5)
    # the recorded reasoning of this state (an exchange the authors kept) is printed
    assert answers[0][1] and answers[0][1].splitlines()[0] in out
    assert "more characters; --full prints them" in out
    # tables are aligned: every row of the beliefs table has the header's width
    block = out.split("beliefs:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert len({len(line) for line in block[:2]}) == 1


def test_explain_fused_only_recording_says_so_and_names_the_fix(recordings_dir, capsys):
    argv = ["explain", "driving", "--obs", "6,5,-1,-1,-1,-1,0,0,1,0,0"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "not a panel of agents" in out and "driving-llama-3_1-70b" in out
    assert len(row_values(out, "feedback belief")) == 3
    # with the per-cluster recording: five agents and the fusion
    argv += ["--set", 'feedback.recording="driving-llama-3_1-70b"']
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert all(f"  {c} " in out for c in CLUSTERS) and "Dempster's conflict" in out


def test_explain_usage_errors_name_the_fix(capsys):
    assert main(["explain", "findmilk", "--obs", "1,2,3"]) == 1
    err = capsys.readouterr().err
    assert "8 entries" in err and "sleep_y" in err
    assert main(["explain", "findmilk"]) == 1
    assert "--obs" in capsys.readouterr().err
    assert main(["explain", "findmilk", "--obs", "a,b"]) == 1
    assert "numbers" in capsys.readouterr().err
    assert main(["explain", "--state-from", "nowhere", "--variant", "x"]) == 1
    assert "--step" in capsys.readouterr().err


def test_explain_state_from_an_episode_of_a_run(tmp_path, capsys):
    run = tmp_path / "run"
    common = ["findmilk", "--run-dir", str(run), *TINY, "--set", 'feedback.source="rules"']
    assert main(["train", *common]) == 0
    assert main(["finetune", *common]) == 0
    capsys.readouterr()
    step = 2
    argv = [
        "explain",
        "--state-from",
        str(run),
        "--variant",
        "finetune-amuled",
        "--step",
        str(step),
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    # the same state computed here: the greedy evaluation episode, then the panel
    scenario = scenario_of_run(run)
    actor = load_policy(run / "finetune-amuled" / "model_last.pt", scenario.ppo)
    task = make_task(scenario.task, 1, shaping_coef=0.0, seed=scenario.evaluation.seed)
    obs = torch.as_tensor(task.reset()).float()
    for _ in range(step):
        obs, *_ = task.step(action_log_probs(actor, obs).argmax(-1))
        obs = torch.as_tensor(obs).float()
    taken = ("up", "down", "left", "right")[int(action_log_probs(actor, obs).argmax(-1)[0])]
    feedback = make_feedback("amuled", scenario, tmp_path / "scratch")
    panel = feedback.panel.fused(obs.numpy(), task.prompt_variables([0]))
    feedback.close()
    assert f"state of step {step} of evaluation episode 0" in out
    assert f"the fine-tuned policy took {taken}" in out
    for c, cluster in enumerate(CLUSTERS):
        np.testing.assert_allclose(row_values(out, cluster, "beliefs:")[:4], panel.beliefs[0, c],
                                   atol=5e-5)  # fmt: skip
    np.testing.assert_allclose(row_values(out, "fused (bjs-dst)"), panel.fused[0], atol=5e-5)
    assert "no reply text kept" in out  # the rules source gives no text
    assert main([*argv[:-1], "100000"]) == 1
    assert "steps (0.." in capsys.readouterr().err


def test_explain_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["explain", "--help"])
    assert info.value.code == 0
    assert "--state-from" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--obs", "nan,3,7,7,2,2,1,1"], "--obs: entry 1 (x) is 'nan', expected a finite number"),
        (["--obs", "2,1e400,7,7,2,2,1,1"], "entry 2 (y) is '1e400', expected a finite number"),
        (["--obs", "2,3,7,7,2,2,1,-1e39"], "is '-1e39', expected a finite number"),  # float32
        (
            ["--obs", "2,3,7,7,2,2,1,1", "--prompt-var", "num_crying=1e400"],
            "--prompt-var num_crying: expected a finite number, found inf",
        ),
        (
            ["--obs", "2,3,7,7,2,2,1,1", "--prompt-var", "num_crying=nan"],
            "--prompt-var num_crying: expected a finite number, found nan",
        ),
        (
            ["--obs", "2,3,7,7,2,2,1,1", "--prompt-var", f"num_crying={10**30}"],
            "expected a number within +-9,007,199,254,740,992 (2^53), found 1e+30",
        ),
    ],
)
def test_explain_refuses_numbers_that_are_not_finite_with_one_line(capsys, argv, expected):
    assert main(["explain", "findmilk", *argv]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("amuled: error: ")
    assert expected in err
