"""Cluster names that only look alike are one identity (issue 24, item 6).

A name that differs from another cluster's only by full-width letters, zero-width
characters or Cyrillic/Greek look-alikes of Latin letters was accepted as a second
cluster beside it; it is now refused as a collision, naming the characters.
"""

from __future__ import annotations

import pytest

from amuled_ma.clusters import ClusterRegistry
from amuled_ma.clusters.loader import identity_key
from amuled_ma.errors import ClusterDefinitionError

CLUSTER = """\
name = "{name}"
kind = "cluster"
title = "{title}"
credence_label = "{label}"
focus = "Focus"
key_principle = "Principle"

[[theories]]
name = "T"
key_concepts = ["a"]
decision_factors = ["b"]
"""

LOOKALIKES = {
    "cyrillic a": "c\u0430re",
    "zero-width space": "ca\u200bre",
    "full width": "\uff43\uff41\uff52\uff45",
    "soft hyphen": "c\u00adare",
    "greek capital alpha and full-width e": "c\u0391r\uff45",
}


def write(folder, name, title="Other", label=None):
    folder.mkdir(parents=True, exist_ok=True)
    text = CLUSTER.format(name=name, title=title, label=label or title)
    (folder / f"{name}.toml").write_text(text)


@pytest.mark.parametrize("name", list(LOOKALIKES.values()), ids=list(LOOKALIKES))
def test_a_lookalike_of_a_shipped_cluster_is_refused(tmp_path, name):
    write(tmp_path / "user", name)
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path / "user"])
    text = str(info.value)
    assert "field 'name'" in text and "only look like another cluster's" in text
    assert "'care' of" in text and "U+" in text and "\n" not in text


def test_lookalikes_in_one_folder_are_refused(tmp_path):
    write(tmp_path / "user", "guardian", title="Guard")
    write(tmp_path / "user", "gu\u0430rdi\u0430n", title="Guard 2")  # Cyrillic а
    with pytest.raises(ClusterDefinitionError, match="U\\+0430"):
        ClusterRegistry.load([tmp_path / "user"])


def test_lookalike_labels_collide():
    assert identity_key("Care Ethics") == identity_key("\u0421\u0430re  \uff25thics")


def test_lookalike_credence_labels_are_refused(tmp_path):
    write(tmp_path / "user", "guardian", title="Guardian", label="C\u0430re Ethics")  # Cyrillic а
    with pytest.raises(ClusterDefinitionError, match="credence_label"):
        ClusterRegistry.load([tmp_path / "user"])


def test_an_override_spelt_the_same_is_still_an_override(tmp_path):
    write(tmp_path / "user", "CARE", title="Care Ethics", label="Care")
    registry = ClusterRegistry.load([tmp_path / "user"])
    assert [o.name for o in registry.overridden] == ["CARE"]
