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


def test_the_memory_of_a_fit_by_hand_and_against_the_real_model():
    import torch

    from amuled_ma.distill.model import _init_params
    from amuled_ma.scenario import memory

    # E=2, H=3, K=1 member, A=16, D=64: P = 64*3 + 3 + 3*3 + 3 + 3*16 + 16 = 271 a network;
    # 2 x 271 x 16 bytes + 2 x 5 states x (2*3 + 16) x 12 bytes = 8,672 + 2,640
    assert memory.distill_bytes(2, 3, 1, 5) == 11_312
    params = _init_params(torch.Generator().manual_seed(0), 2, 64, 3, 16)
    assert sum(p.numel() for p in params) == 2 * 271  # the model's own tensors
    # a share budget: the fit is assumed to hold 4,096 states
    assert memory.distill_bytes(2, 3, 1, 0.1) == 8_672 + 2 * 4096 * 22 * 12


def test_a_distilled_model_beyond_memory_is_refused_in_a_moment(tmp_path, monkeypatch):
    import time

    from amuled_ma.scenario import memory

    monkeypatch.setattr(memory, "physical_memory_bytes", lambda: 32 * 2**30)
    start = time.process_time()
    text = load_error(
        tmp_path, "[feedback.distill]\nenabled = true\nhidden = 4096\nensemble = 64\n"
    )
    assert time.process_time() - start < 2
    assert "[feedback.distill].ensemble x hidden = 64 x 4,096" in text
    assert "need about 40.8 GiB" in text and "32.0 GiB" in text
    assert "e.g. hidden = 1024" in text and "\n" not in text
    # off, the model is never built: no check
    path = tmp_path / "off.toml"
    path.write_text("[feedback.distill]\nenabled = false\nhidden = 4096\nensemble = 64\n")
    assert load_scenario(path).feedback.distill.hidden == 4096
    path.write_text("[feedback.distill]\nenabled = true\nhidden = 1024\nensemble = 64\n")
    assert load_scenario(path).feedback.distill.hidden == 1024  # about 7.8 GiB: fits


def test_a_distilled_model_beyond_any_memory_is_one_line_on_the_command_line(tmp_path, capsys):
    from amuled_ma.cli import main

    # 10**6 asked states in one full-batch fit of 64 networks of 4,096 units: about 6 TB
    argv = ["train", "findmilk", "--variant", "base", "--run-dir", str(tmp_path / "r")]
    # (each --set is checked as it is applied: switched on last, the whole model is checked)
    for text in ("hidden=4096", "ensemble=64", "budget=1000000", "enabled=true"):
        argv += ["--set", f"feedback.distill.{text}"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "need about 5.8 TiB to fit the distilled model" in err
    assert not (tmp_path / "r").exists()


def test_seed_replicas_are_checked_before_planning(monkeypatch):
    from amuled_ma.scenario import memory

    memory.check_seed_replicas(5, 4)
    with pytest.raises(ScenarioError, match=r"--seeds 1,000,000,000: expected at most 10,000"):
        memory.check_seed_replicas(10**9, 4)
    monkeypatch.setattr(memory, "physical_memory_bytes", lambda: 2**30)
    # 8,000 x 4 jobs x 65,536 bytes = 2 GB > half of 1 GiB; 512 MiB / 65,536 / 4 = 2,048
    with pytest.raises(ScenarioError, match=r"\(--seeds <= 2,048\)"):
        memory.check_seed_replicas(8000, 4)
