"""LLM-cache pickle -> recording JSON: every value as pickled, and the file loads for replay."""

import json

import numpy as np
import pytest
from authors_fakes import (
    CLUSTERS,
    driving_cache,
    driving_fused_only_cache,
    findmilk_cache,
    write_pickle,
)

from amuled_ma.authors.caches import (
    convert_cache,
    exchange_agent,
    model_slug,
)
from amuled_ma.beliefs.sources.replay import Recording, obs_key
from amuled_ma.errors import AuthorsImportError


def write_recording(tmp_path, converted):
    path = tmp_path / f"{converted.task}-{model_slug(converted.model)}.json"
    path.write_text(converted.to_json())
    return path


def test_findmilk_cache_values_as_pickled(tmp_path):
    cache = findmilk_cache()
    path = write_pickle(tmp_path / "FindMilk-v4_42" / "gpt-4o-mini_llm_cache.pickle", cache)
    converted = convert_cache(path)
    assert (converted.task, converted.model) == ("findmilk", "gpt-4o-mini")
    data = json.loads(converted.to_json())
    assert data["task"] == "FindMilk" and data["model"] == "gpt-4o-mini"
    assert data["clusters"] == list(CLUSTERS)
    assert data["actions"] == ["up", "down", "left", "right"]
    assert data["obs_layout"] == ["x", "y", "milk_x", "milk_y", "cry_x", "cry_y", "sleep_x",
                                  "sleep_y"]  # fmt: skip
    assert len(data["states"]) == len(cache)
    for (key, entry), state in zip(cache.items(), data["states"], strict=True):
        assert state["obs"] == [float(x) for x in key]
        assert state["beliefs"] == {c: entry[c].tolist() for c in CLUSTERS}
        assert state["moral_agent"] == entry["moral"].tolist()
        fused = [float(entry["rewards"][frozenset({str(a)})]) for a in range(4)]
        assert state["fused_by_reference"] == fused
        assert state["error"] is bool(entry.get("error", False))
        assert "total_conflict" not in state
    flagged = data["states"][1]
    replies = findmilk_cache()[next(k for i, k in enumerate(cache) if i == 1)]["response"]
    assert [e["prompt"] for e in flagged["exchanges"]] == list(replies)
    assert [e["response"] for e in flagged["exchanges"]] == list(replies.values())
    agents = [e["agent"] for e in flagged["exchanges"]]
    assert agents == ["care", "moral_agent", "consequentialist", "virtue", "social justice",
                      "deontologist"]  # fmt: skip
    assert all("exchanges" not in s for i, s in enumerate(data["states"]) if i != 1)
    assert (converted.errors, converted.exchanges, converted.fused_only) == (1, 1, False)


def test_converted_recording_replays_the_pickled_beliefs(tmp_path):
    cache = findmilk_cache()
    path = write_pickle(tmp_path / "FindMilk-v4_42" / "gpt-4o-mini_llm_cache.pickle", cache)
    recording = Recording(write_recording(tmp_path, convert_cache(path)))
    assert len(recording.states) == len(cache)
    for key, entry in cache.items():
        state = {"obs": [float(x) for x in key]}
        belief, _raw = recording.answer(state, "deontologist")
        np.testing.assert_allclose(belief, entry["deontologist"], rtol=0, atol=1e-15)
        moral, _ = recording.answer(state, "moral_agent")
        np.testing.assert_allclose(moral, entry["moral"], rtol=0, atol=1e-15)
    recorded = recording.states[obs_key(list(cache)[1], recording.decimals)]
    _belief, raw = recording.answer(recorded, "care")
    assert raw == 'reply of care: {"0": 0.5}'


def test_fused_only_cache_keeps_all_zero_states_flagged(tmp_path):
    cache = driving_fused_only_cache()
    path = write_pickle(tmp_path / "Drive" / "gpt-4o-mini_llm_cache.pickle", cache)
    converted = convert_cache(path)
    assert (converted.task, converted.fused_only, converted.total_conflicts) == ("driving", True, 1)
    data = json.loads(converted.to_json())
    assert data["task"] == "Driving" and data["actions"] == ["straight", "right", "left"]
    for i, ((key, entry), state) in enumerate(zip(cache.items(), data["states"], strict=True)):
        assert state["obs"] == [float(x) for x in key]
        assert state["beliefs"] is None and state["moral_agent"] is None
        fused = [float(entry["rewards"][frozenset({str(a)})]) for a in range(3)]
        assert state["fused_by_reference"] == fused
        assert state["error"] is False
        assert state.get("total_conflict", False) is (i == 2)
    assert data["states"][2]["fused_by_reference"] == [0.0, 0.0, 0.0]
    # it loads: every cluster is "not recorded" (a replay miss), not an invalid belief
    recording = Recording(write_recording(tmp_path, converted))
    assert recording.answer({"obs": data["states"][0]["obs"]}, "care") is None


