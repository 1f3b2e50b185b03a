import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from job_settings import ablation_jobs

from amuled_ma.beliefs.types import BeliefResult, BeliefSource
from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.deliberation.panel_feedback import PanelFeedback
from amuled_ma.deliberation.summaries import summary_lines
from amuled_ma.errors import ScenarioError
from amuled_ma.records.variants import Variant, parse_feedback
from amuled_ma.scenario import scenario_from_dict

MILK = ("up", "down", "left", "right")


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
        # the state's prompt variables (the same for every copy here); PanelFeedback keys a
        # state by observation and prompt variables, as the panel does
        return [{"crying": 2} for _ in ids]


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
    # per agent: FakePanel's "a" always answered, "b" was always a replay miss
    assert summary["agents"]["a"]["ok"] == 6 and summary["agents"]["b"]["replay_miss"] == 6
    assert summary["agents"]["b"]["failure_rate"] == 1.0 and summary["failure_rate"] == 0.5


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
def test_parse_feedback(name, expected):
    assert parse_feedback(name) == expected


@pytest.mark.parametrize("name", ["", "agg:median", "cluster:", "amuled:x", "llm"])
def test_parse_feedback_rejects(name):
    with pytest.raises(ScenarioError, match="unknown feedback variant"):
        parse_feedback(name)


def test_ablation_lists():
    sc = scenario_from_dict({})
    clusters = ablation_jobs("clusters", sc)
    assert [str(v) for v, _ in clusters][-2:] == ["finetune:moral", "finetune:amuled"]
    assert len(clusters) == len(sc.feedback.clusters) + 2
    assert [v.folder for v, _ in ablation_jobs("aggregation", sc)] == [
        "finetune-agg-mean",
        "finetune-agg-max",
        "finetune-agg-vote",
        "finetune-agg-mec",
        "finetune-agg-nash-vote",
        "finetune-agg-variance-vote",
        "finetune-agg-borda",
        "finetune-amuled",
    ]
    kl = ablation_jobs("kl", sc)
    assert [s.finetune.lambda_kl for _, s in kl] == [0.0, 0.5, 1.0, 2.5, 5.0, 10.0]
    assert [v.folder for v, _ in kl][1] == "finetune-amuled-kl0.5"
    assert Variant.parse("finetune:cluster:care").folder == "finetune-cluster-care"
    # an unknown ablation is refused where the request is made (tests/experiments/test_pipeline.py)


def test_make_source_preflight_fails_before_writing(tmp_path):
    from scenario_feedback import make_source

    from amuled_ma.beliefs import register_source
    from amuled_ma.beliefs.types import BeliefSource
    from amuled_ma.errors import BackendUnavailable

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
    sc = scenario_from_dict({})
    # a plug-in source kind is no choice of a scenario file: set it without validation
    sc = sc.model_copy(
        update={"feedback": sc.feedback.model_copy(update={"source": "down-for-test"})}
    )
    with pytest.raises(BackendUnavailable):
        make_source(sc, tmp_path / "run")
    assert Down.closed
    assert not (tmp_path / "run").exists()


class _Answers(BeliefSource):
    """A plug-in source: per cluster, a fixed answer given with status "ok"."""

    name = "plugin"
    needs_messages = False

    def __init__(self, table):
        self.table = table

    def beliefs(self, requests):
        return [
            BeliefResult(np.asarray(self.table[r.cluster], dtype=np.float64), "ok", self.name)
            for r in requests
        ]


def _panel_feedback(tmp_path, table, clusters=("care", "virtue")):
    from amuled_ma.beliefs.store.cached import CachedSource
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.deliberation import MoralPanel

    store = BeliefStore(tmp_path / "beliefs.sqlite")
    source = CachedSource(_Answers(table), store)
    panel = MoralPanel("findmilk", list(clusters), source, "mean", action_names=MILK)
    return PanelFeedback("amuled", panel, source), store


def test_a_source_that_answers_nan_is_reported_as_100_percent_errors(tmp_path):
    # a server that always answers NaN: every answer an error, not "miss rate 0.00%"
    fb, store = _panel_feedback(tmp_path, {"care": [np.nan] * 4, "virtue": [np.nan] * 4})
    obs = torch.tensor([[0.0, 1.0], [0.0, 1.0], [2.0, 3.0]])
    rewards = fb(obs, FakeTask())
    fb(obs, FakeTask())
    np.testing.assert_array_equal(rewards, np.full((3, 4), 0.25))  # uniform fallbacks
    summary = fb.summary()
    assert summary["miss_rate"] == 0.0 and summary["failure_rate"] == 1.0
    assert summary["statuses"] == {"error": 12}  # 6 rewarded steps x 2 agents
    for agent in ("care", "virtue"):
        row = summary["agents"][agent]
        assert (row["ok"], row["error"], row["total"], row["failure_rate"]) == (0, 6, 6, 1.0)
        assert summary["agents_per_state"][agent]["error"] == 2  # 2 distinct states
    json.dumps(summary, allow_nan=False)  # results.json-ready
    assert summary_lines(summary) == [
        "beliefs not answered: 100.00% of 12 (abstained 0, timeout 0, error 12, replay_miss 0)",
        "  care: ok 0, repaired 0, abstained 0, timeout 0, error 6 (100.00%), replay_miss 0",
        "  virtue: ok 0, repaired 0, abstained 0, timeout 0, error 6 (100.00%), replay_miss 0",
    ]
    # nothing was stored as an answer
    assert store.stats()["by_status"] == {"error": 4} and store.stats()["cacheable_rows"] == 0
    store.close()


def test_per_agent_counts_separate_a_failing_agent_from_a_good_one(tmp_path):
    fb, store = _panel_feedback(tmp_path, {"care": [0.0, 0.0, 0.0, 1.0], "virtue": [-1, 0, 0, 2]})
    fb(torch.tensor([[0.0, 1.0], [5.0, 3.0]]), FakeTask())
    summary = fb.summary()
    assert summary["agents"]["care"]["ok"] == 2 and summary["agents"]["care"]["failed"] == 0
    assert summary["agents"]["virtue"]["error"] == 2
    assert summary["failure_rate"] == 0.5
    assert fb.agent_report(per="states")["virtue"]["failure_rate"] == 1.0
    lines = summary_lines(summary)
    assert lines[0] == (
        "beliefs not answered: 50.00% of 4 (abstained 0, timeout 0, error 2, replay_miss 0)"
    )
    assert lines[1] == "  care: ok 2, repaired 0, abstained 0, timeout 0, error 0, replay_miss 0"
    # a summary written before per-agent counts existed still prints its headline
    assert summary_lines({"statuses": {"ok": 9, "replay_miss": 1}}) == [
        "beliefs not answered: 10.00% of 10 (abstained 0, timeout 0, error 0, replay_miss 1)"
    ]
    with pytest.raises(ValueError, match="per must be"):
        fb.agent_report(per="episodes")
    store.close()
