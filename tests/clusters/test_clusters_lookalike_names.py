"""Cluster names that only look alike are one identity .

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
    assert "field 'name'" in text and "U+" in text and "\n" not in text
    if name.isprintable():
        assert "only look like another cluster's" in text and "'care' of" in text
    else:  # a character that prints as nothing is refused in any name
        assert "prints as nothing" in text


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


#: Look-alikes beyond Cyrillic and Greek, from Unicode's confusables (UTS #39 skeletons
#: through the ``confusable_homoglyphs`` package). Before, each was a second cluster.
BEYOND = {
    "armenian u (U+057D)": ("virtue", "virt\u057de"),
    "armenian o (U+0585)": ("deontological", "de\u0585ntological"),
    "cherokee capitals": ("care", "\u13df\u13aa\u13d2\u13ac"),
    "cherokee small letters": ("care", "\uabaf\uab7a\uaba2\uab7c"),
    "mathematical bold": ("care", "\U0001d41c\U0001d41a\U0001d42b\U0001d41e"),
    "mathematical script e": ("virtue", "virtu\u212f"),
    "apl alpha (U+237A)": ("social_justice", "soci\u237al_justice"),
}


@pytest.mark.parametrize(("shipped", "name"), list(BEYOND.values()), ids=list(BEYOND))
def test_lookalikes_beyond_cyrillic_and_greek_are_refused(tmp_path, shipped, name):
    assert identity_key(name) == identity_key(shipped)
    write(tmp_path / "user", name)
    with pytest.raises(ClusterDefinitionError) as info:
        ClusterRegistry.load([tmp_path / "user"])
    text = str(info.value)
    assert "only look like another cluster's" in text and f"{shipped!r} of" in text, text
    assert "U+" in text and "\n" not in text


def test_the_skeleton_follows_uts39_for_ascii_too():
    # confusables.txt maps 0 -> O, 1 and I -> l, m -> rn: names differing so read alike
    assert identity_key("rn0ral") == identity_key("moral")
    assert identity_key("va1ue") == identity_key("va|ue") == identity_key("value")
    # case is folded first (names are case-insensitive): a capital I reads as i, not l
    assert identity_key("vaIue") == identity_key("vaiue") != identity_key("value")
    assert identity_key("care") != identity_key("core")
    assert identity_key("Guardian") == "guardian"  # plain names keep their letters


def test_distinct_names_in_other_scripts_stay_distinct(tmp_path):
    # a script without Latin look-alikes is not folded into Latin (Armenian ayb, gim)
    assert identity_key("\u0531\u0533") != identity_key("care")
    write(tmp_path / "user", "\u0531\u0533\u0531", title="Armenian")
    registry = ClusterRegistry.load([tmp_path / "user"])
    assert "\u0531\u0533\u0531" in registry.names()


@pytest.mark.parametrize("char", ["\u2800", "\U000e0061", "\ufe0f", "\u3164"])
def test_a_cluster_file_named_with_a_blank_or_tag_character_is_refused(tmp_path, char):
    write(tmp_path / "user", f"care{char}")
    with pytest.raises(ClusterDefinitionError, match=f"U\\+{ord(char):04X}") as info:
        ClusterRegistry.load([tmp_path / "user"])
    assert "prints as nothing" in str(info.value) and "field 'name'" in str(info.value)


def test_small_capitals_collide_with_their_letters(tmp_path):
    write(tmp_path / "user", "\u1d04\u1d00\u0280\u1d07")  # ᴄᴀʀᴇ
    with pytest.raises(ClusterDefinitionError, match="only look like another cluster's"):
        ClusterRegistry.load([tmp_path / "user"])
