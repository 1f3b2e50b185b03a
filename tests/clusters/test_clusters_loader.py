"""Cluster files: the shipped five + moral agent, validation errors naming file and field."""

from __future__ import annotations

from pathlib import Path

import pytest
from cluster_files import cluster_text

from amuled_ma.clusters import ClusterRegistry, default_registry, load_cluster
from amuled_ma.errors import ClusterDefinitionError

PAPER = ["consequentialist", "deontological", "virtue", "care", "social_justice"]


def write(directory: Path, name: str, text: str) -> Path:
    path = directory / f"{name}.toml"
    path.write_text(text)
    return path


def test_shipped_clusters_are_the_paper_five_plus_moral_agent():
    registry = default_registry()
    assert registry.names() == [*PAPER, "moral_agent"]
    assert [c.name for c in registry.panel()] == PAPER
    assert [c.credence_label for c in registry.panel()] == [
        "Consequentialist",
        "Deontological",
        "Virtue Ethics",
        "Care Ethics",
        "Social Justice Ethics",
    ]
    assert [len(c.theories) for c in registry.panel()] == [5, 4, 4, 4, 4]
    assert registry.get("moral_agent").kind == "unprompted"


def test_aliases_resolve_recording_names():
    registry = default_registry()
    assert registry.get("deontologist").name == "deontological"
    assert registry.get("social justice").name == "social_justice"
    assert registry.get("Social-Justice").name == "social_justice"
    assert "moral" in registry
    with pytest.raises(ClusterDefinitionError, match="unknown moral cluster 'nope'"):
        registry.get("nope")


def test_theory_fields_word_for_word():
    kant = default_registry().get("deontological").theories[0]
    assert kant.name == "Kantian Ethics"
    assert kant.key_concepts == (
        "Categorical Imperative",
        "Universalizability",
        "Treating humans as ends",
    )
    assert kant.decision_factors == ("Universality", "Respect for autonomy", "Moral duty")


@pytest.mark.parametrize(
    ("field", "line"),
    [
        ("focus", 'focus = "Focus on protecting the vulnerable"\n'),
        ("key_principle", 'key_principle = "Never leave anyone behind"\n'),
        ("title", 'title = "Guardian Ethics"\n'),
        ("credence_label", 'credence_label = "Guardian Ethics"\n'),
        ("theories[0].key_concepts", 'key_concepts = ["Protection", "Duty of care"]\n'),
        ("theories[0].decision_factors", 'decision_factors = ["Vulnerability", "Risk"]\n'),
    ],
)
def test_missing_field_names_file_and_field(tmp_path, field, line):
    path = write(tmp_path, "guardian", cluster_text("guardian").replace(line, ""))
    with pytest.raises(ClusterDefinitionError) as info:
        load_cluster(path)
    assert str(path) in str(info.value)
    assert repr(field) in str(info.value)


def test_missing_theories_and_wrong_types(tmp_path):
    text = cluster_text("guardian").split("[[theories]]")[0]
    with pytest.raises(ClusterDefinitionError, match="'theories': missing"):
        load_cluster(write(tmp_path, "guardian", text))
    bad = cluster_text("guardian").replace("order = 10", 'order = "ten"')
    with pytest.raises(ClusterDefinitionError, match="'order'"):
        load_cluster(write(tmp_path, "guardian", bad))
    bad = 'colour = "blue"\n' + cluster_text("guardian")
    with pytest.raises(ClusterDefinitionError, match="'colour': unknown field"):
        load_cluster(write(tmp_path, "guardian", bad))
    with pytest.raises(ClusterDefinitionError, match="must equal the file name"):
        load_cluster(write(tmp_path, "other", cluster_text("guardian")))
    with pytest.raises(ClusterDefinitionError, match="not valid TOML"):
        load_cluster(write(tmp_path, "broken", "name = "))


def test_unprompted_needs_instruction_and_mixture_needs_credences(tmp_path):
    text = 'name = "plain"\nkind = "unprompted"\ntitle = "Plain"\n'
    with pytest.raises(ClusterDefinitionError, match="'instruction'"):
        load_cluster(write(tmp_path, "plain", text))
    text = 'name = "blend"\nkind = "mixture"\ntitle = "Blend"\n'
    with pytest.raises(ClusterDefinitionError, match="'credences'"):
        load_cluster(write(tmp_path, "blend", text))
    text += "credences = { care = -1.0 }\n"
    with pytest.raises(ClusterDefinitionError, match=r"'credences\.care'"):
        load_cluster(write(tmp_path, "blend", text))


def test_user_directory_adds_a_cluster_without_code(tmp_path):
    write(tmp_path, "guardian", cluster_text("guardian"))
    registry = ClusterRegistry.load([tmp_path])
    assert registry.names()[-2:] == ["guardian", "moral_agent"]
    assert [c.name for c in registry.panel()] == [*PAPER, "guardian"]


def test_mixture_must_name_panel_clusters(tmp_path):
    write(
        tmp_path,
        "blend",
        'name = "blend"\nkind = "mixture"\ntitle = "Blend"\ncredences = { ghost = 1.0 }\n',
    )
    with pytest.raises(ClusterDefinitionError, match=r"'credences\.ghost'"):
        ClusterRegistry.load([tmp_path])


def test_missing_directory(tmp_path):
    with pytest.raises(ClusterDefinitionError, match="cluster directory not found"):
        ClusterRegistry.load([tmp_path / "absent"])
