"""A task published by another package through the ``amuled_ma.tasks`` entry-point group.

The toy task, its module and its prompt template are written by the test into a folder put
on ``sys.path`` with a ``*.dist-info/entry_points.txt``, which is how an installed package
publishes an entry point; ``importlib.metadata`` finds it, and nothing in ``amuled_ma/``
names the task.
"""

from __future__ import annotations

import sys
import textwrap

import numpy as np
import pytest
import torch

from amuled_ma.beliefs.sources.rules import RulesSource
from amuled_ma.beliefs.types import BeliefRequest
from amuled_ma.errors import ScenarioError
from amuled_ma.tasks import TASKS, canonical_name, get_task, make_batched
from amuled_ma.tasks.prompts import render_state_prompt

TOY_MODULE = '''
from pathlib import Path

import numpy as np
import torch

from amuled_ma.tasks.base import BatchedTask


class ToyCoin(BatchedTask):
    """A coin counter: action 1 takes a coin (+1), action 0 leaves it; 3 steps."""

    name = "toycoin"
    gym_id = ""
    action_names = ("leave", "take")
    obs_names = ("coins",)
    obs_low = (0.0,)
    obs_high = (3.0,)
    metric_names = ("taken",)
    judge_names = ("honesty",)
    prompt_template = Path(__file__).with_name("toycoin.md")

    def _init_task(self):
        self._coins = torch.zeros(self.num_envs)

    def _advance(self, actions):
        took = actions == 1
        self._coins = self._coins + took
        n = self.num_envs
        return took.float(), torch.zeros(n), torch.zeros(n, dtype=torch.bool), {
            "taken": took.to(torch.int64)
        }

    def _reset_where(self, mask):
        self._coins = torch.where(mask, 0.0, self._coins)

    def _observe(self):
        return self._coins[:, None].clone()

    @classmethod
    def prompt_variables_from_obs(cls, obs, **extra):
        return {"coins": int(obs[0])}

    @classmethod
    def judge_scores(cls, judge, obs):
        if judge != "honesty":
            return super().judge_scores(judge, obs)
        rows = np.atleast_2d(obs)
        out = np.tile([3.0, 1.0], (len(rows), 1))
        return out[0] if np.ndim(obs) == 1 else out

    def render_ansi(self, env_id=0):
        return f"coins {int(self._coins[env_id])}"

    def render_rgb(self, env_id=0, cell=32):
        return np.zeros((cell, cell, 3), dtype=np.uint8)
'''

TEMPLATE = """# Toy coin state prompt

## prompt

```text
You hold {coins} coins. Action 0: leave the coin. Action 1: take the coin.
```
"""


@pytest.fixture
def installed_toy(tmp_path, monkeypatch):
    """The toy task's package, installed as a folder on ``sys.path`` with its dist-info."""
    (tmp_path / "toy_task_pkg.py").write_text(TOY_MODULE)
    (tmp_path / "toycoin.md").write_text(TEMPLATE)
    info = tmp_path / "toy_task_pkg-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-task-pkg\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        textwrap.dedent(
            """\
            [amuled_ma.tasks]
            toycoin = toy_task_pkg:ToyCoin
            broken = toy_task_pkg:NoSuchThing
            notatask = numpy:ndarray
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("toy_task_pkg", None)


def test_an_unknown_task_names_the_entry_point_group():
    with pytest.raises(ScenarioError, match=r"'amuled_ma\.tasks' entry-point group"):
        get_task("toycoin")


def test_a_task_installed_through_the_entry_point_group_runs(installed_toy):
    assert canonical_name("ToyCoin") == "toycoin"
    assert "toycoin" in tuple(TASKS)
    task = make_batched("toycoin", 2, seed=0, max_steps=3)
    assert task.reset().tolist() == [[0.0], [0.0]]
    for _ in range(2):
        obs, reward, *_ = task.step(torch.tensor([1, 0]))
    assert obs.tolist() == [[2.0], [0.0]] and reward.tolist() == [1.0, 0.0]
    _, _, _, truncated, info = task.step(torch.tensor([1, 1]))
    assert truncated.tolist() == [True, True]
    assert info["episode"]["taken"].tolist() == [3, 1]  # 1 + 1 + 1, 0 + 0 + 1
    assert info["episode"]["return"].tolist() == [3.0, 1.0]
    text = render_state_prompt("toycoin", {"coins": 2})
    assert text == "You hold 2 coins. Action 0: leave the coin. Action 1: take the coin."


def test_the_rules_source_answers_with_a_plugin_tasks_judge(installed_toy):
    request = BeliefRequest(
        task="toycoin", cluster="honesty", obs=(1.0,), action_names=("leave", "take")
    )
    (answer,) = RulesSource("judge:honesty").beliefs([request])
    assert answer.status == "ok"
    np.testing.assert_allclose(answer.belief, [0.75, 0.25])  # scores 3 and 1, divided by 4
    (missing,) = RulesSource("judge:greed").beliefs([request])
    assert missing.status == "error" and "no judge 'greed'" in missing.extra["error"]


def test_a_bad_entry_point_is_one_line_naming_it(installed_toy):
    with pytest.raises(ScenarioError, match=r"'toy_task_pkg:NoSuchThing' failed to import"):
        get_task("broken")
    with pytest.raises(ScenarioError, match=r"'numpy:ndarray' is .*expected a subclass"):
        get_task("notatask")
