"""Every real reply of the authors' recordings parses to the recorded belief.

The recordings' ``states[].exchanges[].response`` are real, messy replies (384 of them);
``states[].beliefs`` (and ``moral_agent``) hold what the authors' parser made of them.
Our parser must give the same belief, except in the cases listed in BETTER below, where
it reads an answer the authors' parser threw away (it fell back to uniform). Each such
case is listed with its reason; nothing else may differ.
"""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.beliefs.replies.parsing import parse_belief

FILES = [
    "driving-llama-3_1-70b.json",
    "findmilk-gpt-4o-mini.json",
    "findmilk-llama-3_1-70b.json",
    "findmilk-llama-3_1-8b.json",
    "findmilk-mistral-nemo.json",
]

NAMES = (
    "keys name the actions ('Move Up') instead of giving indices; the authors kept only "
    "index keys, found none and fell back to uniform"
)
FOREIGN = (
    "keys copied from the few-shot example ('build', ...) are ignored and the action-named "
    "keys ('move_up', 'move right') read; the authors found no index key and fell back to "
    "uniform"
)
UP, RIGHT = [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]

# (file, state index, agent) -> (our belief, reason). The authors recorded uniform for all.
BETTER = {
    ("findmilk-gpt-4o-mini.json", 318, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 321, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 337, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 340, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 343, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 345, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 348, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 358, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 365, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 374, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 375, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 379, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 384, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 473, "social justice"): ([0.1, 0.1, 0.2, 0.6], FOREIGN),
    ("findmilk-gpt-4o-mini.json", 479, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 484, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 488, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 493, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 498, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 499, "social justice"): (RIGHT, FOREIGN),
    ("findmilk-gpt-4o-mini.json", 507, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 508, "moral_agent"): (UP, NAMES),
    ("findmilk-gpt-4o-mini.json", 513, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 515, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 516, "moral_agent"): (RIGHT, NAMES),
    ("findmilk-gpt-4o-mini.json", 523, "moral_agent"): (UP, NAMES),
}


def recorded(state: dict, agent: str) -> np.ndarray:
    return np.asarray(state["moral_agent"] if agent == "moral_agent" else state["beliefs"][agent])


@pytest.mark.parametrize("name", FILES)
def test_every_recorded_reply_parses_to_the_recorded_belief(load_recording, name):
    recording = load_recording(name)
    actions = recording["actions"]
    exact = better = 0
    for index, state in enumerate(recording["states"]):
        for exchange in state.get("exchanges", ()):
            agent = exchange["agent"]
            parsed = parse_belief(exchange["response"], actions)
            assert parsed.belief.shape == (len(actions),)
            assert np.isclose(parsed.belief.sum(), 1.0)
            case = (name, index, agent)
            if case in BETTER:
                ours, _reason = BETTER[case]
                assert np.allclose(recorded(state, agent), 0.25), case  # authors: uniform
                assert np.allclose(parsed.belief, ours, atol=1e-9), case
                assert parsed.status == "repaired" and "key_names" in parsed.repairs
                better += 1
            else:
                assert np.allclose(parsed.belief, recorded(state, agent), atol=1e-9), (
                    case,
                    parsed,
                    exchange["response"][-300:],
                )
                exact += 1
    assert better == sum(1 for case in BETTER if case[0] == name)


def test_conformance_totals(load_recording):
    """384 replies: 358 equal to the recorded belief, 26 documented better answers."""
    total = abstained = 0
    for name in FILES:
        for state in load_recording(name)["states"]:
            for exchange in state.get("exchanges", ()):
                total += 1
                actions = load_recording(name)["actions"]
                abstained += parse_belief(exchange["response"], actions).status == "abstained"
    assert total == 384
    assert len(BETTER) == 26
    assert abstained > 0  # replies with no JSON (or a cut-off one) abstain, as recorded
