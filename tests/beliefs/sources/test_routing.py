"""RoutedSource: a batch split by agent, one call per member source, answers in order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.beliefs.sources.routing import RoutedSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.deliberation.build import build_members
from amuled_ma.deliberation.plan import PanelPlan
from amuled_ma.deliberation.plan import SourcePlan as SourceSpec
from amuled_ma.errors import BackendUnavailable, ScenarioError

MILK = ("up", "down", "left", "right")


class _Named:
    def __init__(self, name: str) -> None:
        self.name = name


def plan_of(routes: dict, default) -> PanelPlan:
    """A panel plan of ``routes`` plus one agent on the default source."""
    agents = (*routes, "consequentialist")
    return PanelPlan(
        variant="amuled", kind="amuled", task="findmilk", where="s.toml", seed=1,
        clusters=tuple(_Named(a) for a in agents), routes=routes, default=default,
    )  # fmt: skip


CHAT = (("system", "You are a moral agent."), ("user", "State: x=1."))


class Recorder(BeliefSource):
    """Answers a one-hot belief on its own action index; records every call."""

    def __init__(self, label: str, index: int, *, needs_messages: bool = False) -> None:
        self.name = label
        self.index = index
        self.needs_messages = needs_messages
        self.calls: list[list[BeliefRequest]] = []
        self.closed = 0

    def beliefs(self, requests):
        self.calls.append(list(requests))
        return [
            BeliefResult(np.eye(4)[self.index], "ok", self.name, raw=f"{self.name}:{r.cluster}")
            for r in requests
        ]

    def identity(self):
        return {"source": self.name, "index": self.index}

    def close(self):
        self.closed += 1


def req(cluster: str, obs: tuple[float, ...] = (1.0, 2.0), messages=CHAT) -> BeliefRequest:
    return BeliefRequest(
        task="findmilk", cluster=cluster, obs=obs, action_names=MILK, messages=messages
    )


def panel_batch() -> list[BeliefRequest]:
    """Two states x four agents, in the panel's order (state-major, as MoralPanel sends)."""
    return [req(c, obs) for obs in ((1.0, 2.0), (3.0, 4.0)) for c in ("a", "b", "c", "d")]


def test_a_batch_is_split_across_three_sources_each_called_once_in_order():
    one, two, three = Recorder("one", 0), Recorder("two", 1), Recorder("three", 2)
    routed = RoutedSource({"a": one, "b": two, "c": three, "d": three})
    batch = panel_batch()
    results = routed.beliefs(batch)

    assert [len(s.calls) for s in (one, two, three)] == [1, 1, 1]
    assert [r.cluster for r in one.calls[0]] == ["a", "a"]
    assert [r.cluster for r in two.calls[0]] == ["b", "b"]
    assert [(r.cluster, r.obs) for r in three.calls[0]] == [
        ("c", (1.0, 2.0)),
        ("d", (1.0, 2.0)),
        ("c", (3.0, 4.0)),
        ("d", (3.0, 4.0)),
    ]
    # answers back in the batch's order: agent a -> action 0, b -> 1, c and d -> 2
    assert [int(np.argmax(r.belief)) for r in results] == [0, 1, 2, 2] * 2
    assert [r.raw for r in results[:4]] == ["one:a", "two:b", "three:c", "three:d"]
    assert len(routed.members) == 3  # "three" serves c and d: one member, not two


def test_default_source_answers_agents_without_a_route():
    care, rest = Recorder("care", 3), Recorder("rest", 0)
    routed = RoutedSource({"care": care}, rest)
    results = routed.beliefs([req("virtue"), req("care"), req("deontological")])
    assert [int(np.argmax(r.belief)) for r in results] == [0, 3, 0]
    assert [r.cluster for r in rest.calls[0]] == ["virtue", "deontological"]
    assert routed.source_for("anyone") is rest


def test_an_agent_without_a_route_or_default_is_an_error_naming_it():
    routed = RoutedSource({"care": Recorder("care", 0)})
    with pytest.raises(ScenarioError, match=r"no belief source for agent 'virtue'.*care"):
        routed.beliefs([req("virtue")])
    with pytest.raises(ValueError, match="at least one route"):
        RoutedSource({})


def test_store_keys_hold_each_agents_source_identity(tmp_path):
    store = BeliefStore(tmp_path / "beliefs.sqlite")
    one, two, three = Recorder("one", 0), Recorder("two", 1), Recorder("three", 2)
    cached = {s.name: CachedSource(s, store) for s in (one, two, three)}
    routed = RoutedSource(
        {"a": cached["one"], "b": cached["two"], "c": cached["three"], "d": cached["three"]}
    )
    batch = panel_batch()
    routed.beliefs(batch)

    rows = list(store.iter_rows())
    assert len(rows) == 8  # one row per (state, agent): nothing shared across agents
    assert {(row.cluster, row.identity["source"]) for row in rows} == {
        ("a", "one"),
        ("b", "two"),
        ("c", "three"),
        ("d", "three"),
    }
    # the same request keyed with two sources' identities gives two keys
    request = batch[0]
    assert cached["one"].keys([request]) != cached["two"].keys([request])
    # the member reads no chat, so its rows are keyed without it (as a lone replay's are)
    asked = [dataclasses.replace(r, messages=()) for r in batch if r.cluster == "a"]
    assert {row.key for row in rows if row.cluster == "a"} == set(cached["one"].keys(asked))

    # a second run is answered by the store: no member is asked again
    again = RoutedSource(
        {"a": CachedSource(Recorder("one", 0), store), "b": cached["two"], "c": cached["three"]},
        cached["three"],
    )
    results = again.beliefs(batch)
    assert all(r.cached for r in results)
    assert [len(s.calls) for s in (one, two, three)] == [1, 1, 1]
    assert [int(np.argmax(r.belief)) for r in results] == [0, 1, 2, 2] * 2
    store.close()