def test_invalid_belief_written_as_null_with_reason(tmp_path):
    cache = driving_cache(states=2)
    key = next(iter(cache))
    cache[key]["virtue"] = np.array([0.2, 0.2, 0.1])  # sums to 0.5
    path = write_pickle(tmp_path / "Driving_42" / "llama-3.1-8B_llm_cache.pickle", cache)
    converted = convert_cache(path)
    state = converted.recording["states"][0]
    assert "virtue" not in state["beliefs"] or state["beliefs"]["virtue"] is None
    assert "virtue" in state["invalid_beliefs"] and "0.5" in state["invalid_beliefs"]["virtue"]
    assert converted.invalid == 1
    recording = Recording(write_recording(tmp_path, converted))  # loads despite the bad one
    assert recording.answer({"obs": state["obs"]}, "virtue") is None
    assert recording.answer({"obs": state["obs"]}, "care") is not None


def test_task_from_folder_or_observation_length(tmp_path):
    path = write_pickle(tmp_path / "elsewhere" / "m_llm_cache.pickle", driving_cache(states=1))
    assert convert_cache(path).task == "driving"
    wrong = write_pickle(tmp_path / "FindMilk-v4_42" / "m_llm_cache.pickle", driving_cache())
    with pytest.raises(AuthorsImportError, match="observations of 11 values, but FindMilk has 8"):
        convert_cache(wrong)


def test_malformed_entries_named(tmp_path):
    cache = findmilk_cache(states=3)
    key = list(cache)[2]
    del cache[key]["rewards"][frozenset({"3"})]
    path = write_pickle(tmp_path / "FindMilk-v4_42" / "x_llm_cache.pickle", cache)
    with pytest.raises(AuthorsImportError, match=r"state 2 \(obs \[2.0, 1.0.*'rewards' must map"):
        convert_cache(path)
    cache = findmilk_cache(states=2)
    cache[next(iter(cache))]["care"] = np.zeros((2, 2))
    path = write_pickle(tmp_path / "FindMilk-v4_42" / "y_llm_cache.pickle", cache)
    with pytest.raises(AuthorsImportError, match="'care' must be 4 numbers"):
        convert_cache(path)
    path = write_pickle(tmp_path / "FindMilk-v4_42" / "z_llm_cache.pickle", [1, 2])
    with pytest.raises(AuthorsImportError, match="found list"):
        convert_cache(path)


def test_names_like_ours():
    assert model_slug("gpt-4o-mini") == "gpt-4o-mini"
    assert model_slug("llama-3.1-70B") == "llama-3_1-70b"
    assert model_slug("llama-3.1-8B") == "llama-3_1-8b"
    assert model_slug("mistral-nemo") == "mistral-nemo"
    assert model_slug("../evil name") == "__-evil-name"  # one safe file-name part


def test_exchange_agent_from_credences_else_call_order():
    prompt = "x credence values: {Consequentialist: 0.0, Deontological: 1.0, Virtue Ethics: 0.0}"
    assert exchange_agent(prompt, 4) == "deontologist"
    assert exchange_agent("Behave as moral agent.", 0) == "moral_agent"
    assert exchange_agent("credence values: {Virtue Ethics: 0.5, Care Ethics: 0.5}", 3) == "care"


@pytest.mark.parametrize(
    ("value", "found"),
    [
        (np.arange(6.0), "found ndarray of shape (6,) and dtype float64"),
        (np.zeros((2, 3), dtype=np.int64), "found ndarray of shape (2, 3) and dtype int64"),
        (10**5000, "found int"),  # its repr would be refused (4,300 digits at most)
        ({}, "found an empty dict"),
    ],
    ids=["array", "matrix", "huge int", "empty dict"],
)
def test_a_cache_that_is_not_a_dict_is_one_line(tmp_path, capsys, value, found):
    from amuled_ma.cli import main

    path = write_pickle(
        tmp_path / "models" / "FindMilk-v4_42" / "gpt-4o-mini_llm_cache.pickle", value
    )
    with pytest.raises(AuthorsImportError, match=r"expected the authors' LLM cache") as info:
        convert_cache(path)
    assert found in str(info.value)
    # and through the command: one line, no traceback (numpy's truth value of an array)
    runs, out = tmp_path / "runs", tmp_path / "rec"
    assert main(["import", "authors", str(tmp_path), "--runs", str(runs), "--to", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("amuled: error: ") and err.count("\n") == 1 and found in err
