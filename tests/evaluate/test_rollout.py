"""One rollout: the viewer's episode K is the evaluated episode K, greedy and sampled.

The evaluated episodes are ``amuled evaluate``'s (``results.json``: each copy's length and
return, copy 0's actions); the actions of every copy are recomputed here by a plain loop
written from the evaluator's definition (N copies seeded ``seed + i``, one generator seeded
``seed``, one ``torch.multinomial`` over the batch per step), tied to ``results.json``
before the viewer is compared with it.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_cli import RULES, TINY

from amuled_ma.cli import main
from amuled_ma.evaluate.episode_trace import replay_variant
from amuled_ma.evaluate.rollout import rollout
from amuled_ma.experiments.run_folder import scenario_of_run
from amuled_ma.experiments.trained_variants import trained_variant
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.tasks import make_task

#: Episodes of the tiny evaluation (``amuled evaluate --episodes``).
N = 6


@pytest.fixture(scope="module", params=["findmilk", "driving"])
def evaluated_run(request, tmp_path_factory) -> Path:
    """A tiny trained and evaluated base policy (greedy and sampled, N episodes)."""
    task = request.param
    run = tmp_path_factory.mktemp(f"rollout-{task}") / task
    assert main(["train", task, "--run-dir", str(run), *TINY, *RULES]) == 0
    assert main(["evaluate", str(run), "--episodes", str(N), "--no-progress"]) == 0
    return run


def by_hand(run: Path, mode: str, n: int = N):
    """Every copy's first episode, from the evaluator's definition, written out here."""
    scenario = scenario_of_run(run)
    actor = load_policy(run / "base" / "model_last.pt", scenario.ppo)
    seed = scenario.evaluation.seed
    task = make_task(scenario.task, n, shaping_coef=0.0, seed=seed)
    obs = torch.as_tensor(task.reset()).float()
    gen = torch.Generator().manual_seed(seed)
    actions: list[list[int]] = [[] for _ in range(n)]
    rewards: list[list[float]] = [[] for _ in range(n)]
    ended = [False] * n
    with torch.inference_mode():
        for _ in range(task.max_steps + 1):
            probs = action_log_probs(actor, obs).exp()
            if mode == "greedy":
                chosen = probs.argmax(-1)
            else:
                chosen = torch.multinomial(probs, 1, generator=gen).squeeze(-1)
            obs, _, term, trunc, info = task.step(chosen)
            obs = torch.as_tensor(obs).float()
            for i in range(n):
                if not ended[i]:
                    actions[i].append(int(chosen[i]))
                    rewards[i].append(float(info["r_env"][i]))
                    ended[i] = bool(term[i]) or bool(trunc[i])
            if all(ended):
                break
    return actions, rewards


def page_data(path: Path) -> dict:
    found = re.search(
        r'<script type="application/json" id="amuled-data">(.*?)</script>',
        path.read_text(encoding="utf-8"),
        re.S,
    )
    assert found, "no data block in the page"
    return json.loads(found.group(1))


@pytest.mark.parametrize("mode", ["greedy", "sampled"])
def test_the_viewers_episode_is_the_evaluated_episode(evaluated_run, mode, tmp_path):
    run = evaluated_run
    results = json.loads((run / "results.json").read_text())
    assert results["episodes"] == N
    evaluated = results["variants"]["base"][mode]
    actions, rewards = by_hand(run, mode)
    # the loop written here plays the evaluation's episodes (its published numbers)
    assert actions[0] == evaluated["trajectory"]["actions"]
    for k, record in enumerate(evaluated["episodes"]):
        assert len(actions[k]) == record["length"]
        assert sum(rewards[k]) == pytest.approx(record["return_env"], abs=1e-4)
    trained = trained_variant(run, run / "base")
    for k in range(N):
        # the library's replay, with the evaluation's N taken from results.json
        ep = replay_variant(trained, episode=k, mode=mode, episodes=N)
        assert ep.actions.tolist() == actions[k], f"episode {k}"
        np.testing.assert_allclose(ep.rewards, rewards[k], atol=1e-6)
        assert ep.length == evaluated["episodes"][k]["length"]
        assert ep.seed == results["seed"] + k
    # the page of amuled view (N read from results.json by the command)
    for k in (0, N - 1):
        out = tmp_path / f"view{k}.html"
        argv = ["view", str(run), "--variant", "base", "--episode", str(k), "--mode", mode]
        assert main([*argv, "-o", str(out)]) == 0
        v = page_data(out)["variants"][0]
        assert v["a"] == actions[k] and v["T"] == len(actions[k])
        np.testing.assert_allclose(v["r"], rewards[k], atol=0.005 + 1e-9)


def test_a_sampled_episode_needs_the_whole_batch(evaluated_run):
    """One copy with its own generator (the viewer before one rollout) plays other episodes."""
    scenario = scenario_of_run(evaluated_run)
    actor = load_policy(evaluated_run / "base" / "model_last.pt", scenario.ppo)
    actions, _ = by_hand(evaluated_run, "sampled")
    differ = 0
    for k in range(N):
        seed = scenario.evaluation.seed + k
        task = make_task(scenario.task, 1, shaping_coef=0.0, seed=seed)
        obs = torch.as_tensor(task.reset()).float()
        gen = torch.Generator().manual_seed(seed)
        alone = []
        with torch.inference_mode():
            for _ in range(task.max_steps):
                a = torch.multinomial(action_log_probs(actor, obs).exp(), 1, generator=gen)
                alone.append(int(a[0, 0]))
                obs, _, term, trunc, _ = task.step(a.squeeze(-1))
                obs = torch.as_tensor(obs).float()
                if bool(term[0]) or bool(trunc[0]):
                    break
        differ += alone != actions[k]
    assert differ > 0


def test_rollout_checks_its_arguments(evaluated_run):
    from amuled_ma.errors import ScenarioError

    scenario = scenario_of_run(evaluated_run)
    actor = load_policy(evaluated_run / "base" / "model_last.pt", scenario.ppo)
    with pytest.raises(ScenarioError, match="mode: expected one of greedy, sampled"):
        rollout(actor, scenario.task, episodes=2, mode="softmax", seed=0)
    with pytest.raises(ScenarioError, match=r"until: expected copies in 0\.\.1"):
        rollout(actor, scenario.task, episodes=2, seed=0, until=[2])
    trained = trained_variant(evaluated_run, evaluated_run / "base")
    with pytest.raises(ScenarioError, match=r"evaluation episode 0\.\.5 .* found 6"):
        replay_variant(trained, episode=N, episodes=N)
