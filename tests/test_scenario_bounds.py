"""Every number in a scenario has a range; names used as folders are one safe component.

Values that cannot work (NaN, ``save_interval = 0``, ``gamma =
5``, absurd sizes) and a ``name`` that escapes ``runs_dir`` must be refused on load, with
an error naming the file, the key, the expected range and the value found.
"""

import argparse
import json
import math
import time
import typing
from pathlib import Path

import pytest
from sparse_files import sparse

from amuled_ma import scenario as scenario_mod
from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import (
    BaseConfig,
    Scenario,
    load_scenario,
    resolve_scenario_path,
    scenario_from_dict,
)
from amuled_ma.scenario import memory as scenario_memory

SECTIONS = {
    "task": scenario_mod.TaskConfig,
    "ppo": scenario_mod.PPOConfig,
    "base": scenario_mod.BaseConfig,
    "finetune": scenario_mod.FinetuneConfig,
    "feedback": scenario_mod.FeedbackConfig,
    "evaluation": scenario_mod.EvaluationConfig,
    "output": scenario_mod.OutputConfig,
}


def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)


def write(tmp_path: Path, section: str, key: str, value) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(f"[{section}]\n{key} = {toml_value(value)}\n")
    return path


def load_error(path: Path) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    return str(info.value)


# (section, key, bad value, the range the error must state)
BAD = [
    ("base", "save_interval", 0, ">= 1"),
    ("finetune", "save_interval", 0, ">= 1"),
    ("ppo", "clip_param", -1, "in (0, 1)"),
    ("ppo", "clip_param", 0, "in (0, 1)"),
    ("ppo", "gamma", 5, "in [0, 1]"),
    ("ppo", "gamma", -0.1, "in [0, 1]"),
    ("ppo", "lam", 1.5, "in [0, 1]"),
    ("ppo", "hidden_dims", [0], "in [1, 65,536]"),
    ("ppo", "hidden_dims", [64, -1], "in [1, 65,536]"),
    ("ppo", "hidden_dims", [], "length is in [1, 64]"),
    ("ppo", "learning_rate", 0, "in (0, 1]"),
    ("ppo", "learning_rate", 3.0, "in (0, 1]"),
    ("ppo", "entropy_coef", -0.01, ">= 0"),
    ("ppo", "value_loss_coef", -0.5, ">= 0"),
    ("ppo", "max_grad_norm", 0, "> 0"),
    ("ppo", "num_learning_epochs", 0, "in [1, 1000]"),
    ("ppo", "num_mini_batches", 0, "in [1, 65,536]"),
    ("finetune", "lambda_kl", -1, ">= 0"),
    ("finetune", "learning_rate", -1e-3, "in (0, 1]"),
    ("finetune", "num_learning_epochs", 0, "in [1, 1000]"),
    ("finetune", "env_reward_coef", -1, ">= 0"),
    ("finetune", "iterations", 0, "in [1, 100,000,000]"),
    ("finetune", "num_envs", 0, ">= 1"),
    ("finetune", "num_steps_per_env", -4, ">= 1"),
    ("base", "total_steps", 0, "in [1, 10,000,000,000]"),
    ("base", "num_envs", 0, ">= 1"),
    ("base", "num_steps_per_env", 0, ">= 1"),
    ("base", "shaping_coef", -1, ">= 0"),
    ("evaluation", "confidence", 1.5, "in (0, 1)"),
    ("evaluation", "confidence", 1.0, "in (0, 1)"),
    ("evaluation", "confidence", 0.0, "in (0, 1)"),
    ("evaluation", "episodes", 0, "in [1, 1,000,000]"),
    ("evaluation", "episodes", -5, "in [1, 1,000,000]"),
    ("evaluation", "seed", -1, "in [0, "),
    ("task", "seed", -1, "in [0, "),
    ("task", "max_steps", -1, "in [0, 10,000,000]"),
    ("feedback", "concurrency", 0, "in [1, 1024]"),
    ("feedback", "timeout_s", 0, "in (0, 86,400]"),
    ("feedback", "timeout_s", -5.0, "in (0, 86,400]"),
]


@pytest.mark.parametrize(
    ("section", "key", "value", "expected"), BAD, ids=[f"{s}.{k}={v}" for s, k, v, _ in BAD]
)
def test_out_of_range_value_names_file_key_range_and_value(tmp_path, section, key, value, expected):
    path = write(tmp_path, section, key, value)
    text = load_error(path)
    assert str(path) in text
    assert f"[{section}].{key}" in text
    assert expected in text, text
    assert "found" in text
    # the reason for the range is quoted in brackets after it
    assert f"{expected}" in text and "(" in text.split(expected, 1)[1]


def float_fields():
    for section, cls in SECTIONS.items():
        for name, info in cls.model_fields.items():
            if info.annotation is float:
                yield section, name


FLOAT_FIELDS = list(float_fields())


