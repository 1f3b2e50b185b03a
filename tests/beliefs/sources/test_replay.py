"""ReplaySource: the authors' recordings answered offline, keyed by observation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest, ScriptedSource, make_source
from amuled_ma.beliefs.sources.replay import ReplaySource, obs_key
from amuled_ma.errors import ReplayMiss, ScenarioError

MILK = ("up", "down", "left", "right")
OURS = {
    "consequentialist": "consequentialist",
    "deontological": "deontologist",
    "virtue": "virtue",
    "care": "care",
    "social_justice": "social justice",
}


def request(cluster, obs, task="findmilk", actions=MILK):
    return BeliefRequest(task=task, cluster=cluster, obs=tuple(obs), action_names=actions)


@pytest.fixture
def tiny_recording(tmp_path):
    data = {
        "task": "FindMilk",
        "model": "test",
        "clusters": ["consequentialist", "deontologist", "virtue", "care", "social justice"],
        "actions": list(MILK),
        "obs_layout": [],
        "states": [
            {
                "obs": [1.0, 2.0],
                "beliefs": {
                    "consequentialist": [0.1, 0.2, 0.3, 0.4],
                    "deontologist": [1.0, 0.0, 0.0, 0.0],
                    "virtue": [0.25] * 4,
                    "care": [0.0, 1.0, 0.0, 0.0],
                    "social justice": [0.0, 0.0, 1.0, 0.0],
                },
                "moral_agent": [0.0, 0.0, 0.0, 1.0],
                "error": True,
                "exchanges": [{"agent": "care", "prompt": "P", "response": "R"}],
            }
        ],
    }
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(data))
    return path


def test_every_recorded_belief_is_replayed(recordings_dir, load_recording):
    # Every real recording passes the belief check; "beliefs": null (the fused-only
    # driving-gpt-4o-mini.json) means not recorded: a miss, not a crash.
    for path in sorted(recordings_dir.glob("*.json")):
        recording = load_recording(path.name)
        source = ReplaySource(path, miss_policy="uniform")
        task = recording["task"].lower()
        actions = tuple(recording["actions"])
        requests, expected = [], []
        for state in recording["states"]:
            for ours, theirs in OURS.items():
                requests.append(request(ours, state["obs"], task, actions))
                expected.append((state["beliefs"] or {}).get(theirs))
            requests.append(request("moral_agent", state["obs"], task, actions))
            expected.append(state["moral_agent"])
        results = source.beliefs(requests)
        recorded = sum(want is not None for want in expected)
        assert source.misses == len(requests) - recorded and source.hits == recorded
        for result, want in zip(results, expected, strict=True):
            if want is None:
                assert result.status == "replay_miss"
                continue
            assert result.status == "ok"
            assert np.allclose(result.belief, np.asarray(want) / np.sum(want), atol=1e-12)
            assert abs(result.belief.sum() - 1) < 1e-12


def test_names_mapping_and_raw_reply(tiny_recording):
    source = ReplaySource(tiny_recording)
    care, deon, sj, ma = source.beliefs(
        [request(c, [1, 2]) for c in ("care", "deontological", "social justice", "moral_agent")]
    )
    assert care.raw == "R" and deon.raw is None
    assert np.allclose(deon.belief, [1, 0, 0, 0])
    assert np.allclose(sj.belief, [0, 0, 1, 0])
    assert np.allclose(ma.belief, [0, 0, 0, 1])
    explicit = ReplaySource(tiny_recording, cluster_names={"kantian": "deontologist"})
    assert np.allclose(explicit.beliefs([request("kantian", [1, 2])])[0].belief, [1, 0, 0, 0])


def test_rounding_of_observation_keys(tiny_recording):
    source = ReplaySource(tiny_recording, decimals=3)
    (result,) = source.beliefs([request("care", [1.0000001, 1.9999999])])
    assert result.status == "ok"
    assert obs_key([-0.0, 0.12345], 3) == (0.0, 0.123)


def test_miss_policy_error(tiny_recording):
    source = ReplaySource(tiny_recording)
    with pytest.raises(ReplayMiss, match=r"state \[5, 5\] not in tiny.json"):
        source.beliefs([request("care", [5, 5])])
    assert source.misses == 1


def test_miss_policy_uniform_counts(tiny_recording):
    source = ReplaySource(tiny_recording, miss_policy="uniform")
    results = source.beliefs(
        [request("care", [5, 5]), request("care", [1, 2]), request("guardian", [1, 2])]
    )
    assert [r.status for r in results] == ["replay_miss", "ok", "replay_miss"]
    assert np.allclose(results[0].belief, 0.25)
    assert "guardian" in results[2].extra["miss_reason"]
    assert source.misses == 2 and source.hits == 1
    assert source.misses_by_cluster == {"care": 1, "guardian": 1}
    (other_task,) = source.beliefs([request("care", [1, 2], task="driving", actions=MILK[:3])])
    assert other_task.status == "replay_miss"


def test_miss_policy_fallback(tiny_recording):
    fallback = ScriptedSource({"*": [0, 0, 0, 1]})
    source = ReplaySource(tiny_recording, miss_policy="fallback", fallback=fallback)
    hit, miss = source.beliefs([request("care", [1, 2]), request("care", [9, 9])])
    assert hit.source == "replay" and miss.source == "scripted"
    assert miss.status == "ok" and miss.extra["replay_miss"] is True
    assert np.allclose(miss.belief, [0, 0, 0, 1])
    assert source.identity()["fallback"]["source"] == "scripted"
    built = make_source(
        "replay",
        paths=tiny_recording,
        miss_policy="fallback",
        fallback={"kind": "rules", "policy": "human"},
    )
    (built_miss,) = built.beliefs([request("care", [9, 9])])
    assert built_miss.source == "rules" and built_miss.extra["replay_miss"] is True


def test_bad_configuration(tiny_recording, tmp_path):
    with pytest.raises(ScenarioError, match="miss_policy"):
        ReplaySource(tiny_recording, miss_policy="maybe")
    with pytest.raises(ScenarioError, match="needs a fallback"):
        ReplaySource(tiny_recording, miss_policy="fallback")
    with pytest.raises(ScenarioError, match="cannot read recording"):
        ReplaySource(tmp_path / "absent.json")
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ScenarioError, match="no 'task' field"):
        ReplaySource(tmp_path / "bad.json")
    with pytest.raises(ScenarioError, match="4 actions"):
        ReplaySource(tiny_recording).beliefs([request("care", [1, 2], actions=("a", "b"))])


def test_identity_hashes_content(tiny_recording):
    ident = ReplaySource(tiny_recording).identity()
    assert ident["source"] == "replay"
    assert len(ident["recordings"][0]["sha256"]) == 64
    assert ReplaySource(tiny_recording).needs_messages is False
