import json
import shutil

import pytest
from fake_task import grid_factory
from sparse_files import sparse
from tiny_cli import TINY, one_line

from amuled_ma.cli import main
from amuled_ma.evaluate.evaluator import evaluate_run, run_episodes
from amuled_ma.evaluate.report.writing import write_report
from amuled_ma.learn.policies import load_policy
from amuled_ma.learn.population import train_population
from amuled_ma.learn.population_groups import MemberSpec
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import scenario_from_dict


def train(sc, out_dir, variant: str = "base"):
    """Train one job alone (a population of one) on the fake grid task."""
    [outcome] = train_population(
        [MemberSpec(sc, out_dir, Variant.parse(variant), task_factory=grid_factory)]
    )
    return outcome


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
    out = train(sc, tmp_path / "base")
    actor = load_policy(out.checkpoint, sc.ppo)
    records, traj = run_episodes(
        actor, sc.task, episodes=5, mode="sampled", task_factory=grid_factory
    )
    assert len(records) == 5
    assert {"steps_to_milk", "reached_milk", "terminated"} <= set(records[0])
    assert len(traj["obs"]) == len(traj["actions"]) + 1
    greedy, _ = run_episodes(actor, sc.task, episodes=3, mode="greedy", task_factory=grid_factory)
    # a deterministic task and a greedy policy: every copy plays the same episode
    assert len({r["steps_to_milk"] for r in greedy}) == 1


def test_evaluate_run_writes_results_and_report(tmp_path):
    sc = scenario()
    train(sc, tmp_path / "base")
    train(sc, tmp_path / "shaped", "shaped")
    results = evaluate_run(
        tmp_path,
        scenario_name=sc.name,
        task_config=sc.task,
        evaluation=sc.evaluation,
        ppo=sc.ppo,
        task_factory=grid_factory,
    )
    assert set(results.variants) == {"base", "shaped"}
    stats = results.variants["base"].greedy.metrics["steps_to_milk"]
    assert stats.n == 6 and stats.ci_low <= stats.mean <= stats.ci_high
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


def test_seed_replicas_combine_over_seeds_by_hand():
    from amuled_ma.evaluate.evaluator import combine_replicas, merge_feedback

    # seed 1: rescues 2, 4 (mean 3); seed 2: 6, 6 (mean 6); seed 3: 0, 0 (mean 0)
    replicas = [
        ("finetune-amuled", [{"rescues": 2.0}, {"rescues": 4.0}], {"t": 1}),
        ("finetune-amuled.seed2", [{"rescues": 6.0}, {"rescues": 6.0}], {"t": 2}),
        ("finetune-amuled.seed3", [{"rescues": 0.0}, {"rescues": 0.0}], {"t": 3}),
    ]
    entry = combine_replicas(replicas, 0.95)
    stat = entry["metrics"]["rescues"]
    # per-seed means 3, 6, 0: mean 3, sample std 3, t_{0.975,2} = 4.3027 (t table)
    assert stat["n"] == 3 and stat["mean"] == 3.0 and stat["std"] == 3.0
    assert abs(stat["half_width"] - 4.3027 * 3.0 / 3**0.5) < 1e-4
    assert entry["ci_over"] == "seeds" and entry["trajectory"] == {"t": 1}
    assert entry["replicas"]["finetune-amuled.seed2"]["rescues"]["mean"] == 6.0
    one = combine_replicas(replicas[:1], 0.95)
    assert one["ci_over"] == "episodes" and one["metrics"]["rescues"]["n"] == 2

    a = {
        "feedback": "amuled",
        "steps": 10,
        "unique_states": 4,
        "mean_conflict": 0.2,
        "mean_weight": {"care": 0.3, "virtue": 0.1},
        "statuses": {"ok": 45, "replay_miss": 5},
    }
    b = {"feedback": "amuled", "steps": 30, "unique_states": 8, "mean_conflict": 0.4,
         "mean_weight": {"care": 0.5, "virtue": 0.3}, "statuses": {"ok": 150}}  # fmt: skip
    merged = merge_feedback([a, b])
    assert merged["steps"] == 40 and merged["unique_states"] == 6.0
    assert abs(merged["mean_conflict"] - 0.3) < 1e-12
    assert abs(merged["mean_weight"]["care"] - 0.4) < 1e-12
    assert merged["statuses"] == {"ok": 195, "replay_miss": 5}
    assert merged["miss_rate"] == 5 / 200


