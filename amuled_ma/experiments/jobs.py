"""Run a graph of training jobs, in this process or on Ray.

An experiment (``amuled run``, ``amuled ablate``) is a list of :class:`TrainJob`, each
naming the jobs it needs first (a fine-tune needs its base). :func:`run_jobs` checks every
job's folder before anything starts (so a clash with an old checkpoint fails at once),
then trains them:

- one worker and no ``--ray``: one after the other in this process, each with its own
  progress bar (debuggable, no start-up cost);
- otherwise on Ray (:mod:`amuled_ma.experiments.ray_jobs`): a local Ray with one CPU per worker,
  or the cluster at ``--ray ADDRESS``; one progress bar counts the iterations of all jobs.

Every job is single-threaded (``torch.set_num_threads(1)``), so ``workers`` = CPU cores
fills the machine. Fine-tunes of one run share the SQLite belief store, which is safe
across processes of one machine (WAL).

A caller that writes a run folder connects first (:func:`ray_connection`, around the
writing and the training): a SIGTERM while Ray starts then leaves no folder behind.
"""

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
    """Where ``--ray`` sends the jobs.

    Attributes:
        address: A Ray cluster's address; None starts a local Ray for the run.
        resource: A custom resource each job needs one unit of (``--ray-resource``).

    """

    address: str | None = None
    resource: str | None = None


@dataclass
class JobsOutcome:
    """What :func:`run_jobs` did.

    Attributes:
        results: One :class:`~amuled_ma.experiments.run_folder.JobResult` per job, in job order.
        wall_s: Wall-clock seconds of the whole graph.
        workers: Worker processes used (1: this process).

    """

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
    """Jobs at once: ``requested``, or with 0 one per core (1 when live).

    A live Ollama server is itself the bottleneck and uses every core, and a person at the
    terminal answers only in this process, so ``0`` (auto) keeps fine-tunes that ask either
    (for any agent) in this process; replay and rules feedback scale with cores.
    """
    if requested < 0:
        raise AmuledError(f"--jobs must be 0 (auto) or a positive count, got {requested}")
    if requested == 0:
        live = any(j.variant.finetuning and _asks_live(j) for j in jobs)
        requested = 1 if live else available_cpus()
    return max(1, min(requested, len(jobs) or 1))


def _asks_live(job: TrainJob) -> bool:
    """Whether a job's feedback asks an Ollama server or a person (any agent)."""
    feedback = job.scenario.feedback
    kinds: set[str] = {feedback.source}
    kinds |= {spec.source for spec in feedback.agents.values()}
    return bool(kinds & {"ollama", "terminal"})


def check_order(jobs: Sequence[TrainJob]) -> None:
    """Raise :class:`AmuledError` on duplicate names or a need that is not in the graph."""
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
    """Whether :func:`run_jobs` trains ``jobs`` on Ray (else in this process)."""
    return not (ray is None and (workers <= 1 or len(jobs) <= 1))


