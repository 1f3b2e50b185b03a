"""``[feedback].clusters``, ``[feedback].fusion`` and ``--set`` values: one line each, on load.

Through the real command line (``amuled train``, which fails while reading the scenario,
before any folder is made): an empty panel was an AssertionError, a cluster named twice
(``care,care``, ``care,CARE``, ``care,ᴄᴀʀᴇ``) or with a character that prints as nothing
was accepted, and a fusion rule of no name (``evil``, ``""``, ``single:99``) was found only
when the panel was planned.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from tiny_cli import one_line

from amuled_ma.cli import main
from amuled_ma.errors import ScenarioError
from amuled_ma.fusion import RULES
from amuled_ma.scenario.names import identity_key, odd_character
from amuled_ma.scenario.overrides import parse_set
from amuled_ma.scenario.panel_checks import FUSION_RULES, prior_rules


def fails(tmp_path: Path, capsys, *sets: str) -> str:
    """``amuled train findmilk --set ...``: exit 1, one line, no run folder; the line."""
    run_dir = tmp_path / "run"
    argv = ["train", "findmilk", "--variant", "base", "--run-dir", str(run_dir), "--no-progress"]
    for text in sets:
        argv += ["--set", text]
    assert main(argv) == 1
    assert not run_dir.exists()
    return one_line(capsys.readouterr().err)


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("feedback.clusters=[]", "key [feedback].clusters expects at least one moral cluster"),
        ("feedback.clusters=['care','care']", "names one cluster twice: 'care' and 'care'"),
        ("feedback.clusters=['care','CARE']", "names one cluster twice: 'care' and 'CARE'"),
        (  # small capitals: not in Unicode's confusables data
            "feedback.clusters=['care','\u1d04\u1d00\u0280\u1d07']",
            "names one cluster twice: 'care' and '\u1d04\u1d00\u0280\u1d07'",
        ),
        ("feedback.clusters=['care','care\u2800']", "U+2800 (BRAILLE PATTERN BLANK)"),
        ("feedback.clusters=['care','care\U000e0061']", "U+E0061 (TAG LATIN SMALL LETTER A)"),
        ("feedback.clusters=['care','care\ufe0f']", "U+FE0F (VARIATION SELECTOR-16)"),
        ("feedback.clusters=['care','']", "expects names of 1 to 100 characters"),
        (
            "feedback.fusion='evil'",
            "found 'evil'; the rules: bjs-dst, mean, max, vote, single:<i>, mec, nash-vote, "
            "variance-vote, borda (docs/fusion.md)",
        ),
        ("feedback.fusion='nash-votes'", "found 'nash-votes' (did you mean 'nash-vote'?)"),
        ("feedback.fusion='borda:2'", "rule 'borda' takes no parameter"),
        ("feedback.fusion=''", "key [feedback].fusion expects a fusion rule, found ''"),
        ("feedback.fusion='means'", "found 'means' (did you mean 'mean'?)"),
        ("feedback.fusion='single:99'", "single:<i> with i an integer in [-5, 4]"),
        ("feedback.fusion='single:x'", "found 'single:x'"),
        ("feedback.fusion='single'", "expects single:<i> (a member's index)"),
        ("feedback.fusion='vote:2'", "rule 'vote' takes no parameter"),
        (
            "feedback.clusters=['care',",
            "the value \"['care',\" opens a TOML list but is not TOML: Invalid value",
        ),
        ("feedback.clusters=['a' 'b']", "Unclosed array (at column 6)"),
    ],
)
def test_bad_panels_and_rules_are_one_line(tmp_path, capsys, override, expected):
    assert expected in fails(tmp_path, capsys, override)


def test_a_single_rule_within_the_panel_is_accepted():
    # the same checks let the valid forms through (negative indices count from the end)
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario("findmilk")
    for rule in ("single:0", "single:-5", "single:4", "vote", "bjs-dst", "mec", "borda"):
        assert scenario.replace("feedback", fusion=rule).feedback.fusion == rule


def test_the_scenarios_rules_are_the_registered_fusion_rules():
    assert dict(FUSION_RULES) == {name: spec.takes_param for name, spec in RULES.items()}
    assert {"bjs-dst", "mean", "max", "vote", "single"} <= set(FUSION_RULES)
    assert set(prior_rules()) == {name for name, spec in RULES.items() if spec.takes_prior}
    assert set(prior_rules()) == {"bjs-dst", "mec", "nash-vote", "variance-vote", "borda"}


def test_a_rule_registered_in_code_may_be_named_until_it_is_removed():
    from amuled_ma.fusion import register_rule, unregister_rule
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario("findmilk")

    @register_rule("geometric")
    def geometric(beliefs, *, weights, param, diagnostics):
        """Normalised geometric mean."""
        return beliefs.mean(axis=-2)

    try:
        assert scenario.replace("feedback", fusion="geometric").feedback.fusion == "geometric"
    finally:
        unregister_rule("geometric")
    with pytest.raises(ScenarioError, match="found 'geometric'"):
        scenario.replace("feedback", fusion="geometric")


def test_names_of_invisible_characters_and_small_capitals():
    for char in "\u2800\U000e0061\ufe0f\u200b\u3164\u202e\x00":
        assert odd_character(f"care{char}") is not None, hex(ord(char))
    for plain in ("care", "social justice", "caf\u00e9", "cafe\u0301", "\u5fb3"):
        assert odd_character(plain) is None, plain
    assert identity_key("\u1d04\u1d00\u0280\u1d07") == identity_key("care") == "care"
    assert identity_key("care\ufe0f") == "care"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("fedback.x=1", "unknown section [fedback] (did you mean feedback?); the sections are "),
        ("evil.x=1", "unknown section [evil]; the sections are task, ppo, base, finetune"),
        (
            "feedback.clusters=[care]",
            "opens a TOML list but is not TOML: Invalid value (at column 2)",
        ),
        ("task.options={a=}", "opens a TOML table but is not TOML"),
        ("novalue", "expected SECTION.KEY=VALUE"),
    ],
)
def test_set_texts_are_refused_with_the_sections_or_toml_reason(text, expected):
    with pytest.raises(ScenarioError) as info:
        parse_set(text)
    assert expected in str(info.value) and "\n" not in str(info.value)


def test_set_texts_that_parse():
    assert parse_set("feedback.source=ollama") == ("feedback", "source", "ollama")
    assert parse_set("feedback.clusters=['care', 'virtue']")[2] == ["care", "virtue"]
    assert parse_set("feedback.distill.budget=20") == ("feedback", "distill.budget", 20)
