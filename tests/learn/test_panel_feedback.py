"""Panel feedback: one cache keyed like the panel, abstention limits, preflight, names."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import pytest
import torch

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.cli import main
from amuled_ma.deliberation.panel import MoralPanel
from amuled_ma.deliberation.panel_feedback import PanelFeedback
from amuled_ma.errors import AbstentionError, ScenarioError

ACTIONS = ("up", "down", "left", "right")


class CountsCrying(BeliefSource):
    """A live-like source: its answer depends on the state prompt (crying babies left)."""

    name = "counts-crying"
    needs_messages = True

    def __init__(self) -> None:
        self.asked: list[str] = []

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        out = []
        for r in requests:
            prompt = r.messages[-1][1]
            self.asked.append(prompt)
            crying = int(prompt.split("crying=")[1].split()[0])
            belief = np.full(4, 0.1)
            belief[crying % 4] = 0.7
            out.append(BeliefResult(belief, "ok", self.name))
        return out


class Task:
    """Two copies at the same position; the prompt variables differ (crying babies)."""

    def __init__(self) -> None:
        self.crying = [3, 1]

    def prompt_variables(self, env_ids: Sequence[int]) -> list[dict]:
        return [{"x": 0, "crying": self.crying[i]} for i in env_ids]


def _panel(source: BeliefSource, clusters=("a",)) -> MoralPanel:
    return MoralPanel(
        "findmilk", list(clusters), source, "mean", action_names=ACTIONS,
        render_state_prompt=lambda task, v: f"at x={v['x']} crying={v['crying']} end",
        build_messages=lambda cluster, task, state: (("user", state),),
    )  # fmt: skip


def test_memo_keys_states_by_observation_and_prompt_variables():
    """Same observation, other crying count: another state, another answer."""
    source = CountsCrying()
    feedback = PanelFeedback("amuled", _panel(source), source)
    assert feedback.keyed_by_prompt
    task = Task()
    obs = torch.zeros(2, 8)
    out = feedback(obs, task)
    assert out[0].argmax() == 3 and out[1].argmax() == 1  # not the first answer for both
    task.crying = [1, 3]  # the counts changed at the same positions: answered from memo
    again = feedback(obs, task)
    assert again[0].argmax() == 1 and again[1].argmax() == 3
    assert len(source.asked) == 2 and feedback.summary()["unique_states"] == 2


class Silent(BeliefSource):
    """Agent ``b`` never answers (a server that is down for it)."""

    name = "silent"
    needs_messages = False

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        return [
            BeliefResult(np.full(4, 0.25), "timeout", self.name)
            if r.cluster == "b"
            else BeliefResult(np.array([0.7, 0.1, 0.1, 0.1]), "ok", self.name)
            for r in requests
        ]


def test_an_agent_over_the_abstention_limit_stops_the_run_naming_it():
    panel = _panel(Silent(), clusters=("a", "b"))
    feedback = PanelFeedback("amuled", panel, Silent())
    feedback.max_abstention = 0.2
    obs = torch.arange(19 * 8, dtype=torch.float32).reshape(19, 8)
    feedback(obs, None)  # 19 distinct states: not judged yet
    with pytest.raises(AbstentionError) as err:
        feedback(obs + 1000, None)
    text = str(err.value)
    assert "agent 'b' (source: silent)" in text and "timeout" in text
    assert "max_abstention = 0.2" in text
    # within the limit: no error
    tolerant = PanelFeedback("amuled", _panel(Silent(), clusters=("a", "b")), Silent())
    tolerant.max_abstention = 1.0
    tolerant(obs, None)
    tolerant(obs + 1000, None)


TINY = [
    "--set", "base.total_steps=512", "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16", "--set", "finetune.iterations=2",
    "--set", "finetune.num_envs=4", "--set", "finetune.num_steps_per_env=8",
    "--set", "output.tensorboard=false", "--no-progress",
]  # fmt: skip


def test_unknown_cluster_and_missing_recording_fail_before_training(tmp_path, capsys):
    run_dir = tmp_path / "run"
    for extra, needle in [
        (["--feedback", "cluster:no_such_cluster"], "no moral cluster 'no_such_cluster'"),
        (["--set", 'feedback.recording="absent-recording"'], "absent-recording"),
    ]:
        started = time.perf_counter()
        code = main(["finetune", "findmilk", "--run-dir", str(run_dir), *extra, *TINY])
        assert code == 1 and time.perf_counter() - started < 10
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err
        assert not (run_dir / "base").exists()  # nothing trained, not even the base check
    err_fix = "--clusters-dir"
    main(["finetune", "findmilk", "--run-dir", str(run_dir),
          "--feedback", "cluster:no_such_cluster", *TINY])  # fmt: skip
    assert err_fix in capsys.readouterr().err


WELFARE = """\
name = "animal_welfare"
kind = "cluster"
title = "Animal Welfare Ethics"
credence_label = "Animal Welfare Ethics"
focus = "Focus on the wellbeing of every sentient creature"
key_principle = "Suffering matters, whoever feels it."
order = 6

