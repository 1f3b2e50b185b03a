"""A sweep whose population loses a member: one line names it, the others finish, it resumes.

The real sweep machinery in this process (``run_jobs``: plan, prepare, populations,
records); the one fault is injected into one job's feedback, which answers NaN from its
third iteration on (a bad input the panel would not give).
"""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.errors import AmuledError
from amuled_ma.experiments import plans
from amuled_ma.experiments.jobs import run_jobs
from amuled_ma.experiments.plans import plan_ablation
from amuled_ma.experiments.run_folder import read_record
from amuled_ma.learn.checkpoints import LAST, checkpoint_infos
from amuled_ma.scenario import load_scenario

STEPS = 8  # feedback calls per iteration: one per step of the rollout
TINY = {
    "base": {"total_steps": 1024, "num_envs": 16, "num_steps_per_env": 16},
    "finetune": {"iterations": 4, "num_envs": 4, "num_steps_per_env": STEPS, "save_interval": 2},
    "output": {"tensorboard": False},
    "feedback": {"source": "rules"},
}


class NanAfterCalls:
    """A feedback that answers NaN after ``calls`` calls (from the next iteration on)."""

    def __init__(self, inner, calls: int) -> None:
        self.inner, self.calls, self.done = inner, calls, 0

    def __call__(self, obs, task):
        self.done += 1
        out = np.asarray(self.inner(obs, task), dtype=np.float64)
        return out if self.done <= self.calls else np.full_like(out, np.nan)

    def __getattr__(self, name: str):
        return getattr(self.inner, name)


def _scenario():
    scenario = load_scenario("findmilk")
    for section, values in TINY.items():
        scenario = scenario.replace(section, **values)
    return scenario


def test_a_sweep_member_that_fails_is_named_once_and_the_others_finish(
    tmp_path, monkeypatch, capsys
) -> None:
    jobs = plan_ablation("aggregation", _scenario(), tmp_path, [1])
    tunes = [j for j in jobs if str(j.variant) != "base"]
    bad = next(j for j in tunes if j.out_dir.name == "finetune-agg-mean")
    real = plans.build_feedback

    def poisoned(plan, store, **kwargs):
        feedback = real(plan, store, **kwargs)
        if kwargs["state_dir"] == bad.out_dir:
            return NanAfterCalls(feedback, calls=2 * STEPS)
        return feedback

    monkeypatch.setattr(plans, "build_feedback", poisoned)
    capsys.readouterr()
    with pytest.raises(AmuledError) as stop:
        run_jobs(jobs, workers=1, hint="amuled ablate findmilk --what aggregation")
    err = capsys.readouterr().err
    named = [line for line in err.splitlines() if str(bad.out_dir) in line]
    assert len(named) == 1, (err, str(stop.value))  # one line names the member, when it failed
    assert "iteration 3/4" in named[0] and "not a finite number" in named[0]
    # the closing error does not repeat it: it says what to do
    assert str(bad.out_dir) not in str(stop.value)
    assert "a job of a population failed alone" in str(stop.value)
    assert str(stop.value).endswith("amuled ablate findmilk --what aggregation --resume")
    # its last checkpoint before the failure is kept; the record says failed
    kept = checkpoint_infos(bad.out_dir / LAST)
    assert kept is not None and kept["iteration"] == 2 and not kept["completed"]
    assert read_record(bad.out_dir).state == "failed"
    others = [j for j in tunes if j is not bad]
    assert len(others) == 7  # the other aggregation rules and bjs-dst
    for job in others:
        state = checkpoint_infos(job.out_dir / LAST)
        assert state is not None and state["iteration"] == 4 and state["completed"], job.name
        assert read_record(job.out_dir).state == "complete", job.name
    # fixed, the sweep resumes the failed member alone from its checkpoint
    written = {job.name: (job.out_dir / LAST).stat().st_mtime_ns for job in others}
    monkeypatch.setattr(plans, "build_feedback", real)
    resumed = plan_ablation("aggregation", _scenario(), tmp_path, [1], resume=True)
    run_jobs(resumed, workers=1)
    state = checkpoint_infos(bad.out_dir / LAST)
    assert state["iteration"] == 4 and state["completed"]
    assert read_record(bad.out_dir).state == "complete"
    for job in others:  # the finished ones are skipped, not trained again
        assert (job.out_dir / LAST).stat().st_mtime_ns == written[job.name], job.name
