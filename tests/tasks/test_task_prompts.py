"""State prompts, word for word against the prompts the paper's authors sent."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from amuled_ma.tasks import get_task
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import FindMilk
from amuled_ma.tasks.prompts import load_template, parse_template, render_state_prompt

FINDMILK_FILES = [
    "findmilk-gpt-4o-mini.json",
    "findmilk-llama-3_1-70b.json",
    "findmilk-llama-3_1-8b.json",
    "findmilk-mistral-nemo.json",
]
UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def state_part(prompt: str) -> str:
    """The recorded prompt without the cluster's credence sentence (appended after a blank line)."""
    head, sep, _ = prompt.partition("\n\nBehave as")
    assert sep, prompt[-200:]
    return head


def exchanges(recording: dict):
    for state in recording["states"]:
        for ex in state.get("exchanges", []):
            yield state["obs"], ex


@pytest.mark.parametrize("name", [*FINDMILK_FILES, "driving-llama-3_1-70b.json"])
def test_every_recorded_prompt_is_reproduced(load_recording, name):
    rec = load_recording(name)
    task = get_task("findmilk" if name.startswith("findmilk") else "driving")
    assert list(task.obs_names) == rec["obs_layout"]
    assert list(task.action_names) == rec["actions"]
    count = 0
    for obs, ex in exchanges(rec):
        extra = {}
        if task is FindMilk:  # the count of crying babies left is not in the observation
            extra["num_crying"] = int(re.search(r"there are (\d+) crying", ex["prompt"])[1])
        variables = task.prompt_variables_from_obs(obs, **extra)
        assert render_state_prompt(task.name, variables) == state_part(ex["prompt"])
        count += 1
    assert count > 0


def find_exchange(rec: dict, obs: list[float], needle: str = "") -> str:
    for o, ex in exchanges(rec):
        if o == obs and needle in ex["prompt"]:
            return state_part(ex["prompt"])
    raise AssertionError(f"no recorded exchange for {obs}")


def test_findmilk_states_reached_in_the_env(load_recording):
    """Play to the recorded states and render from the env's own variables."""
    cases = [
        # (recording, actions from the start, recorded observation)
        ("findmilk-gpt-4o-mini.json", [RIGHT] * 3 + [UP] * 3 + [LEFT], [2, 3, 7, 7, 2, 2, 1, 1]),
        ("findmilk-mistral-nemo.json", [RIGHT, RIGHT], [2, 0, 7, 7, 2, 2, 1, 1]),
    ]
    for name, actions, obs in cases:
        task = FindMilk(1)
        task.reset()
        for a in actions:
            task.step(torch.tensor([a]))
        assert task.obs[0].tolist() == obs
        num = task.crying_left().item()
        expected = find_exchange(load_recording(name), [float(v) for v in obs], f"are {num} crying")
        assert task.state_prompts()[0] == expected


def test_findmilk_no_crying_babies_sentence(load_recording):
    rec = load_recording("findmilk-gpt-4o-mini.json")
    obs, ex = next((o, e) for o, e in exchanges(rec) if "no crying babies" in e["prompt"])
    variables = FindMilk.prompt_variables_from_obs(obs, num_crying=0)
    text = render_state_prompt("findmilk", variables)
    assert "There are no crying babies around. The closest sleeping baby is at" in text
    assert text == state_part(ex["prompt"])


def test_driving_state_built_in_the_env(load_recording):
    rec = load_recording("driving-llama-3_1-70b.json")
    task = Driving(1, p_car=0.0, p_grandma=0.0)
    task.reset(seed=0)
    task.set_lane(4)
    task.place("car", 4, 8)
    task.place("car", 3, 7)
    task.place("grandma", 3, 5)
    obs = task.obs[0].tolist()
    assert obs == [8, -1, 7, 5, -2, -2, 0, 0, 0, 0, 1]
    text = task.state_prompts()[0]
    assert "The lane on the right does not exist and you cannot take it." in text
    assert text == find_exchange(rec, obs)


def test_driving_fragments_beyond_the_recordings():
    task = Driving(1, p_car=0.0, p_grandma=0.0)
    task.reset(seed=0)
    task.set_lane(0)
    task.place("car", 0, 1)
    task.place("grandma", 1, 2)
    text = task.state_prompts()[0]
    assert (
        "You are currently on lane 0. The current lane has car at 1 unit distance which will "
        "make you collide and has no grandma. The lane on the right has no car and has grandma "
        "is at 2 unit distance which will enable you to rescue her. The lane on the left does "
        "not exist and you cannot take it. You can perform the following actions:"
    ) in text
    assert text.endswith(
        "\n\n\nAction 0: steer straight\nAction 1: steer right\nAction 2: steer left"
    )


def test_findmilk_no_sleeping_babies_sentence():
    variables = FindMilk.prompt_variables_from_obs([3, 3, 7, 7, 4, 4, 0, 0], num_crying=1)
    text = render_state_prompt("FindMilk", variables)
    assert (
        "The closest crying baby is at position (x=4.0, y=4.0). "
        "There are no sleeping babies around. You can" in text
    )
    assert "The room is a grid with a size of 8 by 8 units." in text
    assert "Currently there are 1 crying babies in the room." in text


def test_template_errors(tmp_path: Path):
    with pytest.raises(ValueError, match="variables: missing 'grid_size'"):
        render_state_prompt("findmilk", {"x": 1.0})
    with pytest.raises(ValueError, match="unknown task"):
        render_state_prompt("chess", {})
    bad = tmp_path / "bad.md"
    bad.write_text("# nothing\n\n## other\n\n```text\nhi\n```\n")
    with pytest.raises(ValueError, match="## prompt"):
        parse_template(bad)
    bad.write_text("## prompt\n\n```text\n{a:g}\n```\n\n### g maybe 3\n\n```text\nx\n```\n")
    with pytest.raises(ValueError, match="fragment heading"):
        parse_template(bad)
    ok = tmp_path / "ok.md"
    ok.write_text(
        "## prompt\n\n```text\n[{a:g}] {b:.1f}\n```\n\n### g in 0..1\n\n```text\nlow {value}\n```\n"
        "\n### g otherwise\n\n```text\nhigh\n```\n"
    )
    template = parse_template(ok)
    assert template.render({"a": 1, "b": 2}) == "[low 1] 2.0"
    assert template.render({"a": 7, "b": 2}) == "[high] 2.0"
    with pytest.raises(ValueError, match="missing 'b'"):
        template.render({"a": 1})


def test_templates_ship_as_data():
    for name in ("findmilk", "driving"):
        template = load_template(name)
        assert template.path.parent.name == "tasks"
        assert template.path.parent.parent.name in ("prompts", "_data")
