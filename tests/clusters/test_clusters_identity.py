"""Cluster identities: names, credence labels and mixture credences never collide in silence.

``care.toml`` and ``CARE.toml`` in one directory, a second cluster
labelled ``"Care Ethics"``, and mixture credences that do not sum to 1 or repeat a key in
another case were all accepted. Each case here writes real TOML files and expects a
``ClusterDefinitionError`` naming the files or keys involved.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from cluster_files import write_cluster

from amuled_ma.clusters import ClusterRegistry, build_messages, load_cluster
from amuled_ma.clusters.loader import CREDENCE_SUM_TOLERANCE
from amuled_ma.errors import ClusterDefinitionError

PAPER = ["consequentialist", "deontological", "virtue", "care", "social_justice"]


def write_mixture(directory: Path, credences: str, name: str = "blend") -> Path:
    path = directory / f"{name}.toml"
    path.write_text(
        f'name = "{name}"\nkind = "mixture"\ntitle = "Blend"\ncredences = {{ {credences} }}\n'
    )
    return path


# --- cluster names -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("first", "second"),
    [("guardian", "GUARDIAN"), ("guardian", "Guardian"), ("guardian_angel", "guardian-angel")],
)
def test_same_directory_names_colliding_ignoring_case_is_an_error(tmp_path, first, second):
    a = write_cluster(tmp_path, first, label="Guardian A")
    b = write_cluster(tmp_path, second, label="Guardian B")
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path], include_default=False)
    message = str(info.value)
    assert str(a) in message and str(b) in message
    assert "'name'" in message


def test_same_directory_collision_with_a_shipped_name_is_an_error(tmp_path):
    lower = write_cluster(tmp_path, "care", title="Care Ethics")
    upper = write_cluster(tmp_path, "CARE", title="Care Ethics")
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path])
    assert str(lower) in str(info.value) and str(upper) in str(info.value)


def test_user_directory_overriding_care_is_reported(tmp_path):
    mine = write_cluster(tmp_path, "care", title="Care Ethics", order=4)
    registry = ClusterRegistry.load([tmp_path])
    assert [c.name for c in registry.panel()] == PAPER
    assert registry.get("care").path == mine
    assert registry.get("care").focus == "Focus on protecting the vulnerable"
    assert len(registry.overridden) == 1
    name, old_path, new_path = registry.overridden[0]
    assert name == "care"
    assert (old_path.parent.name, old_path.name) == ("clusters", "care.toml")
    assert old_path != mine
    assert new_path == mine


def test_clusters_list_says_which_file_overrides_which(tmp_path, capsys):
    from amuled_ma.cli import main

    mine = write_cluster(tmp_path, "care", title="Care Ethics", order=4)
    assert main(["clusters", "list", "--clusters-dir", str(tmp_path)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"note: {mine} overrides the cluster 'care' of ")
    assert first.endswith("care.toml") and str(mine) != first.rsplit(" ", 1)[1]


def test_override_in_another_case_replaces_instead_of_adding_a_sixth_cluster(tmp_path):
    mine = write_cluster(tmp_path, "CARE", title="Care Ethics", order=4)
    registry = ClusterRegistry.load([tmp_path])
    assert [c.name for c in registry.panel()] == [*PAPER[:3], "CARE", PAPER[4]]
    assert registry.get("care").path == mine
    assert [(o.name, o.new_path) for o in registry.overridden] == [("CARE", mine)]


def test_two_user_directories_colliding_is_an_override_later_wins(tmp_path):
    first = write_cluster(tmp_path / "a", "guardian")
    second = write_cluster(tmp_path / "b", "Guardian")
    registry = ClusterRegistry.load([tmp_path / "a", tmp_path / "b"])
    assert registry.get("guardian").path == second
    assert [tuple(o) for o in registry.overridden] == [("Guardian", first, second)]
    assert len(registry.panel()) == len(PAPER) + 1


def test_shipped_clusters_override_nothing():
    assert ClusterRegistry.load().overridden == []


# --- credence labels -----------------------------------------------------------------


@pytest.mark.parametrize("label", ["Care Ethics", "care ethics", "  Care   ETHICS "])
def test_a_second_cluster_with_the_care_label_is_an_error(tmp_path, label):
    mine = write_cluster(tmp_path, "nurture", title="Nurture Ethics", label=label)
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path])
    message = str(info.value)
    assert str(mine) in message
    assert "care.toml" in message
    assert "'credence_label'" in message
    assert repr(label) in message


def test_credence_labels_collide_between_user_clusters(tmp_path):
    a = write_cluster(tmp_path, "guardian", label="Protector")
    b = write_cluster(tmp_path, "sentinel", title="Sentinel Ethics", label="protector")
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path], include_default=False)
    assert str(a) in str(info.value) and str(b) in str(info.value)


# --- mixture credences ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("credences", "found"),
    [
        ("consequentialist = 0.5, care = 0.3", "0.8;"),
        ("consequentialist = 0.6, care = 0.6", "1.2;"),
        ("consequentialist = 0.5, care = 0.499", "0.999;"),
        ("care = 0.0", "0;"),
    ],
)
def test_mixture_credences_must_sum_to_one(tmp_path, credences, found):
    path = write_mixture(tmp_path, credences)
    with pytest.raises(ClusterDefinitionError) as info:
        load_cluster(path)
    message = str(info.value)
    assert str(path) in message
    assert "'credences'" in message
    assert f"found a sum of {found}" in message
    assert "add up to 1" in message


def test_mixture_credence_above_one_is_an_error(tmp_path):
    path = write_mixture(tmp_path, "care = 1.5")
    with pytest.raises(ClusterDefinitionError) as info:
        load_cluster(path)
    assert str(path) in str(info.value)
    assert "'credences.care'" in str(info.value)
    assert "between 0 and 1" in str(info.value)


def test_mixture_keys_differing_only_in_case_are_an_error(tmp_path):
    path = write_mixture(tmp_path, "Care = 0.5, care = 0.5")
    with pytest.raises(ClusterDefinitionError) as info:
        load_cluster(path)
    message = str(info.value)
    assert str(path) in message
    assert "'Care'" in message and "'care'" in message
    with pytest.raises(ClusterDefinitionError):
        ClusterRegistry.load([tmp_path])


def test_mixture_keys_naming_one_cluster_by_name_and_alias_are_an_error(tmp_path):
    path = write_mixture(tmp_path, "deontological = 0.5, deontologist = 0.5")
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path])
    message = str(info.value)
    assert str(path) in message
    assert "'deontological'" in message and "'deontologist'" in message


@pytest.mark.parametrize(
    ("credences", "expected"),
    [
        (
            "consequentialist = 0.1, deontological = 0.2, virtue = 0.7",
            "{Consequentialist: 0.1, Deontological: 0.2, Virtue Ethics: 0.7, Care Ethics: 0.0, "
            "Social Justice Ethics: 0.0}",
        ),
        (
            "virtue = 0.333334, care = 0.333333, social_justice = 0.333333",
            "{Consequentialist: 0.0, Deontological: 0.0, Virtue Ethics: 0.333334, "
            "Care Ethics: 0.333333, Social Justice Ethics: 0.333333}",
        ),
    ],
)
def test_mixtures_summing_to_one_within_rounding_are_accepted(tmp_path, credences, expected):
    write_mixture(tmp_path, credences)
    registry = ClusterRegistry.load([tmp_path])
    prompt = build_messages("blend", "findmilk", "S", registry=registry)[-1][1]
    assert expected in prompt


def test_credence_sum_tolerance_is_the_documented_one(tmp_path):
    assert CREDENCE_SUM_TOLERANCE == 1e-6
    load_cluster(write_mixture(tmp_path, "care = 0.5, virtue = 0.5000005"))
    with pytest.raises(ClusterDefinitionError, match=r"found a sum of 1\.000002;"):
        load_cluster(write_mixture(tmp_path, "care = 0.5, virtue = 0.500002"))
