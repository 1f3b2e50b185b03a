"""build_messages: the paper's three blocks, word for word, and credence vectors."""

from __future__ import annotations

import hashlib

import pytest

from amuled_ma.clusters import (
    ClusterRegistry,
    build_messages,
    credence_vector,
    fewshot_messages,
    instruction_text,
    render_system_prompt,
)
from amuled_ma.errors import ClusterDefinitionError

# Our agent name -> the recordings' agent name.
AGENTS = {
    "consequentialist": "consequentialist",
    "deontological": "deontologist",
    "virtue": "virtue",
    "care": "care",
    "social_justice": "social justice",
    "moral_agent": "moral_agent",
}


def test_system_prompt_is_the_authors_text():
    text = render_system_prompt()
    assert text.startswith(
        "You are a moral agent that is capable of following the following  moral clusters.\n\n"
        "The Consequentialist Ethics moral cluster provides a strong focus on Focus on outcomes "
        "and results of actions. The key principle that drives this moral code is Maximizing "
        "overall good/well-being.\nThis moral cluster is further guided by the following ethical "
        "theories:\n- Classical Utilitarianism: This ethical theory adheres to the following key "
        "concepts: Greatest good for the greatest number, Hedonic calculus. When making "
        "decisions, this theory must take into account the following factors: Pleasure, Pain, "
        "Aggregate welfare.\n"
    )
    assert "Relative improvement.\n\nThe Deontological Ethics moral cluster" in text
    assert text.endswith(
        "Environmental impact, Future generations, Ecological balance.\n\nYou will make your "
        "decisions on complex scenarios following the above moral codes. You should explain "
        "your reasoning on how you choose your actions. At the end and last line of you answer, "
        "state the action and probability of belief for that choice as a json with the action "
        "as keys and probability as values. The sum of all beliefs should be equal to 1."
    )
    # Offsets measured in the authors' file (algorithms/llm_moral.py): the span from
    # "following  moral clusters." to "Ecological balance.\n\nYou will" is 6804 characters.
    start = text.index("following  moral clusters.")
    assert text.index("Ecological balance.\n\nYou will") - start == 6804
    assert text.index("Relative improvement.\n\nThe Deontological") - start == 1554
    assert hashlib.sha256(text.encode()).hexdigest() == SYSTEM_SHA256


SYSTEM_SHA256 = "f8f039df99d5fbee5841115b9a93bb751ab3aee23e360163828d3382ed6e84c7"


def test_fewshot_examples_are_the_papers():
    turns = fewshot_messages("findmilk")
    assert [role for role, _ in turns] == ["user", "assistant"] * 3
    assert turns[0][1].startswith("You are a train conductor facing a critical decision.")
    assert turns[1][1].endswith('{"0": 0.05, "1": 0.3, "2": 0.05, "3": 0.6 }')
    assert turns[3][1].endswith('{"A": 0.6, "B": 0.3, "C": 0.1, "D": 0.0 }')
    assert turns[5][1].endswith(
        '{"build": 0.1, "distribute": 0.6, "improve": 0.3, "maintain": 0.0}'
    )
    # trailing spaces of the original are kept
    assert "incremental improvements. \nMaintain the current" in turns[3][1]
    assert "broader well-being. \nOn this other hand" in turns[5][1]
    assert fewshot_messages("driving") == turns  # no task-specific file: the default


def test_task_specific_fewshot_file(tmp_path):
    (tmp_path / "fewshot").mkdir()
    (tmp_path / "system.md").write_text("Clusters:\n{clusters}\nEnd.\n")
    (tmp_path / "fewshot" / "default.toml").write_text("examples = []\n")
    (tmp_path / "fewshot" / "findmilk.toml").write_text(
        "[[examples]]\nuser = 'Q'\nassistant = 'A {\"0\": 1.0}'\n"
    )
    messages = build_messages("care", "FindMilk", "STATE", prompts=tmp_path)
    assert messages[1:3] == (("user", "Q"), ("assistant", 'A {"0": 1.0}'))
    assert messages[0][1].startswith("Clusters:\nThe Consequentialist Ethics")
    assert build_messages("care", "driving", "STATE", prompts=tmp_path)[1][0] == "user"
    (tmp_path / "fewshot" / "broken.toml").write_text("[[examples]]\nuser = 'Q'\n")
    with pytest.raises(ClusterDefinitionError, match=r"examples\[0\]\.assistant"):
        build_messages("care", "broken", "S", prompts=tmp_path)


