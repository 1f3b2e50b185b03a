"""Smoke test of ``amuled bench pipeline`` on tiny budgets (real figures: README, Performance)."""

from __future__ import annotations

import re

import pytest

from amuled_ma.cli import main

TINY = [
    "base.total_steps=1024", "base.num_envs=16", "base.num_steps_per_env=16",
    "finetune.iterations=2", "finetune.num_envs=4", "finetune.num_steps_per_env=8",
    "output.tensorboard=false", "feedback.source=rules", "evaluation.episodes=2",
]  # fmt: skip


@pytest.mark.slow
def test_bench_pipeline_times_every_stage_side_by_side(tmp_path, capsys):
    argv = ["bench", "pipeline", "--tasks", "findmilk", "--jobs", "1,2", "--out", str(tmp_path)]
    argv.append("--ray")
    for text in TINY:
        argv += ["--set", text]
    assert main(argv) == 0
    out = capsys.readouterr().out
    rows = {}
    for stage in ("run", "ablate clusters", "ablate aggregation"):
        match = re.search(rf"\| findmilk: {stage} \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \|", out)
        assert match, stage
        rows[stage] = [float(match[1]), float(match[2]), float(match[3])]
    total = re.search(r"\| \*\*total\*\* \| \*\*([\d.]+)\*\* .* \| \*\*([\d.]+)\*\*", out)
    assert total and abs(float(total[1]) - sum(r[0] for r in rows.values())) < 0.2
    header = "| stage | --jobs 1 (one process) | --jobs 2 (Ray, 2 CPUs) | --ray (local Ray) |"
    assert header in out, out
    assert "speed-up of --ray (local Ray) over --jobs 1 (one process)" in out
    assert "not the target's conditions" in out
    for jobs in (1, 2, "ray"):  # every stage wrote its report
        run = tmp_path / f"jobs{jobs}" / "findmilk"
        assert (run / "report.md").is_file()
        assert (run / "ablate-clusters" / "report.md").is_file()
        assert (run / "ablate-aggregation" / "report.md").is_file()


def test_bench_pipeline_bad_jobs(capsys):
    assert main(["bench", "pipeline", "--jobs", "two"]) == 1
    assert "--jobs 'two'" in capsys.readouterr().err


def test_bench_authors_times_a_short_authors_recipe_fine_tune(capsys):
    from argparse import Namespace

    from amuled_ma.bench import authors

    args = Namespace(tasks="findmilk", iterations=3, base_steps=2048, out=None)
    assert authors.main(args) == 0
    out = capsys.readouterr().out.splitlines()  # each trained job's line, then the table
    at = next(i for i, line in enumerate(out) if line.startswith("task "))
    assert out[at].split() == ["task", "iterations", "ours", "[s]", "authors", "[s]", "speed-up"]
    cells = out[at + 1].split()
    assert cells[0] == "findmilk" and cells[1] == "3" and float(cells[3]) == 1.0  # 360 s x 3/1000


@pytest.mark.slow
def test_bench_pipeline_runs_the_tasks_at_once_and_counts_their_cpu(tmp_path, capsys):
    """``--tasks-at-once``: each task's stages in processes of its own, side by side."""
    argv = ["bench", "pipeline", "--tasks", "findmilk,driving", "--jobs", "1", "--tasks-at-once"]
    argv += ["--seeds", "2", "--out", str(tmp_path)]
    for text in TINY:
        argv += ["--set", text]
    assert main(argv) == 0
    out = capsys.readouterr().out
    stages = {}
    for task in ("findmilk", "driving"):
        for stage in ("run", "ablate clusters", "ablate aggregation"):
            match = re.search(rf"\| {task}: {stage} \| ([\d.]+) \|", out)
            assert match, (task, stage)
            stages[(task, stage)] = float(match[1])
            cpu = re.search(rf"  {task}: {stage}: (\d+) CPU s in (\d+) s", out)
            assert cpu, (task, stage)  # a single-threaded stage: CPU up to its wall clock
            assert int(cpu[1]) <= int(cpu[2]) + 1, cpu[0]
        assert (tmp_path / "jobs1" / task / "ablate-aggregation" / "report.md").is_file()
        seeds = {p.name for p in (tmp_path / "jobs1" / task).glob("finetune-amuled*")}
        assert seeds == {"finetune-amuled", "finetune-amuled.seed2"}, seeds
    total = float(re.search(r"\| \*\*total\*\* \| \*\*([\d.]+)\*\*", out)[1])
    per_task = [
        sum(v for (t, _), v in stages.items() if t == task) for task in ("findmilk", "driving")
    ]
    # the wall clock of the whole: at least the slower task, less than both one after the other
    assert max(per_task) - 1 <= total < sum(per_task), (total, per_task)
    assert "the tasks ran at the same time" in out


def test_a_task_whose_stage_cannot_start_stops_the_bench_with_its_error(tmp_path, monkeypatch):
    """With --tasks-at-once, a stage that fails to start (not an amuled error) is raised."""
    import pytest

    from amuled_ma.bench import pipeline

    def cannot_start(args):
        raise PermissionError(13, "Permission denied", "python")

    monkeypatch.setattr(pipeline, "_subprocess_amuled", cannot_start)
    with pytest.raises(PermissionError, match="Permission denied"):
        pipeline.time_tasks_at_once(["findmilk", "driving"], 1, tmp_path, [], ["--seeds", "1"])
