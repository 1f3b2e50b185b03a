"""The smart-grid adapter over ``ethical-smart-grid`` (the extra ``amuled-ma[smartgrid]``).

Expected numbers come from the package's own functions called directly (its comfort
curve), from a single copy against a batch (the seeding convention), and by hand.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

pytest.importorskip("smartgrid")  # .ci/setup installs the extra; a bare install skips

from smartgrid.agents.profile.comfort import flexible_comfort_profile

from amuled_ma.beliefs.sources.rules import RulesSource
from amuled_ma.beliefs.types import BeliefRequest
from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import load_scenario
from amuled_ma.tasks import make_batched
from amuled_ma.tasks.prompts import render_state_prompt
from amuled_ma.tasks.smartgrid import JUDGE_TEMPERATURE, SmartGrid, action_vector


def test_each_named_action_in_the_packages_quantities():
    # need 753 Wh, battery 43 of 500 Wh: [grid, storage, store, give, buy, sell]
    assert action_vector(0, 753, 43, 500) == [753, 0, 0, 0, 0, 0]
    assert action_vector(1, 753, 43, 500) == [710, 43, 0, 0, 0, 0]
    assert action_vector(2, 753, 43, 500) == [376, 0, 0, 0, 0, 0]  # round(376.5), to even
    assert action_vector(3, 753, 43, 500) == [753, 0, 457, 0, 0, 0]
    assert action_vector(4, 753, 43, 500) == [376, 0, 0, 43, 0, 0]
    assert action_vector(1, 20, 43, 500) == [0, 20, 0, 0, 0, 0]  # the battery covers it


def test_copy_i_of_a_batch_is_a_single_copy_seeded_s_plus_i():
    """Also the package's global-observation memo (one per process) cleared per copy."""
    batch = make_batched("smartgrid", 3, seed=5, max_steps=6)
    alone = make_batched("smartgrid", 1, seed=7, max_steps=6)
    assert torch.equal(batch.reset()[2], alone.reset()[0])
    rng = np.random.default_rng(0)
    for _ in range(14):  # two auto-resets
        actions = torch.as_tensor(rng.integers(0, 5, 3))
        obs, reward, _, truncated, _ = batch.step(actions)
        one, one_reward, _, one_truncated, _ = alone.step(actions[2:])
        assert torch.equal(obs[2], one[0]) and torch.equal(reward[2], one_reward[0])
        assert bool(truncated[2]) == bool(one_truncated[0])


def test_the_comfort_judge_is_the_packages_comfort_of_each_action():
    task = make_batched("smartgrid", 1, seed=0)
    obs = task.reset()[0].numpy()
    learner = task.prompt_variables([0])[0]
    need, storage = learner["need"], learner["storage"]
    consumed = [sum(action_vector(a, need, storage, 500)[:2]) for a in range(5)]
    expected = np.array([flexible_comfort_profile(c, need) for c in consumed])
    scores = SmartGrid.judge_scores("comfort", obs)
    belief = np.exp((expected - expected.max()) / JUDGE_TEMPERATURE)
    np.testing.assert_allclose(scores / scores.sum(), belief / belief.sum(), rtol=1e-9)
    assert scores[2] < scores[0] == scores[1] == scores[3]  # half the need: less comfort


def test_rules_agents_answer_with_the_judges_and_refuse_a_replayed_state():
    task = make_batched("smartgrid", 2, seed=3)
    obs = task.reset().numpy()
    names = SmartGrid.action_names
    requests = [
        BeliefRequest(
            task="smartgrid", cluster="equity", obs=tuple(map(float, o)), action_names=names
        )
        for o in obs
    ]
    answers = RulesSource("judge:equity").beliefs(requests)
    assert [a.status for a in answers] == ["ok", "ok"]
    assert all(abs(a.belief.sum() - 1) < 1e-9 for a in answers)
    stale = BeliefRequest(task="smartgrid", cluster="equity", obs=(0.5,) * 11, action_names=names)
    (answer,) = RulesSource("judge:equity").beliefs([stale])
    assert answer.status == "error" and "no live smart-grid copy" in answer.extra["error"]


def test_the_state_prompt_and_the_episode_metrics():
    task = make_batched("smartgrid", 1, seed=0, max_steps=2)
    task.reset()
    text = render_state_prompt("smartgrid", task.prompt_variables([0])[0])
    assert "small smart grid of 4 prosumers" in text and "Action 4:" in text
    task.step(torch.tensor([0]))
    _, _, _, truncated, info = task.step(torch.tensor([2]))
    episode = info["episode"]
    assert bool(truncated[0]) and int(episode["length"][0]) == 2
    # return_env is the sum of the two steps' comfort; the mean per step is its half
    assert float(episode["comfort"][0]) == pytest.approx(float(episode["return_env"][0]) / 2)


