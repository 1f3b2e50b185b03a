"""MoralPanel: one batch per call, dedup of states, LRU, sanitising, hand-computed fusions."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation import MoralPanel

ACTIONS = ("up", "down", "left", "right")

# Hand-written beliefs per (cluster, obs[0]).
TABLE = {
    ("a", 0.0): [0.5, 0.5, 0.0, 0.0],
    ("b", 0.0): [0.0, 0.5, 0.5, 0.0],
    ("a", 1.0): [1.0, 0.0, 0.0, 0.0],
    ("b", 1.0): [0.0, 0.0, 0.0, 1.0],
}


class Table(BeliefSource):
    name = "table"

    def __init__(self, needs_messages=False, statuses=None):
        self.needs_messages = needs_messages
        self.calls: list[list[BeliefRequest]] = []
        self.statuses = statuses or {}

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        self.calls.append(list(requests))
        out = []
        for r in requests:
            key = (r.cluster, r.obs[0])
            status = self.statuses.get(key, "ok")
            b = self.statuses.get(("belief", *key), TABLE.get(key, [0.25] * 4))
            out.append(BeliefResult(np.asarray(b, float), status, self.name))
        return out


def obs(*firsts):
    return np.array([[f, 7.0] for f in firsts])


def test_mean_rule_hand_computed_and_one_batch():
    src = Table()
    panel = MoralPanel("findmilk", ["a", "b"], src, "mean", action_names=ACTIONS)
    out = panel.fused(obs(0, 1, 0, 0, 1))
    # one call to the source, two distinct states x two clusters
    assert len(src.calls) == 1 and len(src.calls[0]) == 4
    assert out.unique == 2
    # mean of [.5,.5,0,0] and [0,.5,.5,0]; mean of one-hot up and one-hot right
    np.testing.assert_allclose(out.fused[0], [0.25, 0.5, 0.25, 0.0])
    np.testing.assert_allclose(out.fused[1], [0.5, 0.0, 0.0, 0.5])
    np.testing.assert_allclose(out.fused[[2, 3]], [[0.25, 0.5, 0.25, 0.0]] * 2)
    assert out.beliefs.shape == (5, 2, 4) and out.weights.shape == (5, 2)
    np.testing.assert_allclose(out.beliefs[4, 1], [0, 0, 0, 1])
    assert out.statuses.tolist() == [["ok", "ok"]] * 5
    np.testing.assert_allclose(out.reward([1, 3, 0, 2, 1]), [0.5, 0.5, 0.25, 0.25, 0.0])


def test_vote_rule_tie_split():
    panel = MoralPanel("findmilk", ["a", "b"], Table(), "vote", action_names=ACTIONS)
    out = panel.fused(obs(1))
    # a votes up, b votes right: tie -> half each (the fusion module's documented rule)
    np.testing.assert_allclose(out.fused[0], [0.5, 0.0, 0.0, 0.5])


def test_bjs_dst_identical_beliefs_hand_computed():
    # Identical beliefs m = [.5,.5,0,0] from 3 clusters: weights 1/3 each, fused m^3/sum m^3
    # = [.5, .5, 0, 0]; Dempster's conflict of m with itself: 1 - (.25 + .25) = 0.5.
    src = Table(statuses={("belief", c, 5.0): [0.5, 0.5, 0.0, 0.0] for c in "abc"})
    panel = MoralPanel("findmilk", ["a", "b", "c"], src, action_names=ACTIONS)
    out = panel.fused(obs(5))
    np.testing.assert_allclose(out.fused[0], [0.5, 0.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out.weights[0], [1 / 3] * 3, atol=1e-12)
    assert out.conflicts.shape == (1, 2)
    assert out.conflict[0] == pytest.approx(0.5)


def test_every_call_asks_its_distinct_states_the_feedback_memoises():
    # the panel keeps no cache (docs/beliefs.md, "Caches"): a second call asks again, the
    # source (in training: the belief store) answers; a fallback is reported each time
    src = Table(statuses={("b", 1.0): "abstained"})
    panel = MoralPanel("findmilk", ["a", "b"], src, "mean", action_names=ACTIONS)
    panel.fused(obs(0, 1))
    out = panel.fused(obs(1, 0, 0))
    assert len(src.calls) == 2 and sorted(r.obs[0] for r in src.calls[1]) == [0.0, 0.0, 1.0, 1.0]
    assert out.unique == 2 and out.statuses[0].tolist() == ["ok", "abstained"]
    assert out.statuses[1:].tolist() == [["ok", "ok"]] * 2
    np.testing.assert_allclose(out.fused[1:], [[0.25, 0.5, 0.25, 0.0]] * 2)
    np.testing.assert_allclose(out.beliefs[2], [[0.5, 0.5, 0, 0], [0, 0.5, 0.5, 0]])
    np.testing.assert_allclose(out.weights[1], [0.5, 0.5])
    assert panel.stats.fallbacks == 2 and panel.stats.requests == 8


def test_invalid_beliefs_become_errors_that_abstain():
    bad = {("belief", "a", 3.0): [np.nan, 1, 0, 0], ("belief", "b", 3.0): [0.0, 0.0, 0.0, 0.0]}
    panel = MoralPanel("findmilk", ["a", "b"], Table(statuses=bad), "mean", action_names=ACTIONS)
    out = panel.fused(obs(3))
    np.testing.assert_allclose(out.fused[0], [0.25] * 4)
    assert out.statuses[0].tolist() == ["error", "error"]
    assert panel.stats.invalid == 2
    assert panel.stats.invalid_reasons == [
        "a: [nan, 1.0, 0.0, 0.0] holds nan at index 0 (not a finite number)",
        "b: [0.0, 0.0, 0.0, 0.0] sums to 0 (every value is zero)",
    ]
    # a vector off 1 by more than the tolerance is not a belief: [2, 2, 0, 0] is refused
    # (an "ok" answer must be a probability vector; only the reply parser repairs sums)
    off = {("belief", "a", 4.0): [2.0, 2.0, 0, 0], ("belief", "b", 4.0): [0.5, 0.5, 0, 0]}
    panel = MoralPanel("findmilk", ["a", "b"], Table(statuses=off), "mean", action_names=ACTIONS)
    out = panel.fused(obs(4))
    assert out.statuses[0].tolist() == ["error", "ok"]
    # a abstains: the fusion is b's belief alone (not mean(uniform, b) = .375/.375/.125/.125)
    np.testing.assert_allclose(out.fused[0], [0.5, 0.5, 0.0, 0.0])
    np.testing.assert_allclose(out.weights[0], [0.0, 1.0])
    # within 1e-6 of 1 it is a belief, divided by its sum: [.5 + 5e-7, .5, 0, 0]
    near = {("belief", c, 5.0): [0.5 + 5e-7, 0.5, 0, 0] for c in "ab"}
    panel = MoralPanel("findmilk", ["a", "b"], Table(statuses=near), "mean", action_names=ACTIONS)
    out = panel.fused(obs(5))
    assert out.statuses[0].tolist() == ["ok", "ok"]
    total = 1.0 + 5e-7
    np.testing.assert_allclose(out.beliefs[0, 0], [(0.5 + 5e-7) / total, 0.5 / total, 0, 0])


def fake_render(task, variables):
    return f"{task}: robot at x={variables['x']}"


def fake_build(cluster, task, state_prompt):
    return (("system", f"you are {cluster}"), ("user", f"{state_prompt}\n\nanswer as {cluster}"))


def test_messages_rendered_per_state_and_cluster():
    src = Table(needs_messages=True)
    panel = MoralPanel("findmilk", ["a", "b"], src, "mean", action_names=ACTIONS,
                       render_state_prompt=fake_render, build_messages=fake_build)  # fmt: skip
    vars_ = [{"x": 0}, {"x": 0}, {"x": 9}]
    panel.fused(obs(0, 0, 0), vars_)
    # same obs but different prompt variables are different states
    assert len(src.calls[0]) == 4
    msgs = {(r.cluster, r.messages) for r in src.calls[0]}
    assert (
        "b",
        (("system", "you are b"), ("user", "findmilk: robot at x=9\n\nanswer as b")),
    ) in msgs
    with pytest.raises(ValueError, match="prompt_vars must hold 3"):
        panel.fused(obs(0, 0, 0), vars_[:2])


def test_template_shortcut_matches_build_messages():
    from amuled_ma.clusters import build_messages

    panel = MoralPanel("findmilk", ["care", "moral_agent"], Table(needs_messages=True), "mean",
                       action_names=ACTIONS, render_state_prompt=fake_render)  # fmt: skip
    state = "Robot at x=2.0, y=3.0. {not a field} \\n 100% sure"
    for i, name in enumerate(["care", "moral_agent"]):
        assert panel.messages(i, state) == build_messages(name, "findmilk", state)
    assert panel._templates  # the shortcut is in use


def test_with_cached_source_second_panel_sends_nothing(tmp_path):
    src = Table()
    with BeliefStore(tmp_path / "p.sqlite") as store:
        MoralPanel("findmilk", ["a", "b"], CachedSource(src, store), "mean",
                   action_names=ACTIONS).fused(obs(0, 1))  # fmt: skip
        again = CachedSource(Table(), store)
        out = MoralPanel("findmilk", ["a", "b"], again, "mean", action_names=ACTIONS).fused(
            obs(1, 0)
        )
        assert again.stats.sent == 0 and again.stats.store_hits == 4
        np.testing.assert_allclose(out.fused[0], [0.5, 0, 0, 0.5])


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"unknown|rule"):
        MoralPanel("findmilk", ["a"], Table(), "no-such-rule", action_names=ACTIONS)
    with pytest.raises(ValueError, match="duplicate"):
        MoralPanel("findmilk", ["a", "a"], Table(), action_names=ACTIONS)
    panel = MoralPanel("findmilk", ["a"], Table(), action_names=ACTIONS)
    with pytest.raises(ValueError, match=r"\(N, obs_dim\)"):
        panel.fused(np.zeros(3))


def test_replay_of_recording_through_the_panel(load_recording, recordings_dir):
    """The panel on the authors' gpt-4o-mini recording returns the recorded beliefs."""
    from amuled_ma.beliefs.sources.replay import ReplaySource
    from amuled_ma.fusion import fuse

    rec = load_recording("findmilk-gpt-4o-mini.json")
    states = rec["states"][:300]
    ours = ["consequentialist", "deontological", "virtue", "care", "social_justice"]
    source = ReplaySource(recordings_dir / "findmilk-gpt-4o-mini.json")
    panel = MoralPanel("findmilk", ours, source, action_names=tuple(rec["actions"]))
    batch = np.array([s["obs"] for s in states] * 2)  # every state twice
    out = panel.fused(batch)
    recorded = np.array([[s["beliefs"][c] for c in rec["clusters"]] for s in states] * 2)
    np.testing.assert_allclose(out.beliefs, recorded, rtol=0, atol=1e-12)
    assert out.unique == len(states) and (out.statuses == "ok").all()
    np.testing.assert_allclose(out.fused, fuse(recorded), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.weights.sum(axis=1), 1.0)
