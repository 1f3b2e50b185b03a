from types import SimpleNamespace

import numpy as np
import pytest
import torch

from amuled_ma.errors import ScenarioError
from amuled_ma.learn.experiments import ablation_variants, variant_dir_name
from amuled_ma.learn.feedback import CallableFeedback, PanelFeedback, parse_variant
from amuled_ma.scenario import scenario_from_dict


class FakePanel:
    cluster_names = ("a", "b")

    def __init__(self):
        self.calls = []

    def fused(self, obs, prompt_vars):
        self.calls.append(len(obs))
        n = len(obs)
        fused = np.tile([0.1, 0.2, 0.3, 0.4], (n, 1))
        return SimpleNamespace(
            fused=fused,
            weights=np.tile([0.25, 0.75], (n, 1)),
            conflict=np.full(n, 0.5),
            statuses=np.array([["ok", "replay_miss"]] * n),
        )


class FakeTask:
    def prompt_variables(self, ids):
        return [{"id": i} for i in ids]


def test_panel_feedback_batches_new_states_once_and_reports_diagnostics():
    panel = FakePanel()
    fb = PanelFeedback("amuled", panel)
    obs = torch.tensor([[0.0, 1.0], [0.0, 1.0], [2.0, 3.0]])
    out = fb(obs, FakeTask())
    assert out.shape == (3, 4) and panel.calls == [2]  # two distinct states, one batch
    fb(obs, FakeTask())
    assert panel.calls == [2]  # repeated states cost nothing
    summary = fb.summary()
    assert summary["steps"] == 6 and summary["unique_states"] == 2
    assert summary["mean_weight"] == pytest.approx({"a": 0.25, "b": 0.75})
    assert summary["mean_conflict"] == pytest.approx(0.5)
    assert summary["miss_rate"] == pytest.approx(0.5)


def test_callable_feedback():
    fb = CallableFeedback(lambda o: np.full((len(o), 3), 1 / 3))
    assert fb(torch.zeros(4, 2), None).shape == (4, 3)


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("amuled", ("amuled", None)),
        ("human", ("human", None)),
        ("moral", ("moral", None)),
        ("cluster:care", ("cluster", "care")),
        ("agg:vote", ("agg", "vote")),
    ],
)
def test_parse_variant(name, expected):
    assert parse_variant(name) == expected


@pytest.mark.parametrize("name", ["", "agg:median", "cluster:", "amuled:x", "llm"])
def test_parse_variant_rejects(name):
    with pytest.raises(ScenarioError, match="unknown feedback variant"):
        parse_variant(name)


def test_ablation_lists():
    sc = scenario_from_dict({})
    clusters = ablation_variants("clusters", sc)
    assert [v for v, _, _ in clusters][-2:] == ["moral", "amuled"]
    assert len(clusters) == len(sc.feedback.clusters) + 2
    assert [f for _, _, f in ablation_variants("aggregation", sc)] == [
        "finetune-agg-mean",
        "finetune-agg-max",
        "finetune-agg-vote",
        "finetune-amuled",
    ]
    kl = ablation_variants("kl", sc)
    assert [s.finetune.lambda_kl for _, s, _ in kl] == [0.0, 0.5, 1.0, 2.5, 5.0, 10.0]
    assert variant_dir_name("finetune:cluster:care") == "finetune-cluster-care"
    with pytest.raises(ScenarioError):
        ablation_variants("nope", sc)


def test_make_source_preflight_fails_before_writing(tmp_path):
    from amuled_ma.beliefs import register_source
    from amuled_ma.beliefs.types import BeliefSource
    from amuled_ma.errors import BackendUnavailable
    from amuled_ma.learn.feedback import make_source

    class Down(BeliefSource):
        name = "down"
        closed = False

        def check(self):
            raise BackendUnavailable("no server at nowhere")

        def beliefs(self, requests):  # pragma: no cover - never reached
            return []

        def close(self):
            Down.closed = True

    register_source("down-for-test", lambda **_: Down())
    import dataclasses

    sc = scenario_from_dict({})
    sc = dataclasses.replace(sc, feedback=dataclasses.replace(sc.feedback, source="down-for-test"))
    with pytest.raises(BackendUnavailable):
        make_source(sc, tmp_path / "run")
    assert Down.closed
    assert not (tmp_path / "run").exists()
