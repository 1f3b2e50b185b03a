"""DeliberationEnv: PettingZoo API and seed tests on every task, rewards, projection."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, seed_test
from pettingzoo.test.seed_test import parallel_seed_test

from amuled_ma.deliberation import DeliberationEnv, project_to_simplex
from amuled_ma.deliberation.env import env, parallel_env
from amuled_ma.errors import ScenarioError

TASKS = ["findmilk", "driving"]


def test_an_unknown_task_names_the_known_ones():
    with pytest.raises(ScenarioError, match="unknown task 'nope'; known tasks: findmilk, driving"):
        parallel_env("nope")


@pytest.mark.parametrize("task", TASKS)
def test_parallel_api(task):
    parallel = parallel_env(task, max_steps=40)
    assert isinstance(parallel, DeliberationEnv) and parallel.task_name == task
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "agent was not given ..." style warnings
        parallel_api_test(parallel, num_cycles=100)


@pytest.mark.parametrize("task", TASKS)
def test_aec_api(task):
    # advisory warnings (agent naming, Dict observations) are expected for this design
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        api_test(env(task, max_steps=30), num_cycles=50)


@pytest.mark.parametrize("task", TASKS)
def test_seed_aec_form(task):
    seed_test(lambda: env(task, max_steps=40), num_cycles=60)
    parallel_seed_test(lambda: parallel_env(task, max_steps=40), num_cycles=60)


@pytest.mark.parametrize("task", TASKS)
def test_observations_in_spaces_random_beliefs(task):
    env = parallel_env(task, max_steps=15)
    obs, infos = env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(30):
        for agent in env.agents:
            assert env.observation_space(agent).contains(obs[agent]), agent
        actions = {a: env.action_space(a).sample() for a in env.agents}
        # out-of-box beliefs are projected, not rejected
        actions[env.agents[1]] = rng.normal(size=len(env.action_names)) * 5
        obs, rewards, term, trunc, infos = env.step(actions)
        fused = infos["actor"]["fused"]
        assert fused.shape == (len(env.action_names),) and fused.sum() == pytest.approx(1.0)
        assert sum(rewards[c] for c in env.cluster_names) == pytest.approx(1.0)
        if not env.agents:
            assert all(term.values()) or all(trunc.values())
            obs, _ = env.reset()


def test_rewards_and_infos_hand_computed():
    env = DeliberationEnv("findmilk", ["a", "b"], "mean", r_env_weight=2.0, feedback_coef=3.0)
    env.reset(seed=0)
    # a says up, b says down -> mean [.5, .5, 0, 0]; the actor goes up: feedback .5
    _obs, rew, _term, _trunc, info = env.step({"actor": 0, "a": [1, 0, 0, 0], "b": [0, 1, 0, 0]})
    r_env = info["actor"]["r_env"]
    assert rew["actor"] == pytest.approx(2.0 * r_env + 3.0 * 0.5)
    # mean rule: each cluster's share of the fused mass, .5 each
    assert rew["a"] == pytest.approx(0.5) and rew["b"] == pytest.approx(0.5)
    np.testing.assert_allclose(info["b"]["fused"], [0.5, 0.5, 0, 0])
    assert info["a"]["weights"] == pytest.approx({"a": 0.5, "b": 0.5})
    assert info["a"]["conflict"] == 0.0 and info["a"]["r_feedback"] == pytest.approx(0.5)
    # a missing cluster belief counts as uniform: mean of [1,0,0,0] and [.25]*4 at "left"
    _, rew, _, _, info = env.step({"actor": 2, "a": [1, 0, 0, 0]})
    np.testing.assert_allclose(info["actor"]["fused"], [0.625, 0.125, 0.125, 0.125])
    assert rew["actor"] == pytest.approx(2.0 * info["actor"]["r_env"] + 3.0 * 0.125)


def test_bjs_dst_identical_beliefs_info():
    env = DeliberationEnv("findmilk", ["a", "b", "c"])
    env.reset(seed=0)
    m = [0.5, 0.5, 0.0, 0.0]
    _, rew, _, _, info = env.step({"actor": 1, "a": m, "b": m, "c": m})
    # identical beliefs: weights 1/3, fused m^3 / sum m^3 = m, first conflict 1 - sum m^2 = .5
    np.testing.assert_allclose(info["actor"]["fused"], m, atol=1e-12)
    assert rew["a"] == pytest.approx(1 / 3)
    assert info["c"]["conflict"] == pytest.approx(0.5)


def test_episode_end_truncation():
    env = parallel_env("findmilk", max_steps=3)
    env.reset(seed=0)
    for step in range(3):
        assert env.agents == env.possible_agents
        acts = {a: env.action_space(a).sample() for a in env.agents}
        acts["actor"] = 0 if step % 2 else 1  # dither: never reaches the milk in 3 steps
        obs, _rew, term, trunc, _info = env.step(acts)
    assert env.agents == [] and all(trunc.values()) and not any(term.values())
    assert obs["care"]["prompt"] == ""
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"actor": 0})


def test_bad_actions_and_arguments():
    env = parallel_env("findmilk")
    env.reset(seed=0)
    with pytest.raises(KeyError, match="actor"):
        env.step({"care": [1, 0, 0, 0]})
    with pytest.raises(ValueError, match=r"0\.\.3"):
        env.step({"actor": 4})
    with pytest.raises(ValueError, match="clusters"):
        DeliberationEnv("findmilk", ["actor"])
    with pytest.raises(ValueError):
        DeliberationEnv("findmilk", fusion_rule="no-such-rule")
    assert env.observation_space("care") is env.observation_space("care")
    assert env.action_space("actor") is env.action_space("actor")


# -- the projection, by hand -------------------------------------------------------------
@pytest.mark.parametrize(
    ("v", "expected"),
    [
        ([0.5, 0.5, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]),  # on the simplex: unchanged
        ([1.0, 1.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]),  # rho = 2, theta = -1/2
        ([0.2, 0.9, 0.4, 0.0], [1 / 30, 22 / 30, 7 / 30, 0.0]),  # rho = 3, theta = -1/6
        ([0.0, 0.0, 0.0, 0.0], [0.25, 0.25, 0.25, 0.25]),  # rho = 4, theta = 1/4
        ([3.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),  # rho = 1, theta = -2
        ([-1.0, 0.0, 2.0], [0.0, 0.0, 1.0]),  # rho = 1, theta = -1
        ([0.3, 0.3], [0.5, 0.5]),  # rho = 2, theta = 0.2
        ([np.nan, 1.0, 0.0], [1 / 3, 1 / 3, 1 / 3]),  # broken input: uniform
    ],
)
def test_project_to_simplex_by_hand(v, expected):
    np.testing.assert_allclose(project_to_simplex(v), expected, atol=1e-15)


def test_projection_is_the_nearest_point():
    rng = np.random.default_rng(1)
    for _ in range(200):
        v = rng.normal(size=5) * 2
        x = project_to_simplex(v)
        assert x.min() >= 0 and x.sum() == pytest.approx(1.0, abs=1e-12)
        # no random simplex point is closer (a KKT-free sanity check)
        for y in rng.dirichlet(np.ones(5), size=20):
            assert np.linalg.norm(x - v) <= np.linalg.norm(y - v) + 1e-12


def test_driven_by_a_moral_panel():
    from amuled_ma.beliefs.types import BeliefResult, BeliefSource
    from amuled_ma.deliberation import MoralPanel

    class Fixed(BeliefSource):
        name = "fixed"
        needs_messages = False

        def beliefs(self, requests):
            table = {"a": [0.0, 0.0, 1.0, 0.0], "b": [0.0, 0.0, 0.5, 0.5]}
            return [BeliefResult(np.array(table[r.cluster]), "ok", self.name) for r in requests]

    env = DeliberationEnv("findmilk", ["a", "b"], "mean")
    env.reset(seed=0)
    panel = MoralPanel("findmilk", ["b", "a"], Fixed(), "mean")
    actions = env.panel_actions(panel)
    np.testing.assert_allclose(actions["a"], [0, 0, 1, 0])
    np.testing.assert_allclose(actions["b"], [0, 0, 0.5, 0.5])
    _, rew, _, _, info = env.step({"actor": 2, **actions})
    np.testing.assert_allclose(info["actor"]["fused"], [0, 0, 0.75, 0.25])
    assert rew["actor"] == pytest.approx(info["actor"]["r_env"] + 0.75)
    with pytest.raises(KeyError, match="no cluster"):
        env.panel_actions(MoralPanel("findmilk", ["a"], Fixed(), "mean"))
