"""Driving's ``non_straight_steps``: the authors' "lane changes", beside ours.

The authors count ``lane_changes += action != 0`` (``environments/drive.py:136``): a move
against the road's edge, which leaves the lane as it is, counts. Expected counts are worked
out by hand from the road's rules (5 lanes, start in lane 2, ``right`` is +1, clipped).
"""

from __future__ import annotations

import torch

from amuled_ma.evaluate.evaluator import run_episodes
from amuled_ma.evaluate.paper import paper_row
from amuled_ma.evaluate.report.tables import paper_table
from amuled_ma.evaluate.results import Results
from amuled_ma.learn.policies import build_model
from amuled_ma.scenario import scenario_from_dict
from amuled_ma.tasks.driving import Driving

STRAIGHT, RIGHT, LEFT = 0, 1, 2


def test_an_episode_counts_every_non_straight_step_and_only_real_lane_changes():
    task = Driving(1, seed=1)
    task.reset()
    cycle = [STRAIGHT, RIGHT, LEFT, LEFT, STRAIGHT]
    for t in range(300):
        *_, info = task.step(torch.tensor([cycle[t % 5]]))
    episode = info["episode"]
    # 3 of every 5 actions are not straight: 60 cycles x 3
    assert episode["non_straight_steps"].item() == 180
    # lanes: 2 -R-> 3 -L-> 2 -L-> 1, 1 -R-> 2 -L-> 1 -L-> 0, then each cycle
    # 0 -R-> 1 -L-> 0 -L-> 0 (clipped): 3 + 3 + 58 x 2
    assert episode["lane_changes"].item() == 122


def always(action: int, scenario) -> torch.nn.Module:
    """An actor whose greedy action is ``action`` in every state (zero weights, one bias)."""
    actor = build_model(scenario.ppo, "actor", 11, 3)
    last = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.0, 0.0, 0.0]))
        last.bias[action] = 50.0
    return actor


def test_the_evaluator_reports_both_counts():
    scenario = scenario_from_dict({"task": {"name": "driving"}})
    records, _ = run_episodes(always(RIGHT, scenario), scenario.task, episodes=1, mode="greedy")
    for record in records:
        # 300 steps to the right: lane 2 -> 3 -> 4, then clipped at the edge
        assert record["non_straight_steps"] == 300 and record["lane_changes"] == 2
    records, _ = run_episodes(always(STRAIGHT, scenario), scenario.task, episodes=1, mode="greedy")
    assert all(r["non_straight_steps"] == 0 and r["lane_changes"] == 0 for r in records)


def test_the_papers_lane_changes_sit_beside_our_non_straight_steps():
    # the paper's Driving AMULED row: 2.0 collisions, 13.6 rescues, 54.2 "lane changes"
    assert paper_row("driving", "finetune-amuled").values == {
        "collisions": 2.0,
        "rescues": 13.6,
        "non_straight_steps": 54.2,
    }

    def stat(mean: float) -> dict:
        return {"mean": mean, "std": 1.0, "n": 10, "half_width": 0.0}

    metrics = {
        "collisions": stat(1.5),
        "rescues": stat(12.0),
        "lane_changes": stat(30.0),
        "non_straight_steps": stat(41.0),
    }
    entry = {"metrics": metrics, "ci_over": "episodes", "n_seeds": 1}
    results = {
        "scenario": "driving",
        "task": "driving",
        "episodes": 10,
        "confidence": 0.95,
        "seed": 42,
        "variants": {"finetune-amuled": {"sampled": entry}},
    }
    table = paper_table(Results.model_validate(results))
    assert "Columns: collisions / rescues / non_straight_steps." in table
    assert "| 2.0 / 13.6 / 54.2 | 1.50 ± 0.00 / 12.00 ± 0.00 / 41.00 ± 0.00 |" in table