@contextlib.contextmanager
def ray_connection(
    jobs: Sequence[TrainJob], *, workers: int, ray: RayTarget | None = None
) -> Iterator[None]:
    """Connect to the Ray :func:`run_jobs` will train ``jobs`` on, for the ``with`` block.

    Enter it before the run folder is written: a SIGTERM (or Ctrl-C) while Ray starts or
    connects then ends the command (exit 143, or 130) with nothing written, and the run
    folder's lock removes the folder it made. Without Ray (one worker, no ``--ray``) it
    does nothing. Ray is shut down (or disconnected from a cluster) when the block ends.

    Args:
        jobs: The jobs :func:`run_jobs` will get.
        workers: Its ``workers``.
        ray: Its ``ray``.

    Raises:
        AmuledError: No cluster answers at the address.
        KeyboardInterrupt: SIGTERM (:class:`~amuled_ma.errors.Terminated`) or Ctrl-C
            while connecting; Ray is shut down first.

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
    """Train a graph of jobs.

    Args:
        jobs: The jobs, each after the jobs it needs, planned
            (:func:`~amuled_ma.experiments.plans.plan_jobs`; an unplanned graph is
            planned here).
        workers: Jobs at once; 1 (without ``ray``) trains in this process, more on a
            local Ray with that many CPUs.
        progress: Show progress bars.
        hint: The command that re-runs the graph (its ``--resume`` form is printed on stops).
        describe: Turns each finished :class:`~amuled_ma.experiments.run_folder.JobResult`
            into the line printed about it.
        ray: Train on Ray even with one worker, at this cluster (``--ray [ADDRESS]``).
        population: Train jobs of one shape together as populations
            (:mod:`~amuled_ma.experiments.population_jobs`; ``--no-population``: False).

    Returns:
        The outcome, results in job order.

    Raises:
        AmuledError: A job's folder clashes with an old checkpoint (before anything runs),
            or a job failed (after the running ones finished).
        KeyboardInterrupt: Ctrl-C, after every running job wrote its checkpoint.

    """
    check_order(jobs)
    if any(job.action is None for job in jobs):
        from amuled_ma.experiments.plans import plan_jobs  # here: it imports torch

        jobs = plan_jobs(jobs, hint)
    start = time.perf_counter()
    on_ray = uses_ray(jobs, workers, ray)
    skipped = {j.name: JobResult(j.variant, j.out_dir, skipped=True) for j in jobs
               if j.action == "skip"}  # fmt: skip
    for result in skipped.values():
        print(describe(result), flush=True)
    groups = job_groups(jobs, workers=workers if on_ray else 1, population=population)
    if not on_ray:
        ran = _train_groups(groups, progress=progress, hint=hint, describe=describe)
        results_by_name = {**skipped, **ran}
        return JobsOutcome([results_by_name[j.name] for j in jobs], time.perf_counter() - start, 1)
    target = ray or RayTarget()
    with ray_switches(target.address is None):
        from amuled_ma.experiments.ray_jobs import run_on_ray  # here: importing Ray takes a second

        ran = run_on_ray(
            groups,
            address=target.address,
            workers=workers,
            progress=progress,
            hint=hint,
            describe=describe,
            resource=target.resource,
        )
    results_by_name = {**skipped, **ran}
    return JobsOutcome(
        [results_by_name[j.name] for j in jobs], time.perf_counter() - start, workers
    )


def job_groups(jobs: Sequence[TrainJob], *, workers: int, population: bool) -> list[list[TrainJob]]:
    """The planned jobs to train (not skipped) as groups that train together, needs first.

    With ``population``, :func:`~amuled_ma.experiments.population_jobs.population_groups`
    (jobs of one shape together, a level cut into as few populations as fill the
    workers); else one job a group.
    """
    if not population:
        return [[job] for job in jobs if job.action != "skip"]
    from amuled_ma.experiments.population_jobs import population_groups  # here: torch

    return population_groups(jobs, workers=workers)


def _train_groups(
    groups: Sequence[Sequence[TrainJob]],
    *,
    progress: bool,
    hint: str,
    describe: Callable[[Any], str],
) -> dict[str, JobResult]:
    """Train groups one after the other in this process; results by job name.

    Every group trains as populations (a group of one: a population of one). Jobs that
    failed alone in a population stop the graph once their group has finished.

    Raises:
        AmuledError: A job failed (the others of its group finished first; a lone job's
            own error).

    """
    from amuled_ma.experiments.population_jobs import (  # here: torch
        population_failure,
        train_population_jobs,
    )

    results: dict[str, JobResult] = {}
    for group in groups:
        outcome = train_population_jobs(group, progress=progress, hint=hint)
        for name, result in outcome.results.items():
            results[name] = result
            print(describe(result), flush=True)
        if outcome.failures:
            raise population_failure(outcome.failures, hint)
    return results
