"""Run a graph of training jobs, in this process or in parallel worker processes.

An experiment (``amuled run``, ``amuled ablate``) is a list of :class:`TrainJob`, each
naming the jobs it needs first (a fine-tune needs its base). :func:`run_jobs` checks every
job's folder before anything starts (so a clash with an old checkpoint fails at once),
then trains them:

- ``workers == 1``: one after the other in this process, each with its own progress bar;
- ``workers > 1``: in a pool of ``spawn``-ed worker processes, a job starting as soon as
  the jobs it needs are done; one progress bar counts the iterations of all jobs.

Every job is single-threaded (``torch.set_num_threads(1)``), so ``workers`` = CPU cores
fills the machine. Fine-tunes of one run share the SQLite belief store, which is safe
across processes (WAL).

Ctrl-C (or SIGTERM) in parallel mode: the workers ignore SIGINT and SIGTERM; the parent
sets a stop event that every running job checks after each iteration, so each writes its
checkpoint as it would on a Ctrl-C of its own; the parent then prints the resume command
once and re-raises :class:`KeyboardInterrupt`. If the parent dies without a word
(``kill -9``), each worker notices, lets its running job write its checkpoint the same
way, and exits. A failing job stops new jobs from starting; running ones finish (their work is
kept) and the first error is raised.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any

from amuled_ma.errors import AmuledError
from amuled_ma.learn.config import planned_iterations
from amuled_ma.learn.run_folder import JobResult, TrainJob, prepare_variant, training_config
from amuled_ma.scenario import Scenario


@dataclass
class JobsOutcome:
    """What :func:`run_jobs` did.

    Attributes:
        results: One :class:`~amuled_ma.learn.run_folder.JobResult` per job, in job order.
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
    """Number of worker processes: ``requested``, or with 0 one per core (1 when live).

    A live Ollama server is itself the bottleneck and uses every core, and a person at the
    terminal answers only in this process, so ``0`` (auto) keeps fine-tunes that ask either
    (for any agent) in this process; replay and rules feedback scale with cores.
    """
    if requested < 0:
        raise AmuledError(f"--jobs must be 0 (auto) or a positive count, got {requested}")
    if requested == 0:
        live = any(j.variant.finetuning and _asks_live(j.scenario) for j in jobs)
        requested = 1 if live else available_cpus()
    return max(1, min(requested, len(jobs) or 1))


def _asks_live(scenario: Scenario) -> bool:
    """Whether a scenario's feedback asks an Ollama server or a person (any agent)."""
    kinds = {scenario.feedback.source}
    kinds |= {str(spec.get("source")) for spec in scenario.feedback.agents.values()}
    return bool(kinds & {"ollama", "terminal"})


def total_iterations(job: TrainJob) -> int:
    """Iterations a job runs to (for the progress bar)."""
    return planned_iterations(job.scenario, finetune=job.variant.finetuning)


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


def _train(
    job: TrainJob,
    *,
    progress: bool,
    hint: str,
    on_iteration: Callable[[Any, int], None] | None = None,
) -> JobResult:
    from amuled_ma.learn.experiments import train_variant  # here: it imports torch

    return train_variant(
        job.scenario,
        job.run_dir,
        job.variant,
        resume=job.resume,
        force=job.force,
        progress=progress,
        hint=hint,
        seed=job.seed,
        out_dir=job.out_dir,
        base_variant=job.base_variant,
        base_dir=job.base_dir,
        on_iteration=on_iteration,
    )


# ------------------------------------------------------------------ worker side
_STOP: Any = None
_PROGRESS: Any = None
#: set when the parent process is gone (killed): the running job checkpoints and ends
_ORPHANED = threading.Event()
#: clear while this worker trains a job
_IDLE = threading.Event()


def _init_worker(stop: Any, progress: Any) -> None:
    """Worker initializer: ignore SIGINT and SIGTERM (the parent coordinates stops).

    A watcher thread ends the worker when the parent dies (``kill -9``, a crash): the
    pool's workers would otherwise train on unattended and then wait for work forever.
    """
    global _STOP, _PROGRESS
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _STOP, _PROGRESS = stop, progress
    _IDLE.set()
    threading.Thread(target=_exit_with_parent, name="parent-watch", daemon=True).start()


def _exit_with_parent() -> None:
    """Wait for the parent to end; let the running job write its checkpoint; exit."""
    parent = mp.parent_process()
    if parent is None:
        return
    parent.join()
    _ORPHANED.set()
    _IDLE.wait()  # the running job stops after its current iteration, checkpoint written
    os._exit(1)  # not sys.exit: queue feeder threads would wait for a reader that is gone


def _stop_requested() -> bool:
    """Whether this worker's job must stop: the parent asked (Ctrl-C) or is gone."""
    return _STOP.is_set() or _ORPHANED.is_set()


def _worker_train(job: TrainJob) -> JobResult:
    """Train one job in a worker; report iterations, stop when the parent asks or dies."""
    pending = 0
    last_sent = time.monotonic()

    def on_iteration(_trainer: Any, _iteration: int) -> None:
        nonlocal pending, last_sent
        pending += 1
        now = time.monotonic()
        if now - last_sent > 0.25:
            _PROGRESS.put((job.name, pending))
            pending, last_sent = 0, now
        if _stop_requested():
            raise KeyboardInterrupt

    if _stop_requested():  # queued before the stop: do not start
        raise KeyboardInterrupt
    _IDLE.clear()
    try:
        return _train(job, progress=False, hint="", on_iteration=on_iteration)
    finally:
        if pending and not _ORPHANED.is_set():
            _PROGRESS.put((job.name, pending))
        _IDLE.set()