def test_messages_shape_and_credence_sentence():
    messages = build_messages("care", "findmilk", "STATE")
    assert [role for role, _ in messages] == ["system", *["user", "assistant"] * 3, "user"]
    assert messages[-1][1] == (
        "STATE\n\nBehave as an agent that assigns the following credence values: "
        "{Consequentialist: 0.0, Deontological: 0.0, Virtue Ethics: 0.0, Care Ethics: 1.0, "
        "Social Justice Ethics: 0.0}. Using the credence confidence for moral theories, reason "
        "through what action you will take."
    )
    assert build_messages("moral_agent", "findmilk", "STATE")[-1][1] == (
        "STATE\n\nBehave as moral agent. Using moral theories, reason through what action you "
        "will take."
    )
    assert hash(messages)  # hashable, for deduplication


def test_mixture_credences():
    text = instruction_text(
        ClusterRegistry.load().get("care"), credences={"care": 0.5, "deontologist": 0.5}
    )
    assert (
        "{Consequentialist: 0.0, Deontological: 0.5, Virtue Ethics: 0.0, Care Ethics: 0.5," in text
    )
    with pytest.raises(ClusterDefinitionError, match="'ghost' is not a panel cluster"):
        credence_vector(ClusterRegistry.load().get("care"), credences={"ghost": 1.0})
    with pytest.raises(ClusterDefinitionError, match="must be a number >= 0"):
        credence_vector(ClusterRegistry.load().get("care"), credences={"care": -0.1})


def test_mixture_file_and_user_cluster(tmp_path):
    (tmp_path / "blend.toml").write_text(
        'name = "blend"\nkind = "mixture"\ntitle = "Blend"\n'
        "credences = { consequentialist = 0.25, care = 0.75 }\n"
    )
    registry = ClusterRegistry.load([tmp_path])
    messages = build_messages("blend", "findmilk", "S", registry=registry)
    assert (
        "{Consequentialist: 0.25, Deontological: 0.0, Virtue Ethics: 0.0, Care Ethics: 0.75,"
        in (messages[-1][1])
    )
    assert messages[0] == build_messages("care", "findmilk", "S")[0]  # mixtures add no section


def test_state_prompt_block_matches_every_recorded_prompt(load_recording, recordings_dir):
    """The recordings' prompts end with exactly our closing instruction."""
    checked = 0
    for path in sorted(recordings_dir.glob("*.json")):
        recording = load_recording(path.name)
        for state in recording["states"]:
            for exchange in state.get("exchanges", ()):
                ours = next(k for k, v in AGENTS.items() if v == exchange["agent"])
                prompt = exchange["prompt"]
                marker = "\n\nBehave as "
                state_part = prompt[: prompt.rindex(marker)]
                messages = build_messages(ours, recording["task"], state_part)
                assert messages[-1][1] == prompt
                checked += 1
    assert checked == 384


def test_with_the_task_renderer_driving_prompts_are_the_recorded_ones(load_recording):
    """End to end with the tasks engineer's renderer: every recorded Driving prompt."""
    np = pytest.importorskip("numpy")
    prompts = pytest.importorskip("amuled_ma.tasks.prompts")
    driving = pytest.importorskip("amuled_ma.tasks.driving")
    recording = load_recording("driving-llama-3_1-70b.json")
    checked = 0
    for state in recording["states"]:
        for exchange in state.get("exchanges", ()):
            variables = driving.Driving.prompt_variables_from_obs(np.asarray(state["obs"]))
            text = prompts.render_state_prompt("driving", variables)
            ours = next(k for k, v in AGENTS.items() if v == exchange["agent"])
            assert build_messages(ours, "driving", text)[-1][1] == exchange["prompt"]
            checked += 1
    assert checked == 30
