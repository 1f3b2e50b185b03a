"""The jobs of a sweep trained as populations (``amuled run`` / ``ablate``).

A population costs a fixed ~0.26 s of CPU per iteration whatever its size, so a level of the
graph is cut into as few populations as fill the workers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from amuled_ma.errors import AmuledError
from amuled_ma.experiments.plans import PreparedJob, member_spec, prepare_job
from amuled_ma.experiments.run_folder import JobResult, TrainJob
from amuled_ma.learn.population_groups import (
    memory_budget_bytes,
    population_key,
    split_populations,
)


def population_groups(
    jobs: Sequence[TrainJob],
    *,
    workers: int = 1,
    memory_budget: int | None = None,
) -> list[list[TrainJob]]:
    """Group the jobs to train into populations, needs in earlier groups.

    A level of the graph is cut into at least ``workers`` populations when it has the jobs
    (shapes first, a shape cut only when there are fewer shapes than workers), each within its
    share of ``memory_budget`` (default: half this machine's memory). A group of one is a lone job.
    """
    todo = [job for job in jobs if job.action != "skip"]
    depth: dict[str, int] = {}
    for job in todo:  # graph order: a job's needs are numbered before it
        depth[job.name] = 1 + max((depth[n] for n in job.needs if n in depth), default=-1)
    budget = max(1, (memory_budget or memory_budget_bytes()) // max(1, workers))
    groups: list[list[TrainJob]] = []
    for level in sorted(set(depth.values())):
        layer = [job for job in todo if depth[job.name] == level]
        specs = [member_spec(job) for job in layer]
        # a population costs a fixed ~0.26 s per iteration whatever its size: as few as
        # fill the workers (the level's shapes first, each cut only when they are fewer)
        shapes = len({population_key(spec) for spec in specs})
        each = max(1, math.ceil(workers / max(1, shapes)))
        for members in split_populations(specs, budget, min_count=each):
            groups.append([layer[i] for i in members])
    return groups


@dataclass
class GroupOutcome:
    """What `train_population_jobs` did: results of the jobs that finished, a line per failure."""

    results: dict[str, JobResult] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)


def train_population_jobs(
    jobs: Sequence[TrainJob],
    *,
    progress: bool = False,
    hint: str = "",
    on_iteration: Callable[[Any, int], None] | None = None,
    store_for: Callable[[TrainJob], Any] | None = None,
    announce: bool = True,
) -> GroupOutcome:
    """Train a group of jobs as populations, each job ending as a lone job ends.

    Jobs are split by `population_key` (a retried group may hold jobs at other iterations). A
    job that fails alone is marked ``failed``; the others finish. ``announce``: print a line
    when a job fails (a Ray worker leaves it to the driver).

    Raises:
        AmuledError: A job's inputs are missing (before anything trains).
        KeyboardInterrupt: Ctrl-C or SIGTERM, after every member wrote its checkpoint.
    """
    from amuled_ma.learn.population import train_population  # here: it imports torch

    outcome = GroupOutcome()
    prepared: list[PreparedJob] = []
    done: dict[str, JobResult] = {}
    try:
        for job in jobs:
            ready = prepare_job(
                job, hint=hint, store=store_for(job) if store_for is not None else None
            )
            if isinstance(ready, JobResult):
                done[job.name] = ready
            else:
                prepared.append(ready)
        specs = [ready.member(on_iteration) for ready in prepared]
        alone = len(jobs) == 1  # a lone job: its failure is the group's error
        for members in split_populations(specs, memory_budget_bytes()):
            try:
                trained = train_population(
                    [specs[i] for i in members], progress=progress, announce=announce and not alone
                )
                if alone and isinstance(trained[0], BaseException):
                    raise trained[0]
            except Exception:
                for i in members:
                    prepared[i].failed()
                raise
            for i, result in zip(members, trained, strict=True):
                ready = prepared[i]
                if isinstance(result, BaseException):
                    ready.failed()
                    outcome.failures.append(str(result))
                else:
                    done[ready.job.name] = ready.finished(result)
    finally:
        for ready in prepared:
            ready.close()
    outcome.results = {job.name: done[job.name] for job in jobs if job.name in done}
    return outcome


def population_failure(failures: Sequence[str], hint: str) -> AmuledError:
    """The sweep's closing error for jobs that failed alone (each named when it failed)."""
    count = f"{len(failures)} jobs" if len(failures) > 1 else "a job"
    then = f"; after fixing it, continue with: {hint} --resume" if hint else ""
    return AmuledError(
        f"{count} of a population failed alone (named above; their last checkpoints are "
        f"kept) and the other members finished{then}"
    )