# ------------------------------------------------------------------ parent side
def _preflight(jobs: Sequence[TrainJob], hint: str) -> dict[str, str]:
    """Decide new/resume/skip for every job before anything runs (errors come first)."""
    from amuled_ma.learn.experiments import check_inputs  # here: it imports torch

    actions, problems = {}, []
    planned = {j.out_dir.name for j in jobs}
    for j in jobs:
        try:
            base_dir = j.base_dir or j.run_dir
            check_inputs(j.scenario, j.variant, base_dir, j.base_variant, planned)
            actions[j.name] = prepare_variant(
                j.out_dir,
                resume=j.resume,
                force=j.force,
                hint=hint,
                training=training_config(j.scenario, j.variant, j.seed),
            )
        except AmuledError as err:
            problems.append(str(err))
    if len(problems) == 1:
        raise AmuledError(problems[0])
    if problems:
        raise AmuledError(
            f"{len(problems)} of {len(jobs)} jobs cannot start, nothing was trained:\n"
            + "\n".join(f"  - {p}" for p in problems)
        )
    return actions


def run_jobs(
    jobs: Sequence[TrainJob],
    *,
    workers: int = 1,
    progress: bool = False,
    hint: str = "",
    describe: Callable[[Any], str] = str,
) -> JobsOutcome:
    """Train a graph of jobs.

    Args:
        jobs: The jobs, each after the jobs it needs.
        workers: Worker processes; 1 trains in this process.
        progress: Show progress bars.
        hint: The command that re-runs the graph (its ``--resume`` form is printed on stops).
        describe: Turns each finished :class:`~amuled_ma.learn.run_folder.JobResult`
            into the line printed about it.

    Returns:
        The outcome, results in job order.

    Raises:
        AmuledError: A job's folder clashes with an old checkpoint (before anything runs),
            or a job failed (after the running ones finished).
        KeyboardInterrupt: Ctrl-C, after every running job wrote its checkpoint.

    """
    check_order(jobs)
    actions = _preflight(jobs, hint)
    start = time.perf_counter()
    if workers <= 1 or len(jobs) <= 1:
        results = []
        for job in jobs:
            result = _train(job, progress=progress, hint=hint)
            print(describe(result), flush=True)
            results.append(result)
        return JobsOutcome(results, time.perf_counter() - start, 1)
    skipped = {j.name: JobResult(j.variant, j.out_dir, skipped=True) for j in jobs
               if actions[j.name] == "skip"}  # fmt: skip
    for result in skipped.values():
        print(describe(result), flush=True)
    todo = [j for j in jobs if j.name not in skipped]
    results_by_name = {
        **skipped,
        **_run_parallel(todo, workers, progress, hint, describe, set(skipped)),
    }
    return JobsOutcome(
        [results_by_name[j.name] for j in jobs], time.perf_counter() - start, workers
    )


def _run_parallel(
    jobs: Sequence[TrainJob],
    workers: int,
    progress: bool,
    hint: str,
    describe: Callable[[Any], str],
    already_done: set[str],
) -> dict[str, Any]:
    from tqdm.auto import tqdm

    ctx = mp.get_context("spawn")
    stop, channel = ctx.Event(), ctx.Queue()
    waiting = list(jobs)
    running: dict[Future, TrainJob] = {}
    done: dict[str, Any] = {}
    failure: BaseException | None = None
    bar = tqdm(
        total=sum(total_iterations(j) for j in jobs),
        desc=f"{len(jobs)} jobs on {workers} workers",
        unit="it",
        disable=not progress,
        dynamic_ncols=True,
    )

    def drain() -> None:
        while True:
            try:
                _name, count = channel.get_nowait()
            except queue.Empty:
                return
            bar.update(count)

    executor = ProcessPoolExecutor(
        max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(stop, channel)
    )
    try:
        while waiting or running:
            if failure is None:
                ready = [j for j in waiting if all(n in done or n in already_done for n in j.needs)]
                for job in ready:
                    waiting.remove(job)
                    running[executor.submit(_worker_train, job)] = job
            elif not running:
                break
            finished, _ = wait(list(running), timeout=0.25, return_when=FIRST_COMPLETED)
            drain()
            for future in finished:
                job = running.pop(future)
                if future.cancelled():
                    continue
                try:
                    result = future.result()
                except BaseException as error:  # re-raised below, after the running jobs
                    if failure is None:
                        failure = error
                        for other in running:
                            other.cancel()  # queued jobs do not start; running ones finish
                    bar.write(f"  ✗ {job.name}: {type(error).__name__}: {error}", file=sys.stderr)
                    continue
                done[job.name] = result
                bar.write(describe(result))
    except KeyboardInterrupt as signal_stop:  # Ctrl-C, or SIGTERM (errors.Terminated)
        stop.set()
        bar.write("stopping: every running job writes its checkpoint ...", file=sys.stderr)
        for future in running:
            future.cancel()
        wait(list(running))  # each running job ends with KeyboardInterrupt after saving
        failure = signal_stop
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
        drain()
        bar.close()
    if isinstance(failure, KeyboardInterrupt):
        if hint:
            print(f"resume with: {hint} --resume", file=sys.stderr)
        raise failure
    if failure is not None:
        if hint:
            print(f"after fixing it, continue with: {hint} --resume", file=sys.stderr)
        raise failure
    return done
