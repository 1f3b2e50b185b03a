"""An agent without an answer abstains: left out of the fusion, weight 0, counted."""

from collections.abc import Sequence

import numpy as np
import pytest

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation.panel import MoralPanel
from amuled_ma.fusion.reference import fuse_beliefs

ACTIONS = ("up", "down", "left", "right")
ANSWERS = {
    "a": [0.7, 0.1, 0.1, 0.1],
    "b": [0.6, 0.2, 0.1, 0.1],
    "c": [0.1, 0.1, 0.1, 0.7],
}


class Answers(BeliefSource):
    """Answers ``ANSWERS`` for every state; ``absent`` agents fail with ``status``."""

    name = "answers"
    needs_messages = False

    def __init__(self, absent: Sequence[str] = (), status: str = "abstained") -> None:
        self.absent, self.status = set(absent), status

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        out = []
        for r in requests:
            if r.cluster in self.absent:
                out.append(BeliefResult(np.full(4, 0.25), self.status, self.name))
            else:
                out.append(BeliefResult(np.asarray(ANSWERS[r.cluster]), "ok", self.name))
        return out


@pytest.mark.parametrize("status", ["abstained", "timeout", "error", "replay_miss"])
def test_absent_agent_is_excluded_and_gets_weight_zero(status):
    panel = MoralPanel("findmilk", ["a", "b", "c"], Answers(["c"], status), action_names=ACTIONS)
    out = panel.fused(np.zeros((2, 8)))
    # the reference implementation (one state at a time, dicts) over the two answers
    expected = fuse_beliefs([ANSWERS["a"], ANSWERS["b"]])
    np.testing.assert_allclose(out.fused[0], expected, atol=1e-12)
    np.testing.assert_allclose(out.weights[0, 2], 0.0)
    assert out.weights[0, :2].sum() == pytest.approx(1.0)
    assert out.statuses[0].tolist() == ["ok", "ok", status]


def test_a_fake_uniform_belief_would_have_taken_weight():
    """Why abstention matters: fed as uniform, the silent agent takes a share of the weight."""
    from amuled_ma.fusion import fuse

    beliefs = np.array([[ANSWERS["a"], ANSWERS["b"], [0.25] * 4]])
    weights = fuse(beliefs, "bjs-dst", return_diagnostics=True).weights[0]
    assert weights[2] > 0.3  # the old behaviour: about 0.31 for an agent that said nothing
    panel = MoralPanel("findmilk", ["a", "b", "c"], Answers(["c"]), action_names=ACTIONS)
    assert panel.fused(np.zeros((1, 8))).weights[0, 2] == 0.0


def test_nobody_answers_gives_the_counted_uniform_fallback():
    panel = MoralPanel("findmilk", ["a", "b"], Answers(["a", "b"]), action_names=ACTIONS)
    out = panel.fused(np.zeros((3, 8)))
    np.testing.assert_allclose(out.fused, 0.25)
    np.testing.assert_allclose(out.weights, 0.0)
    assert panel.stats.no_answer == 1  # one distinct state


def test_mixed_rows_fuse_each_over_its_own_answers():
    class PerState(Answers):
        def beliefs(self, requests):
            out = []
            for r in requests:
                missing = (r.obs[0] == 1.0 and r.cluster == "a") or (
                    r.obs[0] == 2.0 and r.cluster == "b"
                )
                belief = np.full(4, 0.25) if missing else np.asarray(ANSWERS[r.cluster])
                out.append(BeliefResult(belief, "abstained" if missing else "ok", self.name))
            return out

    panel = MoralPanel("findmilk", ["a", "b", "c"], PerState(), action_names=ACTIONS)
    obs = np.zeros((3, 8))
    obs[1, 0], obs[2, 0] = 1.0, 2.0
    out = panel.fused(obs)
    np.testing.assert_allclose(out.fused[0], fuse_beliefs(list(ANSWERS.values())), atol=1e-12)
    np.testing.assert_allclose(out.fused[1], fuse_beliefs([ANSWERS["b"], ANSWERS["c"]]), atol=1e-12)
    np.testing.assert_allclose(out.fused[2], fuse_beliefs([ANSWERS["a"], ANSWERS["c"]]), atol=1e-12)
    assert out.weights[1, 0] == 0.0 and out.weights[2, 1] == 0.0


def test_a_cluster_missing_from_the_recording_gains_no_weight(recordings_dir, tmp_path):
    """A sixth cluster nobody recorded: before, it got the largest weight (0.193)."""
    from amuled_ma.beliefs.sources.replay import ReplaySource

    source = ReplaySource(recordings_dir / "findmilk-gpt-4o-mini.json", miss_policy="uniform")
    names = ["consequentialist", "deontological", "virtue", "care", "social_justice"]
    panel = MoralPanel("findmilk", [*names, "animal_welfare"], source)
    import json

    states = json.loads((recordings_dir / "findmilk-gpt-4o-mini.json").read_text())["states"]
    obs = np.array([s["obs"] for s in states[:50]])
    out = panel.fused(obs)
    assert (out.weights[:, 5] == 0).all()
    assert (out.statuses[:, 5] == "replay_miss").all()
    five = MoralPanel("findmilk", names, source)
    np.testing.assert_allclose(out.fused, five.fused(obs).fused, atol=1e-12)