def test_the_float_fields_are_found():
    assert ("ppo", "gamma") in FLOAT_FIELDS and ("feedback", "timeout_s") in FLOAT_FIELDS
    assert len(FLOAT_FIELDS) >= 12


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize(
    ("section", "key"), FLOAT_FIELDS, ids=[f"{s}.{k}" for s, k in FLOAT_FIELDS]
)
def test_nan_and_infinities_refused_for_every_float(tmp_path, section, key, bad):
    path = write(tmp_path, section, key, bad)
    text = load_error(path)
    assert str(path) in text and f"[{section}].{key}" in text
    assert "finite" in text and repr(bad) in text


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_numbers_refused_inside_free_tables(tmp_path, bad):
    path = tmp_path / "s.toml"
    path.write_text(f"[feedback]\nollama = {{temperature = {bad}}}\n")
    assert "[feedback].ollama.temperature" in load_error(path)
    path.write_text(f"[task]\noptions = {{p = [0.1, {bad}]}}\n")
    assert "[task].options.p[1]" in load_error(path)


def number_type(annotation) -> bool:
    if typing.get_origin(annotation) is list:
        annotation = typing.get_args(annotation)[0]
        if typing.get_origin(annotation) is typing.Annotated:
            annotation = typing.get_args(annotation)[0]
    return annotation in (int, float)


def test_every_number_has_a_declared_range():
    for section, cls in SECTIONS.items():
        for name, info in cls.model_fields.items():
            if number_type(info.annotation):
                rng = scenario_mod.field_range(cls, name)
                assert rng is not None, f"[{section}].{name} has no range"
                assert rng.why, f"[{section}].{name}: the range gives no reason"
    assert scenario_mod.field_length(scenario_mod.PPOConfig, "hidden_dims").describe() == (
        "in [1, 64]"
    )


def test_defaults_lie_inside_their_ranges():
    scenario = Scenario()
    for section in SECTIONS:
        section_model = getattr(scenario, section)
        assert scenario_mod.validate_section(section, section_model.model_dump(), "defaults") == (
            section_model
        )


@pytest.mark.parametrize("section", ["base", "finetune"])
def test_memory_check_refuses_1e8_envs_at_once(tmp_path, section):
    path = write(tmp_path, section, "num_envs", 100_000_000)
    start = time.perf_counter()
    text = load_error(path)
    assert time.perf_counter() - start < 0.5
    assert f"[{section}].num_envs" in text and "memory" in text
    assert "found num_envs = 100000000" in text


