"""``[task].options`` are checked when the scenario is read, before any run folder exists.

A bad option (``amuled run findmilk --set 'task.options={layout="evil"}'``) is refused
before the run folder, the belief store or a local Ray exists, not by the first job's task
seconds later. The option models
of :mod:`amuled_ma.scenario.task_options` must stay equal to the tasks' constructors: the
second half of this file holds them together.
"""

from __future__ import annotations

import inspect

import pytest
from tiny_cli import RULES, TINY, amuled, one_line

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import load_scenario
from amuled_ma.scenario.task_options import RESERVED, TASK_OPTIONS, options_model
from amuled_ma.tasks import TASKS, make_batched
from amuled_ma.tasks.names import ALIASES, BUILTIN_TASKS, TASK_NAMES, canonical_name


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ('{layout="evil"}', "option layout should be 'paper' or 'random', found 'evil'"),
        ("{evil=1}", "unknown option 'evil'"),
        ("{max_steps=5}", "max_steps cannot be a task option"),
        ('{tie_break="last"}', "option tie_break should be 'first' or 'random'"),
    ],
)
def test_run_refuses_bad_task_options_before_any_folder(tmp_path, options, expected):
    run_dir = tmp_path / "runs" / "x"
    args = ["run", "findmilk", "--run-dir", str(run_dir), "--jobs", "2", *TINY, *RULES]
    done = amuled(*args, "--set", f"task.options={options}", cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    line = one_line(done.stderr)
    assert "key [task].options" in line and expected in line, line
    assert "(override of [task])" in line, line  # names where the value came from
    assert not (tmp_path / "runs").exists(), sorted(p.name for p in tmp_path.rglob("*"))


def test_a_scenario_file_with_bad_task_options_is_one_line_naming_it(tmp_path):
    path = tmp_path / "driving-evil.toml"
    path.write_text('[task]\nname = "driving"\noptions = {p_car = 1.5}\n')
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert message.startswith(f"{path}: key [task].options of task 'driving': option p_car")
    assert "found 1.5" in message and "\n" not in message
    path.write_text('[task]\nname = "driving"\noptions = {p_car = true}\n')
    with pytest.raises(ScenarioError, match="option p_car should be a valid number"):
        load_scenario(path)
    path.write_text('[task]\nname = "driving"\noptions = {p_car = 1, p_grandma = 0.5}\n')
    assert load_scenario(path).task.options == {"p_car": 1, "p_grandma": 0.5}


def test_the_options_a_task_accepts_still_load():
    for name, options in (("findmilk", {"layout": "random", "tie_break": "random"}),
                          ("driving", {"p_car": 0.0, "p_grandma": 1.0})):  # fmt: skip
        scenario = load_scenario(name).replace("task", options=options)
        assert scenario.task.options == options


# ------------------------------------------------- the models equal the tasks' constructors
def _task_parameters(name: str) -> dict[str, inspect.Parameter]:
    """The keyword options of a task: the parameters of its ``_init_task``."""
    signature = inspect.signature(TASKS[name]._init_task)
    skip = {"self", "num_envs", *RESERVED}
    return {p: v for p, v in signature.parameters.items() if p not in skip}


@pytest.mark.parametrize("name", BUILTIN_TASKS)
def test_each_task_has_an_option_model_with_its_options_and_defaults(name):
    model = TASK_OPTIONS[name]
    parameters = _task_parameters(name)
    assert list(model.model_fields) == list(parameters), (
        f"the options of {name} changed: declare them in amuled_ma/scenario/task_options.py"
    )
    for option, parameter in parameters.items():
        assert model.model_fields[option].default == parameter.default, option


def _values_of(annotation: object) -> tuple[object, ...]:
    return getattr(annotation, "__args__", ())


@pytest.mark.parametrize("name", TASK_NAMES)
def test_the_model_and_the_task_accept_and_refuse_the_same_values(name):
    model = TASK_OPTIONS[name]
    for option, field in model.model_fields.items():
        choices = _values_of(field.annotation)
        good = list(choices) or [0.0, 0.5, 1, 1.0]
        bad = ["evil", 7] if choices else [-0.1, 1.5, "0.5", True]
        for value in good:
            model.model_validate({option: value})
            make_batched(name, 1, **{option: value})  # the task takes it too
        for value in bad:
            with pytest.raises(ValueError):
                model.model_validate({option: value})
            with pytest.raises((TypeError, ValueError)):
                make_batched(name, 1, **{option: value})


def test_every_spelling_of_a_task_name_finds_its_model():
    for spelling in (*TASK_NAMES, *ALIASES, "FindMilk", " Driving "):
        assert options_model(spelling) is TASK_OPTIONS[canonical_name(spelling)], spelling
    assert options_model("no-such-task") is None
