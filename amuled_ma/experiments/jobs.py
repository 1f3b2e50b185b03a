"""Run a graph of training jobs, in this process (one worker, no ``--ray``) or on Ray."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from amuled_ma.errors import AmuledError
from amuled_ma.experiments.ray_switches import ray_switches
from amuled_ma.experiments.run_folder import JobResult, TrainJob


@dataclass(frozen=True)
class RayTarget:
    """Where ``--ray`` sends the jobs (``address`` None: a local Ray) and ``--ray-resource``."""

    address: str | None = None
    resource: str | None = None


@dataclass
class JobsOutcome:
    """What `run_jobs` did: results in job order, wall seconds, workers used (1: this process)."""

    results: list[JobResult] = field(default_factory=list)
    wall_s: float = 0.0
    workers: int = 1


def available_cpus() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def resolve_workers(requested: int, jobs: Sequence[TrainJob]) -> int:
    """Jobs at once: ``requested``, or with 0 one per core (1 when a job asks Ollama or a person).

    A live Ollama server is itself the bottleneck; a person answers only in this process.
    """
    if requested < 0:
        raise AmuledError(f"--jobs must be 0 (auto) or a positive count, got {requested}")
    if requested == 0:
        feedbacks = [j.scenario.feedback for j in jobs if j.variant.finetuning]
        kinds = {f.source for f in feedbacks} | {
            spec.source for f in feedbacks for spec in f.agents.values()
        }
        requested = 1 if kinds & {"ollama", "terminal"} else available_cpus()
    return max(1, min(requested, len(jobs) or 1))


def check_order(jobs: Sequence[TrainJob]) -> None:
    """Raise `AmuledError` on duplicate names or a need that is not in the graph."""
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise AmuledError(f"duplicate job names in {names}")
    known: set[str] = set()
    for job in jobs:
        missing = [n for n in job.needs if n not in known]
        if missing:
            raise AmuledError(f"job {job.name!r} needs {missing}, which do not come before it")
        known.add(job.name)


# ------------------------------------------------------------------ parent side
def uses_ray(jobs: Sequence[TrainJob], workers: int, ray: RayTarget | None) -> bool:
    """Whether `run_jobs` trains ``jobs`` on Ray (else in this process)."""
    return not (ray is None and (workers <= 1 or len(jobs) <= 1))


@contextlib.contextmanager
def ray_connection(
    jobs: Sequence[TrainJob], *, workers: int, ray: RayTarget | None = None
) -> Iterator[None]:
    """Connect to the Ray `run_jobs` will use, for the ``with`` block (nothing without Ray).

    Entered before the run folder is written, a SIGTERM while Ray starts leaves nothing.

    Raises:
        AmuledError: No cluster answers at the address.
        KeyboardInterrupt: SIGTERM (`Terminated`) or Ctrl-C while connecting; Ray is shut down.
    """
    if not uses_ray(jobs, workers, ray):
        yield
        return
    target = ray or RayTarget()
    with ray_switches(target.address is None):
        from amuled_ma.experiments.ray_jobs import connect, disconnect

        ours = connect(target.address, workers)
    try:
        yield
    finally:
        if ours:
            disconnect()


def run_jobs(
    jobs: Sequence[TrainJob],
    *,
    workers: int = 1,
    progress: bool = False,
    hint: str = "",
    describe: Callable[[Any], str] = str,
    ray: RayTarget | None = None,
    population: bool = True,
) -> JobsOutcome:
    """Train a graph of planned jobs (an unplanned graph is planned here).

    ``workers`` 1 without ``ray`` trains in this process; ``population`` trains jobs of one
    shape together.

    Raises:
        AmuledError: A job's folder clashes (before anything runs), or a job failed (after the
            running ones finished).
        KeyboardInterrupt: Ctrl-C, after every running job wrote its checkpoint.
    """
    check_order(jobs)
    if any(job.action is None for job in jobs):
        from amuled_ma.experiments.plans import plan_jobs  # here: a slow import

        jobs = plan_jobs(jobs, hint)
    start = time.perf_counter()
    on_ray = uses_ray(jobs, workers, ray)
    skipped = {j.name: JobResult(j.variant, j.out_dir, skipped=True) for j in jobs
               if j.action == "skip"}  # fmt: skip
    for result in skipped.values():
        print(describe(result), flush=True)
    groups = job_groups(jobs, workers=workers if on_ray else 1, population=population)
    if on_ray:
        target = ray or RayTarget()
        with ray_connection(jobs, workers=workers, ray=target):
            from amuled_ma.experiments.ray_jobs import run_on_ray  # imported by ray_connection

            ran = run_on_ray(
                groups,
                ship=target.address is not None,
                progress=progress,
                hint=hint,
                describe=describe,
                resource=target.resource,
            )
    else:  # each group in turn, here
        from amuled_ma.experiments.plans import population_failure, train_population_jobs

        ran = {}
        for group in groups:
            results, failures = train_population_jobs(group, progress=progress, hint=hint)
            for name, result in results.items():
                ran[name] = result
                print(describe(result), flush=True)
            if failures:  # the others of its group finished first
                raise population_failure(failures, hint)
    by_name = {**skipped, **ran}
    wall = time.perf_counter() - start
    return JobsOutcome([by_name[j.name] for j in jobs], wall, workers if on_ray else 1)


def job_groups(jobs: Sequence[TrainJob], *, workers: int, population: bool) -> list[list[TrainJob]]:
    """The planned jobs to train (not skipped) as groups that train together, needs first."""
    if not population:
        return [[job] for job in jobs if job.action != "skip"]
    from amuled_ma.experiments.plans import population_groups

    return population_groups(jobs, workers=workers)
