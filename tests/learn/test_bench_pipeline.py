"""Smoke test of ``amuled bench pipeline`` on tiny budgets (real figures: README, Performance)."""

from __future__ import annotations

import re

from amuled_ma.cli import main

TINY = [
    "base.total_steps=1024", "base.num_envs=16", "base.num_steps_per_env=16",
    "finetune.iterations=2", "finetune.num_envs=4", "finetune.num_steps_per_env=8",
    "output.tensorboard=false", "feedback.source=rules", "evaluation.episodes=2",
]  # fmt: skip


def test_bench_pipeline_times_every_stage_side_by_side(tmp_path, capsys):
    argv = ["bench", "pipeline", "--tasks", "findmilk", "--jobs", "1,2", "--out", str(tmp_path)]
    for text in TINY:
        argv += ["--set", text]
    assert main(argv) == 0
    out = capsys.readouterr().out
    rows = {}
    for stage in ("run", "ablate clusters", "ablate aggregation"):
        match = re.search(rf"\| findmilk: {stage} \| ([\d.]+) \| ([\d.]+) \|", out)
        assert match, stage
        rows[stage] = [float(match[1]), float(match[2])]
    total = re.search(r"\| \*\*total\*\* \| \*\*([\d.]+)\*\* .* \| \*\*([\d.]+)\*\*", out)
    assert total and abs(float(total[1]) - sum(r[0] for r in rows.values())) < 0.2
    assert "speed-up of --jobs 2 over --jobs 1" in out and "not the target's conditions" in out
    for jobs in (1, 2):  # every stage wrote its report
        run = tmp_path / f"jobs{jobs}" / "findmilk"
        assert (run / "report.md").is_file()
        assert (run / "ablate-clusters" / "report.md").is_file()
        assert (run / "ablate-aggregation" / "report.md").is_file()


def test_bench_pipeline_bad_jobs(capsys):
    assert main(["bench", "pipeline", "--jobs", "two"]) == 1
    assert "--jobs 'two'" in capsys.readouterr().err
