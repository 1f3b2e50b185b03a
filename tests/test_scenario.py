from pathlib import Path

import pytest

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import load_scenario, resolve_scenario_path, scenario_from_dict


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", ["findmilk", "driving"])
def test_shipped_scenarios_load_by_name(name):
    scenario = load_scenario(name)
    assert scenario.task.name == name
    assert scenario.finetune.lambda_kl == 2.5
    assert scenario.evaluation.episodes == 50
    assert scenario.ppo.hidden_dims == [64, 64]
    assert scenario.ppo.learning_rate == 2.5e-4
    assert len(scenario.feedback.clusters) == 5
    assert scenario.path is not None and scenario.path.is_file()


def test_every_number_in_shipped_scenarios_is_commented():
    for path in resolve_scenario_path("findmilk").parent.glob("*.toml"):
        for line in path.read_text().splitlines():
            code = line.split("#", 1)[0]
            if "=" in code and any(ch.isdigit() for ch in code.split("=", 1)[1]):
                assert "#" in line, f"{path.name}: number without a comment: {line}"


def test_unknown_key_names_file_key_and_choices(tmp_path):
    path = write(tmp_path, "[ppo]\nlearnin_rate = 0.1\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    text = str(info.value)
    assert str(path) in text and "[ppo].learnin_rate" in text and "learning_rate" in text


def test_unknown_section(tmp_path):
    with pytest.raises(ScenarioError, match="unknown section"):
        load_scenario(write(tmp_path, "[pppo]\nx = 1\n"))


def test_wrong_type_names_expected_and_found(tmp_path):
    path = write(tmp_path, '[finetune]\nlambda_kl = "big"\n')
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    text = str(info.value)
    assert str(path) in text and "[finetune].lambda_kl" in text
    assert "expects float" in text and "found string" in text


def test_int_accepted_for_float_but_not_bool_for_int(tmp_path):
    scenario = load_scenario(write(tmp_path, "[finetune]\nlambda_kl = 3\n"))
    assert scenario.finetune.lambda_kl == 3.0 and isinstance(scenario.finetune.lambda_kl, float)
    with pytest.raises(ScenarioError, match="expects integer, found boolean"):
        load_scenario(write(tmp_path, "[base]\nnum_envs = true\n"))


def test_list_element_type_checked(tmp_path):
    with pytest.raises(ScenarioError, match="list of integer"):
        load_scenario(write(tmp_path, '[ppo]\nhidden_dims = [64, "x"]\n'))


def test_choices_and_positive(tmp_path):
    with pytest.raises(ScenarioError, match="replay, ollama, rules"):
        load_scenario(write(tmp_path, '[feedback]\nsource = "gpt"\n'))
    with pytest.raises(ScenarioError, match="positive"):
        load_scenario(write(tmp_path, "[finetune]\niterations = 0\n"))


def test_invalid_toml(tmp_path):
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(write(tmp_path, "[ppo\n"))


def test_missing_scenario_lists_shipped():
    with pytest.raises(ScenarioError, match="findmilk"):
        load_scenario("no-such-scenario")


def test_paths_resolve_against_scenario_file(tmp_path):
    path = write(tmp_path, '[feedback]\nrecording = "rec/x.json"\n')
    scenario = load_scenario(path)
    assert scenario.recording_path() == (tmp_path / "rec" / "x.json").resolve()


def test_replace_validates():
    scenario = scenario_from_dict({})
    assert scenario.replace("finetune", lambda_kl=1.0).finetune.lambda_kl == 1.0
    with pytest.raises(ScenarioError):
        scenario.replace("finetune", lambda_kl="x")


def test_to_dict_round_trip():
    scenario = load_scenario("findmilk")
    data = scenario.to_dict()
    data.pop("path")
    again = scenario_from_dict(data)
    assert again.ppo == scenario.ppo and again.feedback == scenario.feedback
