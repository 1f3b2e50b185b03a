"""Replay of a recording that keeps only the fused belief, and reward 0 for a miss."""

import json

import numpy as np
import pytest
import torch
from job_settings import train_variant
from scenario_feedback import make_feedback

from amuled_ma.deliberation.panel_feedback import FusedReplayFeedback, PanelFeedback
from amuled_ma.errors import ScenarioError
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

STRAIGHT = [-1.0] * 6 + [0.0, 0.0, 1.0, 0.0, 0.0]  # empty road, lane 2
CAR_AHEAD = [3.0, -1.0, -1.0, -1.0, -1.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0]
UNKNOWN = [1.0, 2.0, -1.0, -1.0, -1.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0]


def _fused_only(tmp_path) -> str:
    """A two-state fused-only recording in the authors' layout (one total conflict)."""
    states = [
        {"obs": STRAIGHT, "beliefs": None, "moral_agent": None,
         "fused_by_reference": [0.9, 0.05, 0.05], "error": False},
        {"obs": CAR_AHEAD, "beliefs": None, "moral_agent": None,
         "fused_by_reference": [0.0, 0.0, 0.0], "error": False},
    ]  # fmt: skip
    data = {
        "task": "Driving", "model": "gpt-4o-mini",
        "clusters": ["consequentialist", "deontologist", "virtue", "care", "social justice"],
        "actions": ["straight", "right", "left"], "states": states,
    }  # fmt: skip
    path = tmp_path / "driving-fused.json"
    path.write_text(json.dumps(data))
    return str(path)


def _scenario(recording: str, **feedback):
    sc = load_scenario("driving").replace("feedback", recording=recording, **feedback)
    return sc.replace("output", tensorboard=False)


def test_fused_only_recording_is_the_amuled_feedback(tmp_path):
    feedback = make_feedback("amuled", _scenario(_fused_only(tmp_path), miss_policy="zero"))
    assert isinstance(feedback, FusedReplayFeedback)
    out = feedback(torch.tensor([STRAIGHT, CAR_AHEAD, UNKNOWN]), task=None)
    assert out.tolist() == [[0.9, 0.05, 0.05], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    report = feedback.summary()["agents"]["fused (recorded)"]
    assert (report["ok"], report["total_conflict"], report["replay_miss"]) == (1, 1, 1)
    uniform = make_feedback("amuled", _scenario(_fused_only(tmp_path), miss_policy="uniform"))
    assert uniform(torch.tensor([UNKNOWN]), task=None)[0] == pytest.approx([1 / 3] * 3)


@pytest.mark.parametrize("variant", ["cluster:care", "moral", "agg:mean"])
def test_variants_needing_cluster_beliefs_are_refused_before_training(tmp_path, variant):
    recording = _fused_only(tmp_path)
    with pytest.raises(ScenarioError, match="keeps only the authors' fused belief") as err:
        make_feedback(variant, _scenario(recording))
    assert recording in str(err.value) and "driving-llama-3_1-70b" in str(err.value)


def test_another_fusion_rule_is_refused(tmp_path):
    with pytest.raises(ScenarioError, match="bjs-dst"):
        make_feedback("amuled", _scenario(_fused_only(tmp_path), fusion="mean"))


def test_the_papers_driving_cache_replays(recordings_dir, tmp_path):
    """The authors' 6,704-state gpt-4o-mini Driving cache: every state gives its fused belief."""
    path = recordings_dir / "driving-gpt-4o-mini.json"
    states = json.loads(path.read_text())["states"]
    feedback = make_feedback("amuled", _scenario(str(path), miss_policy="zero"))
    obs = torch.tensor([s["obs"] for s in states[:500]])
    got = feedback(obs, task=None)
    for row, state in zip(got, states[:500], strict=True):
        ref = np.asarray(state["fused_by_reference"])
        assert row == pytest.approx(ref / ref.sum() if ref.any() else ref, abs=1e-12)
    # a short AMULED fine-tune on it trains (the fused belief is the reward)
    sc = _scenario(str(path), miss_policy="zero").replace(
        "base", total_steps=512, num_envs=16, num_steps_per_env=16
    )
    sc = sc.replace("finetune", iterations=2, num_envs=4, num_steps_per_env=8)
    train_variant(sc, tmp_path / "run", Variant("base"))
    job = train_variant(sc, tmp_path / "run", Variant.finetune("amuled"))
    assert job.outcome.feedback["agents"]["fused (recorded)"]["total"] == 2 * 4 * 8


def test_a_state_every_cluster_missed_rewards_zero_with_miss_policy_zero(tmp_path):
    data = {
        "task": "Driving", "model": "m", "actions": ["straight", "right", "left"],
        "clusters": ["consequentialist", "deontologist", "virtue", "care", "social justice"],
        "states": [{"obs": STRAIGHT, "fused_by_reference": None, "moral_agent": None,
                    "beliefs": {c: [0.8, 0.1, 0.1] for c in
                                ("consequentialist", "deontologist", "virtue", "care",
                                 "social justice")}}],
    }  # fmt: skip
    path = tmp_path / "driving-small.json"
    path.write_text(json.dumps(data))
    sc = _scenario(str(path), miss_policy="zero", store=str(tmp_path / "s.sqlite"))
    feedback = make_feedback("amuled", sc, tmp_path)
    assert isinstance(feedback, PanelFeedback) and feedback.miss_zero
    out = feedback(torch.tensor([STRAIGHT, UNKNOWN]), task=None)
    # five identical beliefs fuse to m^5 / sum(m^5) (Dempster's rule applied k - 1 times)
    total = 0.8**5 + 2 * 0.1**5
    assert out[0] == pytest.approx([0.8**5 / total, 0.1**5 / total, 0.1**5 / total], abs=1e-9)
    assert out[1].tolist() == [0.0, 0.0, 0.0]
    feedback.close()