def test_the_shipped_scenario_and_bad_options():
    scenario = load_scenario("smartgrid")
    assert scenario.feedback.clusters == ["comfort", "equity", "over_consumption"]
    with pytest.raises(ValueError, match=r"households: expected an integer in 1\.\.1000, got 0"):
        make_batched("smartgrid", 1, households=0)
    with pytest.raises(ScenarioError, match="option households"):
        load_scenario("smartgrid").replace("task", options={"households": 0})


def _package_step(env, action: int) -> dict:
    """The package's own ``SmartGrid.step`` on ``env``: the learner ``action``, others grid."""
    actions = {
        agent.name: action_vector(
            action if agent.name == "Household1" else 0,
            agent.need,
            agent.state.storage,
            agent.profile.max_storage,
        )
        for agent in env.world.agents
    }
    env.observation_manager.reset()  # the package's memo is keyed by the step alone
    obs, rewards, _, _, _ = env.step(actions)
    env.observation_manager.reset()
    return {"obs": np.asarray(np.asarray(obs["Household1"]), np.float32), **rewards["Household1"]}


def test_the_step_and_the_look_ahead_are_the_packages_own_step():
    """Each step's rewards and observation, and each judge's look-ahead reward of every action,
    equal what the package's ``SmartGrid.step`` returns on a deep copy of the same world."""
    task = make_batched("smartgrid", 1, seed=11, max_steps=24)
    obs = task.reset()
    env = task._envs[0]  # the adapter's package environment, read only
    rng = np.random.default_rng(1)
    for _ in range(6):
        reward = {a: _package_step(copy.deepcopy(env), a) for a in range(5)}
        for judge, name in (("comfort", "Comfort"), ("equity", "Equity")):
            expected = np.array([reward[a][name] for a in range(5)])
            scores = SmartGrid.judge_scores(judge, obs[0].numpy())
            np.testing.assert_allclose(
                JUDGE_TEMPERATURE * np.log(scores), expected - expected.max(), atol=1e-9
            )
        expected = np.array([reward[a]["OverConsumption"] for a in range(5)])
        scores = SmartGrid.judge_scores("over_consumption", obs[0].numpy())
        np.testing.assert_allclose(
            JUDGE_TEMPERATURE * np.log(scores), expected - expected.max(), atol=1e-9
        )
        action = int(rng.integers(0, 5))
        obs, _, _, _, info = task.step(torch.tensor([action]))
        assert float(info["r_env"][0]) == pytest.approx(reward[action]["Comfort"], abs=1e-6)
        assert float(info["r_shaping"][0]) == pytest.approx(reward[action]["Equity"], abs=1e-6)
        np.testing.assert_array_equal(info["final_obs"][0].numpy(), reward[action]["obs"])


def test_a_state_two_tasks_show_stays_judgeable_when_one_moves_on():
    """Seed replicas of a population share copies (copy 1 seeded 5 is copy 0 seeded 6)."""
    first = make_batched("smartgrid", 2, seed=5)
    second = make_batched("smartgrid", 2, seed=6)
    shown = first.reset()[1].numpy()
    np.testing.assert_array_equal(second.reset()[0].numpy(), shown)
    second.step(torch.tensor([4, 4]))
    scores = SmartGrid.judge_scores("equity", shown)  # first's copy 1 still shows it
    assert scores.shape == (5,) and scores.max() == 1.0


def test_a_moral_agent_on_the_synthetic_human_is_refused_and_left_out_of_the_ablation(
    tmp_path, capsys
):
    from amuled_ma.deliberation.plan import NoHumanRule, plan_panel
    from amuled_ma.experiments.plans import plan_ablation

    scenario = load_scenario("smartgrid")  # [feedback].source = "rules": the moral agent's too
    problems = plan_panel("moral", scenario).problems
    assert [type(error) for error, _ in problems] == [NoHumanRule]
    assert '"judge:comfort"' in str(problems[0][0])  # the fix names the task's judges
    assert plan_panel("amuled", scenario).problems == ()  # every value has its judge
    assert (
        plan_panel("moral", load_scenario("findmilk").replace("feedback", source="rules")).problems
        == ()
    )  # the paper's task has its human
    jobs = plan_ablation("clusters", scenario, tmp_path, [1])
    folders = sorted(job.out_dir.name for job in jobs)
    assert folders == [
        "base", "finetune-amuled", "finetune-cluster-comfort", "finetune-cluster-equity",
        "finetune-cluster-over_consumption",
    ]  # fmt: skip
    assert "no 'moral' row" in capsys.readouterr().err
