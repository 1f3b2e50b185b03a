import json

from fake_task import grid_factory

from amuled_ma.evaluate.evaluator import evaluate_run, run_episodes
from amuled_ma.evaluate.report import write_report
from amuled_ma.learn.trainer import Trainer, load_policy
from amuled_ma.scenario import scenario_from_dict


def scenario():
    return scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "base": {"total_steps": 4 * 32 * 5, "num_envs": 4, "num_steps_per_env": 32},
            "evaluation": {"episodes": 6},
            "output": {"tensorboard": False},
        }
    )


def test_run_episodes_one_record_per_copy(tmp_path):
    sc = scenario()
    out = Trainer(sc, tmp_path / "base", task_factory=grid_factory).train()
    actor = load_policy(out.checkpoint, sc)
    records, traj = run_episodes(actor, sc, episodes=5, mode="sampled", task_factory=grid_factory)
    assert len(records) == 5
    assert {"steps_to_milk", "reached_milk", "terminated"} <= set(records[0])
    assert len(traj["obs"]) == len(traj["actions"]) + 1
    greedy, _ = run_episodes(actor, sc, episodes=3, mode="greedy", task_factory=grid_factory)
    # a deterministic task and a greedy policy: every copy plays the same episode
    assert len({r["steps_to_milk"] for r in greedy}) == 1


def test_evaluate_run_writes_results_and_report(tmp_path):
    sc = scenario()
    Trainer(sc, tmp_path / "base", task_factory=grid_factory).train()
    Trainer(sc, tmp_path / "shaped", variant="shaped", task_factory=grid_factory).train()
    results = evaluate_run(tmp_path, sc, task_factory=grid_factory)
    assert set(results["variants"]) == {"base", "shaped"}
    stats = results["variants"]["base"]["greedy"]["metrics"]["steps_to_milk"]
    assert stats["n"] == 6 and stats["ci_low"] <= stats["mean"] <= stats["ci_high"]
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["episodes"] == 6
    csv = (tmp_path / "results.csv").read_text().splitlines()
    assert csv[0].startswith("variant,mode,metric,mean,ci_low,ci_high")
    report = write_report(tmp_path, results)
    text = report.read_text()
    assert "steps_to_milk" in text and "Fused-belief diagnostics" in text
    for name in (
        "curves_base.png",
        "metrics_greedy.png",
        "metrics_sampled.png",
        "trajectory_findmilk.png",
    ):
        assert (tmp_path / name).is_file(), name
        assert f"]({name})" in text