def test_messages_go_only_to_members_that_read_them():
    llm, rule = Recorder("llm", 0, needs_messages=True), Recorder("rule", 1)
    routed = RoutedSource({"care": llm}, rule)
    assert routed.needs_messages is True
    routed.beliefs([req("care"), req("virtue")])
    assert llm.calls[0][0].messages == CHAT
    assert rule.calls[0][0].messages == ()  # the rule's store keys match a lone rule's
    assert RoutedSource({"care": rule}).needs_messages is False


def test_identity_describes_every_member_and_close_closes_each_once():
    one, two = Recorder("one", 0), Recorder("two", 1)
    routed = RoutedSource({"a": one, "b": two, "c": two}, one)
    assert routed.identity() == {
        "source": "routed",
        "routes": {
            "a": {"source": "one", "index": 0},
            "b": {"source": "two", "index": 1},
            "c": {"source": "two", "index": 1},
        },
        "default": {"source": "one", "index": 0},
    }
    routed.close()
    assert (one.closed, two.closed) == (1, 1)


def test_iter_beliefs_yields_every_index_once_with_its_agents_answer():
    one, two = Recorder("one", 0), Recorder("two", 1)
    routed = RoutedSource({"a": one}, two)
    batch = [req("b"), req("a"), req("b", (5.0, 5.0))]
    pairs = dict(routed.iter_beliefs(batch))
    assert sorted(pairs) == [0, 1, 2]
    assert [int(np.argmax(pairs[i].belief)) for i in range(3)] == [1, 0, 1]


def test_a_member_answering_the_wrong_count_is_an_error():
    class Short(Recorder):
        def beliefs(self, requests):
            return super().beliefs(requests)[:-1]

    routed = RoutedSource({"a": Short("short", 0)})
    with pytest.raises(RuntimeError, match="answered 1 results for 2 requests"):
        routed.beliefs([req("a"), req("a", (9.0, 9.0))])


def test_members_with_equal_specs_are_built_once_and_shared():
    built: list[tuple[str, dict]] = []

    def build(kind, **options):
        built.append((kind, options))
        return Recorder(kind, 0)

    rules = SourceSpec("rules", {"policy": "human"}, "[feedback.agents.x]")
    default = SourceSpec("rules", {"policy": "human"}, "[feedback].source = 'rules'")
    other = SourceSpec("terminal", {"person": "ann", "attempts": 3}, "[feedback.agents.care]")
    routes, fallback, _ = build_members(
        plan_of({"virtue": rules, "care": other, "deontological": rules}, default), build=build
    )
    assert len(built) == 2  # rules once (two agents and the default), terminal once
    assert routes["virtue"] is routes["deontological"] is fallback
    assert routes["care"] is not fallback


def test_preflight_names_each_agent_and_source_and_closes_what_was_built():
    made: list[Recorder] = []

    class Down(Recorder):
        def check(self):
            raise BackendUnavailable(f"no Ollama server answers at http://{self.name}:11434")

    def build(kind, **options):
        if kind == "policy":
            raise ScenarioError(f"policy file {options['path']} not found; fix the path")
        source = Down(options["host"], 0) if kind == "ollama" else Recorder(kind, 0)
        made.append(source)
        return source

    ok = SourceSpec("rules", {"policy": "human"}, "[feedback].source = 'rules'")
    down = SourceSpec("ollama", {"host": "nowhere"}, "[feedback.agents.care] (source 'ollama')")
    gone = SourceSpec("policy", {"path": "v.pt"}, "[feedback.agents.virtue] (source 'policy')")

    with pytest.raises(ScenarioError) as info:
        build_members(plan_of({"care": down, "virtue": gone}, ok), build=build)
    text = str(info.value)
    assert text.startswith("s.toml: 2 belief sources of the panel cannot be used")
    assert (
        "  - [feedback.agents.care] (source 'ollama'): no Ollama server answers at "
        "http://nowhere:11434" in text
    )
    assert "  - [feedback.agents.virtue] (source 'policy'): policy file v.pt not found" in text
    assert all(s.closed == 1 for s in made)

    # one problem keeps its own class (the CLI and callers tell them apart)
    with pytest.raises(BackendUnavailable) as one:
        build_members(plan_of({"care": down}, ok), build=build)
    assert str(one.value) == (
        "s.toml: [feedback.agents.care] (source 'ollama'): no Ollama server answers at "
        "http://nowhere:11434"
    )