[[theories]]
name = "Sentientism"
key_concepts = ["Sentience", "Suffering"]
decision_factors = ["Who can feel pain here"]
"""


def test_named_variant_with_a_user_cluster_sits_beside_amuled(tmp_path, capsys):
    clusters = tmp_path / "my_clusters"
    clusters.mkdir()
    (clusters / "animal_welfare.toml").write_text(WELFARE)
    run_dir = tmp_path / "run"
    rules = ["--set", 'feedback.source="rules"']
    assert main(["train", "findmilk", "--run-dir", str(run_dir), *TINY]) == 0
    assert main(["finetune", "findmilk", "--run-dir", str(run_dir), *rules, *TINY]) == 0
    panel = ["consequentialist", "deontological", "virtue", "care", "social_justice",
             "animal_welfare"]  # fmt: skip
    argv = ["finetune", "findmilk", "--run-dir", str(run_dir), "--clusters-dir", str(clusters),
            "--name", "with-welfare", "--set", f"feedback.clusters={panel!r}".replace("'", '"'),
            *rules, "--set", 'feedback.agents.animal_welfare={source="rules"}',
            *TINY]  # fmt: skip
    # rules answer a user's cluster only when asked for it by name (its text is not read)
    assert main(argv) == 0
    assert (run_dir / "finetune-with-welfare" / "model_last.pt").is_file()
    assert (run_dir / "finetune-amuled" / "model_last.pt").is_file()
    capsys.readouterr()
    assert main(["evaluate", str(run_dir), "--episodes", "2", "--no-progress"]) == 0
    report = (run_dir / "report.md").read_text()
    assert "finetune-with-welfare" in report and "finetune-amuled" in report
    assert "animal_welfare" in report


def test_a_cluster_file_names_its_default_source_and_the_scenario_overrides_it(tmp_path):
    from scenario_feedback import make_feedback

    from amuled_ma.scenario import load_scenario

    clusters = tmp_path / "clusters"
    clusters.mkdir()
    (clusters / "animal_welfare.toml").write_text(WELFARE + '\n[source]\nsource = "rules"\n')
    panel = ["consequentialist", "deontological", "virtue", "care", "social_justice",
             "animal_welfare"]  # fmt: skip
    scenario = load_scenario("findmilk").replace(
        "feedback", clusters=panel, clusters_dirs=[str(clusters)],
        store=str(tmp_path / "s.sqlite"), recording="findmilk-gpt-4o-mini",
    )  # fmt: skip
    feedback = make_feedback("amuled", scenario, tmp_path)
    assert feedback.agent_source("animal_welfare").startswith("rules")
    assert feedback.agent_source("care").startswith("replay")
    feedback.close()
    # the scenario's table for the agent wins over the file's default
    overridden = scenario.replace("feedback", agents={"animal_welfare": {"source": "terminal"}})
    feedback = make_feedback("amuled", overridden, tmp_path)
    assert feedback.agent_source("animal_welfare").startswith("terminal")
    feedback.close()
    # a table routing it to a recording that does not hold it is refused up front
    replayed = scenario.replace("feedback", agents={"animal_welfare": {"source": "replay"}})
    with pytest.raises(ScenarioError, match='cluster "animal_welfare" is not in recording'):
        make_feedback("amuled", replayed, tmp_path)


def test_rare_unanswered_states_do_not_stop_a_run():
    """25 of 45 distinct states unanswered, but visited once each among 1,000 steps: 2.5%."""

    class RareMisses(BeliefSource):
        name = "rare"
        needs_messages = False

        def beliefs(self, requests):
            return [
                BeliefResult(np.full(4, 0.25), "replay_miss", self.name)
                if r.obs[0] >= 100
                else BeliefResult(np.array([0.7, 0.1, 0.1, 0.1]), "ok", self.name)
                for r in requests
            ]

    feedback = PanelFeedback("amuled", _panel(RareMisses()), RareMisses())
    feedback.max_abstention = 0.2
    common = torch.arange(20, dtype=torch.float32).repeat_interleave(8).reshape(20, 8)
    rare = (100 + torch.arange(25, dtype=torch.float32)).repeat_interleave(8).reshape(25, 8)
    for _ in range(48):
        feedback(common, None)  # 960 steps on 20 answered states
    feedback(rare, None)  # 25 steps on 25 unanswered states
    report = feedback.agent_report(per="states")["a"]
    assert report["replay_miss"] == 25 and report["total"] == 45
    # per step: 25 of 985 = 2.5%, far below the limit; per distinct state it would be 56%
    with pytest.raises(AbstentionError):
        for _ in range(40):
            feedback(rare, None)  # now the policy keeps visiting them: 1,025 of 1,985