def test_learning_curve_band_over_seeds_by_hand():
    from amuled_ma.evaluate.report.curves import curve_band

    def curve(values):
        return [{"env_steps": 100 * (i + 1), "r": v} for i, v in enumerate(values)]

    # 3 rows: the rolling window is 1 row, so each seed's curve is its raw values
    x, mean, half, _ = curve_band([curve([1, 2, 3]), curve([3, 4, 5])], "r")
    assert x.tolist() == [100, 200, 300] and mean.tolist() == [2, 3, 4]
    # two seeds differing by 2: std sqrt(2), half = t_{0.975,1} * sqrt(2) / sqrt(2) = 12.7062
    assert all(abs(h - 12.7062) < 1e-4 for h in half)
    x, mean, half, _ = curve_band([curve([1, 2, 3]), curve([3, 4])], "r")  # cut to the shortest
    assert x.tolist() == [100, 200] and all(abs(h - 12.7062) < 1e-4 for h in half)


def test_learning_curve_band_iteration_no_seed_logged_is_nan_without_warning():
    import warnings

    import numpy as np

    from amuled_ma.evaluate.report.curves import curve_band

    # the metric is missing at the second row in both seeds (an episode metric that no
    # episode finished in that iteration): NaN there, one seed's value where only one has it
    a = [{"env_steps": 1, "r": 1.0}, {"env_steps": 2}, {"env_steps": 3, "r": 5.0}]
    b = [{"env_steps": 1, "r": 3.0}, {"env_steps": 2}, {"env_steps": 3}]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _x, mean, half, _ = curve_band([a, b], "r")
    assert mean[0] == 2.0 and abs(half[0] - 12.7062) < 1e-4
    assert np.isnan(mean[1]) and half[1] == 0.0
    assert mean[2] == 5.0 and half[2] == 0.0


def test_merged_replicas_sum_each_agents_counts():
    from amuled_ma.evaluate.evaluator import merge_feedback

    def summary(ok: int, miss: int) -> dict:
        row = {"ok": ok, "replay_miss": miss, "total": ok + miss, "failed": miss,
               "failure_rate": miss / (ok + miss)}  # fmt: skip
        return {"statuses": {"ok": ok, "replay_miss": miss}, "agents": {"care": row},
                "agents_per_state": {"care": row}}  # fmt: skip

    merged = merge_feedback([summary(90, 10), summary(70, 30)])
    care = merged["agents"]["care"]
    assert (care["ok"], care["replay_miss"], care["total"]) == (160, 40, 200)
    assert care["failure_rate"] == 0.2 and merged["failure_rate"] == 0.2
    assert merged["miss_rate"] == 0.2


# ---------------------------------------------------------------------------------------
# Size caps: a run folder's files over their cap are refused unread, one line


@pytest.fixture(scope="module")
def tiny_base_run(tmp_path_factory):
    """A tiny FindMilk run (base only), trained through the real CLI."""
    run = tmp_path_factory.mktemp("caps") / "findmilk"
    assert main(["train", "findmilk", "--run-dir", str(run), *TINY]) == 0
    return run


def test_a_feedback_json_over_16_mib_is_refused_before_any_episode(tiny_base_run, tmp_path, capsys):
    from amuled_ma.evaluate.evaluator import MAX_FEEDBACK_BYTES

    assert MAX_FEEDBACK_BYTES == 16 * 2**20
    run = tmp_path / "run"
    shutil.copytree(tiny_base_run, run)
    path = run / "base" / "feedback.json"
    sparse(path, 10 * 2**30)
    capsys.readouterr()
    argv = ["evaluate", str(run), "--episodes", "1", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 1
    line = one_line(capsys.readouterr().err)
    assert line == (
        f"amuled: error: {path}: the diagnostics file is 10,737,418,240 bytes, more than the "
        "16,777,216 a diagnostics file may be (a fine-tune's is about 4 KB); it is not read; "
        "is it the right folder? It is written by 'amuled finetune'; fine-tune the variant "
        "again with --force, or delete the file (the report then has no diagnostics for it)"
    )
    assert not (run / "results.json").exists()  # refused before any episode ran


def test_a_results_json_over_256_mib_is_refused_by_view_with_one_line(
    tiny_base_run, tmp_path, capsys
):
    from amuled_ma.evaluate.results import MAX_RESULTS_BYTES

    assert MAX_RESULTS_BYTES == 256 * 2**20
    run = tmp_path / "run"
    shutil.copytree(tiny_base_run, run)
    sparse(run / "results.json", 10 * 2**30)
    capsys.readouterr()
    out = tmp_path / "v.html"
    assert main(["view", str(run), "--variant", "base", "-o", str(out)]) == 1
    line = one_line(capsys.readouterr().err)
    assert line.startswith(
        f"amuled: error: {run / 'results.json'}: the results file is 10,737,418,240 bytes, "
        "more than the 268,435,456 a results file may be (about 140 bytes an episode of each "
        "variant and mode); it is not read; is it the right folder? Evaluate the run again "
        f"with 'amuled evaluate {run}'"
    )
    assert not out.exists()