def test_memory_check_uses_the_stated_fraction_of_this_machine(monkeypatch):
    gib = 2**30
    monkeypatch.setattr(scenario_memory, "physical_memory_bytes", lambda: 4 * gib)
    # 50% of 4 GiB = 2 GiB = 524,288 transitions of 4 KiB
    limit = int(scenario_memory.MEMORY_FRACTION * 4 * gib) // scenario_memory.BYTES_PER_TRANSITION
    assert limit == 524_288
    ok = scenario_from_dict({"base": {"num_envs": limit // 128, "num_steps_per_env": 128}})
    assert ok.base.num_envs == 4096
    with pytest.raises(ScenarioError, match=r"expected at most 524,288 rollout transitions"):
        scenario_from_dict({"base": {"num_envs": limit // 128 + 1, "num_steps_per_env": 128}})


def test_memory_read_from_sysconf_with_a_fallback(monkeypatch):
    assert scenario_memory.physical_memory_bytes() > 2**20

    def no_sysconf(name):
        raise ValueError(name)

    monkeypatch.setattr(scenario_memory.os, "sysconf", no_sysconf)
    assert scenario_memory.physical_memory_bytes() == scenario_memory.FALLBACK_MEMORY_BYTES


def test_network_and_episode_sizes_checked_against_memory():
    with pytest.raises(ScenarioError, match=r"\[ppo\]\.hidden_dims.*memory"):
        scenario_from_dict({"ppo": {"hidden_dims": [65_536] * 64}})
    with pytest.raises(ScenarioError, match=r"\[evaluation\]\.episodes"):
        scenario_from_dict({"evaluation": {"episodes": 10**7}})


def test_integer_written_as_float_is_refused_with_the_fix(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("[base]\nnum_envs = 1e8\n")
    text = load_error(path)
    assert "[base].num_envs expects integer, found float" in text
    assert "write the integer as 100_000_000" in text


def test_run_length_capped(tmp_path):
    with pytest.raises(ScenarioError, match=r"\[base\]\.total_steps.*10,000,000,000"):
        scenario_from_dict({"base": {"total_steps": 10**20}})
    assert scenario_from_dict(
        {"base": {"total_steps": scenario_memory.MAX_ENV_STEPS}}
    ).base.total_steps
    with pytest.raises(ScenarioError, match=r"\[finetune\]\.iterations.*MAX_ENV_STEPS"):
        scenario_from_dict({"finetune": {"iterations": 10**8, "num_steps_per_env": 128}})


def test_overrides_are_checked_like_the_file():
    scenario = load_scenario("findmilk")
    with pytest.raises(ScenarioError, match=r"\[evaluation\]\.episodes"):
        scenario.replace("evaluation", episodes=0)
    with pytest.raises(ScenarioError, match=r"\[ppo\]\.gamma.*finite"):
        scenario.replace("ppo", gamma=math.nan)
    assert scenario.replace("ppo", gamma=1.0).ppo.gamma == 1.0


def test_set_on_the_command_line_is_checked():
    from amuled_ma.commands._experiment import load

    args = argparse.Namespace(scenario="findmilk", overrides=["base.save_interval=0"])
    with pytest.raises(ScenarioError, match=r"\[base\]\.save_interval"):
        load(args)
    args = argparse.Namespace(scenario="findmilk", overrides=["ppo.clip_param=nan"])
    with pytest.raises(ScenarioError, match=r"\[ppo\]\.clip_param"):
        load(args)


def test_sections_built_in_code_are_checked_too():
    with pytest.raises(ScenarioError, match=r"\[base\]\.save_interval"):
        BaseConfig(save_interval=0)
    with pytest.raises(ScenarioError, match=r"\[base\]\.num_envs"):
        BaseConfig(**{**Scenario().base.model_dump(), "num_envs": 0})


# ------------------------------------------------------------------------ names
BAD_NAMES = [
    "../../escaped",
    "a/b",
    "a\\b",
    "",
    "..",
    ".",
    ".hidden",
    "-rf",
    "C:x",
    "a\x00b",
    "tab\there",
    " padded",
    "x" * 101,
    "a..b",
]


@pytest.mark.parametrize("name", BAD_NAMES, ids=repr)
def test_unsafe_scenario_name_refused(tmp_path, name):
    path = tmp_path / "s.toml"
    path.write_text(f"name = {json.dumps(name)}\n")  # a TOML basic string
    text = load_error(path)
    assert str(path) in text and "key name" in text
    assert "safe path component" in text and "no '/'" in text


@pytest.mark.parametrize("name", ["../x", "a/b", ""])
def test_unsafe_task_name_refused(name):
    with pytest.raises(ScenarioError, match=r"\[task\]\.name.*safe path component"):
        scenario_from_dict({"task": {"name": name}})


@pytest.mark.parametrize("name", ["findmilk", "driving", "my run 2", "kl0.5", "a_b-c+d"])
def test_safe_names_accepted(name):
    scenario = scenario_from_dict({"name": name})
    assert scenario.default_run_dir() == Path("runs") / name


def test_unsafe_file_stem_refused(tmp_path):
    path = tmp_path / ".hidden.toml"
    path.write_text("[task]\nseed = 3\n")
    text = load_error(path)
    assert "file name" in text and "'.hidden'" in text


def test_scenario_built_in_code_checks_its_name():
    with pytest.raises(ScenarioError, match="safe path component"):
        Scenario(name="../../escaped")
    with pytest.raises(ScenarioError, match="safe path component"):
        Scenario(**{**dict(Scenario()), "name": "a/b"})


def test_safe_child_stays_inside_the_root(tmp_path):
    safe_child = scenario_mod.safe_child
    assert safe_child(tmp_path, "run") == tmp_path / "run"
    assert safe_child("runs", "run") == Path("runs") / "run"
    for bad in ("../escaped", "..", "a/b", str(tmp_path)):
        with pytest.raises(ScenarioError, match="safe path component"):
            safe_child(tmp_path, bad)
    scenario = scenario_from_dict({"name": "findmilk"})
    assert scenario.default_run_dir(tmp_path) == tmp_path / "findmilk"


# ------------------------------------------------------------------ shipped files
SHIPPED = sorted(resolve_scenario_path("findmilk").parent.glob("*.toml"))


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scenarios_still_load(path):
    scenario = load_scenario(path)
    assert scenario.default_run_dir().name == scenario.name


def test_the_docs_list_every_range():
    docs = Path(__file__).resolve().parents[1] / "docs" / "learning.md"
    text = docs.read_text(encoding="utf-8").split("## Scenario value ranges", 1)[1]
    text = text.split("\n## ", 1)[0]
    for section, cls in SECTIONS.items():
        for name in cls.model_fields:
            rng = scenario_mod.field_range(cls, name)
            if rng is not None:
                row = f"`[{section}].{name}`"
                assert row in text, f"docs/learning.md does not list {row}"
                assert rng.describe() in text.split(row, 1)[1].split("\n", 1)[0], row


def test_a_2_gb_scenario_is_refused_from_its_size_unread(tmp_path):
    from amuled_ma.scenario.loading import MAX_SCENARIO_BYTES, MAX_SCENARIO_CHARS

    assert MAX_SCENARIO_BYTES == 4 * MAX_SCENARIO_CHARS  # UTF-8's most bytes a character
    path = tmp_path / "big.toml"
    sparse(path, 2 * 10**9)
    start = time.perf_counter()
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert time.perf_counter() - start < 1.0
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: the scenario is 2,000,000,000 bytes, more than the ")
    assert f"{MAX_SCENARIO_BYTES:,} a scenario may be" in message and "it is not read" in message
