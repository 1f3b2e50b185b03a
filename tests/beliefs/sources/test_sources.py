"""make_source registry, rules and scripted sources, entry-point agents."""

from __future__ import annotations

import json
import sys
import types
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
import torch

from amuled_ma.beliefs import (
    BeliefRequest,
    BeliefSource,
    RulesSource,
    ScriptedSource,
    make_source,
    register_source,
    source_kinds,
)
from amuled_ma.beliefs.sources.registry import built_in
from amuled_ma.clusters import plugins
from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import AGENT_SPECS

MILK = ("up", "down", "left", "right")


def req(cluster="care", obs=(1.0, 2.0), task="findmilk"):
    return BeliefRequest(task=task, cluster=cluster, obs=obs, action_names=MILK)


def test_builtin_kinds():
    assert set(AGENT_SPECS) <= set(source_kinds())
    with pytest.raises(ScenarioError, match="unknown belief source kind 'psychic'"):
        make_source("psychic")
    with pytest.raises(ScenarioError, match="bad options"):
        make_source("rules", colour="blue")
    # scripted answers are built in code (ScriptedSource), never named by a scenario
    with pytest.raises(ScenarioError, match="unknown belief source kind 'scripted'"):
        make_source("scripted")


def kind_options(kind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict:
    """Options that build each kind a scenario may name, from files made here."""
    if kind == "replay":
        recording = {
            "task": "FindMilk", "model": "test", "clusters": ["care"], "actions": list(MILK),
            "obs_layout": [], "states": [{"obs": [1.0, 2.0], "beliefs": {"care": [0, 1, 0, 0]}}],
        }  # fmt: skip
        (tmp_path / "rec.json").write_text(json.dumps(recording))
        return {"paths": str(tmp_path / "rec.json")}
    if kind == "policy":
        torch.save(torch.nn.Sequential(torch.nn.Linear(2, 4)).state_dict(), tmp_path / "p.pt")
        return {"path": str(tmp_path / "p.pt")}
    if kind == "entry-point":
        module = types.ModuleType("amuled_test_kinds")
        module.Fixed = lambda: ScriptedSource({"*": [0, 0, 1, 0]})
        monkeypatch.setitem(sys.modules, "amuled_test_kinds", module)
        monkeypatch.setattr(plugins, "_ALLOWED", frozenset({"amuled_test_kinds:Fixed"}))
        return {"name": "amuled_test_kinds:Fixed"}
    return {
        "ollama": {"model": "amuled-tiny", "host": "http://127.0.0.1:9"},
        "rules": {"policy": "human"},
        "terminal": {"person": "ana"},
    }[kind]


@pytest.mark.parametrize("kind", sorted(AGENT_SPECS))
def test_every_kind_a_scenario_may_name_is_built(kind, tmp_path, monkeypatch):
    source = make_source(kind, **kind_options(kind, tmp_path, monkeypatch))
    assert isinstance(source, BeliefSource)
    # the entry-point kind builds the plug-in's own source; every other kind its namesake
    assert source.name == ("scripted" if kind == "entry-point" else kind)
    source.close()


def test_every_built_in_source_can_be_named():
    assert set(built_in()) == set(AGENT_SPECS.values())


def test_scripted_table_and_function():
    source = ScriptedSource({"care": [0, 2, 0, 0], "*": [1, 1, 1, 1]})
    care, other = source.beliefs([req("care"), req("virtue")])
    assert np.allclose(care.belief, [0, 1, 0, 0]) and care.status == "ok"
    assert np.allclose(other.belief, 0.25)
    fn = ScriptedSource(lambda r: [r.obs[0], 0, 0, 0], label="first")
    assert np.allclose(fn.beliefs([req()])[0].belief, [1, 0, 0, 0])
    assert fn.identity() == {"source": "scripted", "label": "first"}
    broken = ScriptedSource(lambda r: 1 / 0)
    assert broken.beliefs([req()])[0].status == "error"


@pytest.mark.parametrize(
    ("values", "status"),
    [
        ([1, 1, 0, 0], "ok"),
        ([-1, 1, 0, 0], "error"),  # negative scores are refused, not clipped
        ([1e308, 1e308, 0, 0], "error"),  # the sum overflows to inf
        ([np.inf, 0, 0, 0], "error"),
        ([0, 0, 0, 0], "error"),
        ([np.nan, 1, 0, 0], "error"),
        ([1, 2], "error"),
        ("x", "error"),
    ],
)
def test_scores_divided_by_their_sum_or_an_error(values, status):
    result = ScriptedSource({"*": values}).beliefs([req()])[0]
    belief, got = result.belief, result.status
    assert got == status
    assert belief.shape == (4,) and np.isclose(belief.sum(), 1) and np.all(belief >= 0)


def test_rules_with_a_callable_and_a_module_path(monkeypatch):

    monkeypatch.setattr(
        plugins, "_ALLOWED", frozenset({"amuled_test_rules:rule", "no_such_module_xyz:rule"})
    )
    source = RulesSource(lambda task, obs: [0, 0, 1, 0])
    assert np.allclose(source.beliefs([req()])[0].belief, [0, 0, 1, 0])
    module = types.ModuleType("amuled_test_rules")
    module.rule = lambda task, obs: [0, 0, 0, 1] if task == "findmilk" else [1, 0, 0, 0]
    sys.modules["amuled_test_rules"] = module
    try:
        source = make_source("rules", policy="amuled_test_rules:rule")
        assert np.allclose(source.beliefs([req()])[0].belief, [0, 0, 0, 1])
        assert source.identity() == {"source": "rules", "policy": "amuled_test_rules:rule"}
    finally:
        del sys.modules["amuled_test_rules"]
    with pytest.raises(ScenarioError, match="cannot import"):
        RulesSource("no_such_module_xyz:rule")
    failing = RulesSource(lambda task, obs: 1 / 0)
    assert failing.beliefs([req()])[0].status == "error"


def test_rules_human_policy_uses_the_tasks_module():
    pytest.importorskip(
        "amuled_ma.tasks.human", reason="tasks engineer's human policies not landed"
    )
    source = RulesSource("human")
    result = source.beliefs([req(obs=(0.0, 0.0, 3.0, 3.0, 1.0, 0.0, 0.0, 1.0))])[0]
    assert result.belief.shape == (4,) and np.isclose(result.belief.sum(), 1)


def test_registered_kind_and_entry_point(monkeypatch):
    class Constant(BeliefSource):
        name = "constant"

        def __init__(self, index=0):
            self.index = index

        def beliefs(self, requests):
            return ScriptedSource({"*": np.eye(4)[self.index]}).beliefs(requests)

    register_source("constant", Constant)
    assert make_source("constant", index=2).beliefs([req()])[0].belief[2] == 1.0

    module = types.ModuleType("amuled_test_plugin")
    module.Plugin = Constant
    sys.modules["amuled_test_plugin"] = module
    point = EntryPoint("plugged", "amuled_test_plugin:Plugin", "amuled_ma.agents")
    monkeypatch.setattr(
        "amuled_ma.clusters.plugins.entry_points",
        lambda group: [point] if group == "amuled_ma.agents" else [],
    )
    try:
        assert "plugged" in source_kinds()
        assert make_source("plugged", index=1).beliefs([req()])[0].belief[1] == 1.0
    finally:
        del sys.modules["amuled_test_plugin"]


def test_factory_must_build_a_source():
    register_source("notasource", lambda: object())
    with pytest.raises(ScenarioError, match="did not build a BeliefSource"):
        make_source("notasource")


def test_rules_batch_call_and_per_request_fallback():
    calls = []

    def batched(task, obs):
        calls.append(obs.shape)
        return np.tile([1.0, 0, 0, 0], (len(obs), 1)) if obs.ndim == 2 else [1.0, 0, 0, 0]

    results = RulesSource(batched).beliefs([req(obs=(float(i), 0.0)) for i in range(5)])
    assert calls == [(5, 2)] and all(r.belief[0] == 1.0 for r in results)

    def single_only(task, obs):
        calls.append(obs.shape)
        return [0, obs[0], 0, 1]

    calls.clear()
    results = RulesSource(single_only).beliefs([req(obs=(1.0, 0.0)), req(obs=(3.0, 0.0))])
    assert calls == [(2, 2), (2,), (2,)]
    assert np.allclose(results[1].belief, [0, 0.75, 0, 0.25])


def test_a_batch_with_a_request_left_unanswered_is_refused_naming_the_source():
    from amuled_ma.beliefs.types import BeliefResult, in_order

    one = BeliefResult(np.array([0.5, 0.5]), "ok", "rules")
    assert in_order([(1, one), (0, one)], 2, "rules") == [one, one]
    with pytest.raises(RuntimeError, match=r"'rules' left 1 request\(s\) without a result"):
        in_order([(1, one)], 2, "rules")
