"""Which jobs train together, how many fit a memory budget, what each member's feedback sees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from job_settings import job_shape_of

from amuled_ma.deliberation.mdp import CopiesView, MemberFeedback
from amuled_ma.learn.population_groups import (
    MEMBER_OVERHEAD_BYTES,
    MemberSpec,
    member_memory_bytes,
    population_key,
    split_populations,
)
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

#: (scenario, variant) -> (copies, rollout, learning rate, annealed, shaping c, task weight),
#: read from the scenario files' own lines (scenarios/*.toml), not from the code.
SHAPES = {
    ("findmilk-authors", "base"): (8, 128, 2.5e-4, True, 0.0, 1.0),
    ("findmilk-authors", "shaped"): (8, 128, 2.5e-4, True, 1.0, 1.0),
    ("findmilk-authors", "finetune:amuled"): (1, 128, 2.5e-4, False, 0.0, 0.0),
    ("driving-authors", "finetune:amuled"): (1, 128, 2.5e-4, False, 0.0, 0.0),
}


@pytest.mark.parametrize(("name", "variant"), sorted(SHAPES))
def test_job_shape_reads_the_scenarios_run_shape(name, variant) -> None:
    """The one derivation ``Trainer`` and the population learner both use."""
    scenario = load_scenario(name)
    shape = job_shape_of(scenario, Variant.parse(variant))
    envs, steps, lr, anneal, shaping, task_weight = SHAPES[(name, variant)]
    assert (shape.num_envs, shape.steps_per_env) == (envs, steps)
    assert (shape.learning_rate, shape.anneal) == (lr, anneal)
    assert (shape.shaping_coef, shape.task_weight) == (shaping, task_weight)
    assert shape.cfg["num_steps_per_env"] == steps
    if variant.startswith("finetune"):
        assert shape.total_iterations == 1000  # finetune_moral.py: 1000 x 128 / 128
        assert shape.cfg["algorithm"]["num_learning_epochs"] == 8
    assert job_shape_of(scenario, Variant.parse(variant), iterations=7).total_iterations == 7


def jobs(tmp_path: Path, count: int, **finetune) -> list[MemberSpec]:
    scenario = load_scenario("findmilk-authors").replace("finetune", **finetune)
    return [
        MemberSpec(scenario, tmp_path / f"j{k}", variant=Variant.finetune("amuled"), seed=k)
        for k in range(count)
    ]


def test_members_may_differ_in_seed_feedback_kl_and_recipe(tmp_path) -> None:
    a, b = jobs(tmp_path, 2)
    b.variant = Variant.finetune("cluster:care")
    b.scenario = b.scenario.replace("finetune", lambda_kl=0.5, recipe="equation")
    b.scenario = b.scenario.replace("feedback", fusion="mean")
    assert population_key(a) == population_key(b)


@pytest.mark.parametrize(
    ("section", "change"),
    [
        ("finetune", {"num_envs": 2}),
        ("finetune", {"iterations": 10}),
        ("finetune", {"learning_rate": 1e-3}),
        ("finetune", {"num_learning_epochs": 4}),
        ("ppo", {"hidden_dims": [32, 32]}),
        ("task", {"max_steps": 50}),
    ],
)
def test_members_share_the_task_network_and_run_shape(tmp_path, section, change) -> None:
    a, b = jobs(tmp_path, 2)
    b.scenario = b.scenario.replace(section, **change)
    assert population_key(a) != population_key(b)


def test_populations_split_under_a_memory_budget(tmp_path) -> None:
    specs = jobs(tmp_path, 10)
    other = jobs(tmp_path / "other", 3, num_envs=2)
    each = member_memory_bytes(specs[0].shape())
    assert each > MEMBER_OVERHEAD_BYTES
    # the same key, everything fits: one population
    assert split_populations(specs, 100 * each) == [list(range(10))]
    # four fit: as even as possible, 4 + 3 + 3, in order
    assert split_populations(specs, 4 * each + 1) == [[0, 1, 2, 3], [4, 5, 6], [7, 8, 9]]
    # a budget below one member still trains each job (alone)
    assert split_populations(specs[:2], 1) == [[0], [1]]
    assert split_populations(specs, 100 * each, max_size=5) == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]]
    # other keys are other populations
    mixed = split_populations([*specs[:2], *other], 100 * each)
    assert mixed == [[0, 1], [2, 3, 4]]


def test_memory_per_member_grows_with_the_rollout_and_the_network(tmp_path) -> None:
    (spec,) = jobs(tmp_path, 1)
    small = member_memory_bytes(spec.shape(), device="cuda")
    wide = spec.scenario.replace("ppo", hidden_dims=[256, 256])
    assert (
        member_memory_bytes(job_shape_of(wide, Variant.finetune("amuled")), device="cuda") > small
    )
    long = spec.scenario.replace("finetune", num_envs=64)
    assert (
        member_memory_bytes(job_shape_of(long, Variant.finetune("amuled")), device="cuda")
        > 10 * small
    )


class Prompts:
    """A task of 6 copies whose prompt variables name the copy."""

    num_envs = 6
    obs = torch.arange(12.0).reshape(6, 2)
    name = "toy"

    def prompt_variables(self, env_ids=None):
        ids = range(6) if env_ids is None else env_ids
        return [{"copy": int(i)} for i in ids]


def test_a_members_feedback_sees_its_copies_numbered_from_zero() -> None:
    view = CopiesView(Prompts(), 2, 2)
    assert view.num_envs == 2 and view.name == "toy"
    assert view.prompt_variables() == [{"copy": 2}, {"copy": 3}]
    assert view.prompt_variables([1]) == [{"copy": 3}]
    assert torch.equal(view.obs, Prompts.obs[2:4])

    seen = []

    def member(k):
        def feedback(obs, task):
            seen.append((k, obs.tolist(), task.prompt_variables()))
            return np.full((len(obs), 3), float(k))

        return feedback

    fused = MemberFeedback([member(0), member(1), member(2)], 2)(Prompts.obs, Prompts())
    assert fused.shape == (6, 3) and fused[:, 0].tolist() == [0, 0, 1, 1, 2, 2]
    assert seen[1] == (1, [[4.0, 5.0], [6.0, 7.0]], [{"copy": 2}, {"copy": 3}])


def test_prompt_variables_are_read_once_a_step_for_every_copy() -> None:
    task = Prompts()
    reads = []
    original = task.prompt_variables

    def counted(env_ids=None):
        reads.append(env_ids)
        return original(env_ids)

    task.prompt_variables = counted  # type: ignore[method-assign]

    def member(obs, view):
        return np.array([[float(v["copy"])] for v in view.prompt_variables()])

    feedback = MemberFeedback([member, member, member], 2)
    assert feedback(task.obs, task)[:, 0].tolist() == [0, 1, 2, 3, 4, 5]
    assert reads == [None]  # one read of all copies, served to the three members
    feedback(task.obs, task)
    assert reads == [None, None]  # and again the next step (the states changed)
