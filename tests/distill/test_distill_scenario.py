"""``[feedback.distill]`` in a scenario: defaults, overrides, and errors that name the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from amuled_ma import scenario as scenario_mod
from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import DistillConfig, load_scenario

DOCS = Path(__file__).resolve().parents[2] / "docs"


def load_error(tmp_path: Path, body: str) -> str:
    path = tmp_path / "s.toml"
    path.write_text(body)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    text = str(info.value)
    assert text.startswith(str(path)), text
    return text


def test_off_by_default_and_read_from_the_file(tmp_path):
    assert load_scenario("findmilk").feedback.distill == DistillConfig()
    assert not DistillConfig().enabled and DistillConfig().budget == 0.1
    path = tmp_path / "s.toml"
    path.write_text(
        "[feedback.distill]\nenabled = true\nbudget = 25\nselection = 'random'\n"
        "refit_every = 8\nholdout = 0.0\nanswer_misses = true\nseed = 4\n"
    )
    distill = load_scenario(path).feedback.distill
    assert (distill.enabled, distill.budget, distill.selection) == (True, 25, "random")
    assert isinstance(distill.budget, int)  # an integer is a count of states
    assert (distill.refit_every, distill.holdout, distill.answer_misses, distill.seed) == (
        8, 0.0, True, 4,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ("budget = 1.5", "key [feedback.distill].budget expects a share in (0, 1]"),
        ("budget = 0", "found integer (0)"),
        ("budget = 'all'", "found string ('all')"),
        ("budget = true", "found boolean (True)"),
        ("ensemble = 0", "key [feedback.distill].ensemble expects a positive integer in [1, 64]"),
        ("hidden = 0", "key [feedback.distill].hidden expects a positive integer"),
        ("refit_every = 2.0", "key [feedback.distill].refit_every expects integer"),
        ("holdout = 0.9", "key [feedback.distill].holdout expects a finite number in [0, 0.5]"),
        ("selection = 'best'", "key [feedback.distill].selection expects one of uncertainty"),
        ("model = 'gp'", "key [feedback.distill].model expects one of mlp"),
        ("seed = -1", "key [feedback.distill].seed expects a non-negative integer"),
        ("enabled = 1", "key [feedback.distill].enabled expects boolean"),
        ("budgte = 0.1", "unknown key [feedback.distill].budgte (did you mean budget?)"),
    ],
)
def test_a_bad_value_names_the_file_the_key_what_was_expected_and_found(tmp_path, body, expected):
    text = load_error(tmp_path, f"[feedback.distill]\n{body}\n")
    assert expected in text
    assert ("found" in text) != text.count("unknown key"), text  # a value: what was found


def test_the_table_itself_must_be_a_table(tmp_path):
    text = load_error(tmp_path, "[feedback]\ndistill = 3\n")
    assert "key [feedback].distill expects table" in text


def test_set_overrides_reach_into_the_table():
    scenario = load_scenario("findmilk")
    changed = scenario.replace("feedback", **{"distill.enabled": True, "distill.budget": 0.3})
    assert changed.feedback.distill.enabled and changed.feedback.distill.budget == 0.3
    assert changed.feedback.distill.ensemble == 5 and changed.feedback.clusters == (
        scenario.feedback.clusters
    )
    with pytest.raises(ScenarioError, match=r"\(override of \[feedback\]\).*distill\]\.budget"):
        scenario.replace("feedback", **{"distill.budget": 2.0})
    with pytest.raises(ScenarioError, match=r"no key \[feedback\]\.distil \(did you mean distill"):
        scenario.replace("feedback", **{"distil.budget": 0.1})


def test_built_in_code_the_error_names_the_key():
    with pytest.raises(ScenarioError, match=r"\[feedback\.distill\]\.holdout"):
        DistillConfig(holdout=0.7)


def test_the_docs_list_every_range_and_key():
    learning = (DOCS / "learning.md").read_text(encoding="utf-8")
    table = learning.split("## Scenario value ranges", 1)[1].split("\n## ", 1)[0]
    for name in DistillConfig.model_fields:
        rng = scenario_mod.field_range(DistillConfig, name)
        if rng is not None:
            row = f"`[feedback.distill].{name}`"
            assert row in table, f"docs/learning.md does not list {row}"
            assert rng.describe() in table.split(row, 1)[1].split("\n", 1)[0], row
    assert "`[feedback.distill].budget`" in table
    distill = (DOCS / "distill.md").read_text(encoding="utf-8")
    for name in DistillConfig.model_fields:
        assert f"`{name}`" in distill, f"docs/distill.md does not document {name}"
