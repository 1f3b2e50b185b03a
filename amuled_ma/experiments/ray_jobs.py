"""Train a job graph on Ray: a local Ray started for the run, or a cluster at an address.

:func:`run_on_ray` submits one Ray task per job (:func:`train_job`, one CPU each); a
fine-tune's task takes its base's task as an argument, so Ray itself holds it back until the
base is trained (the graph is Ray's own dependencies, nothing scheduled by hand).

- **Where the files go.** With a shared file system (every node sees the driver's run folder,
  always so on one machine) each task writes its job folder in place. A node that does not
  see the folder (found with a token file the driver writes into it) gets the folders its job
  needs (its own partial checkpoint, its base) packed into the task's arguments, trains into
  its own copy, and returns the job folder packed; the driver writes it (:func:`pack`,
  :func:`unpack`).
- **A worker or node that dies** (``kill -9``, a lost machine): Ray runs the task again
  (``max_retries``), on any node with room; the job finds the checkpoint its first attempt
  left (same sweep: the mark file :data:`SWEEP_MARK` in its folder) and resumes from it.
- **Ctrl-C (or SIGTERM) on the driver**: every task is cancelled
  (:func:`ray.cancel`, which raises :class:`KeyboardInterrupt` in a running task); each
  running job writes its checkpoint as on a Ctrl-C of its own; the driver prints the
  ``--resume`` command and re-raises. A local Ray dies with its driver (``kill -9``
  included), so no process outlives it.
- **Progress**: the tasks put their iteration counts on a :class:`ray.util.queue.Queue`;
  one bar on the driver counts them.

Results are bit-identical to ``--jobs 1``: every job is single-threaded and seeded by its
own settings, wherever it runs (``tests/learn/test_jobs.py``).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import signal
import socket
import sys
import tarfile
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from amuled_ma.deliberation.feedback import store_path
from amuled_ma.errors import AmuledError
from amuled_ma.experiments.ray_store import start_store_actors
from amuled_ma.experiments.run_folder import JobResult, TrainJob, checkpoint_state
from amuled_ma.learn.checkpoints import LAST
from amuled_ma.learn.config import planned_iterations

#: In a job folder: the sweep whose attempt started it (a retry of the same sweep resumes).
SWEEP_MARK = ".amuled-sweep"
#: In the run folder: the driver's token (a node that reads it shares the file system).
SHARED_TOKEN = ".amuled-ray-token"
#: In the run folder: the sweep the driver is stopping (a queued task does not begin).
STOP_MARK = ".amuled-ray-stop"
#: Attempts after the first when a worker or node dies (Ray's ``max_retries``).
MAX_RETRIES = 3
#: Seconds between progress reports of a task.
REPORT_EVERY_S = 0.25


def check_address(address: str, timeout_s: float = 5.0) -> None:
    """Fail at once, naming the fix, when no Ray head listens at ``HOST:PORT``.

    ``ray.init`` would otherwise retry for minutes. ``auto`` and ``ray://`` addresses are
    left to Ray.

    Raises:
        AmuledError: The address is malformed or nothing accepts a connection there.

    """
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise AmuledError(
            f"--ray {address!r}: expected HOST:PORT of a Ray head (e.g. 10.0.0.5:6379), "
            "'auto', or nothing for a local Ray"
        )
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as error:
        raise AmuledError(
            f"--ray {address}: no Ray head answers there ({error}); start one on that "
            f"machine with 'ray start --head --port={port}', or give no address for a "
            "local Ray"
        ) from error


def connect(address: str | None, workers: int) -> bool:
    """Connect to Ray: start a local one with ``workers`` CPUs, or join ``address``.

    Args:
        address: A cluster's address (``HOST:PORT``, ``ray://...``, or ``auto``); None
            starts a local Ray for this run.
        workers: CPUs of the local Ray (one job per CPU); ignored with an address.

    Returns:
        True when this call connected (and :func:`ray.shutdown` is ours to call).

    Raises:
        AmuledError: No cluster answers at ``address``, naming it and the fix.

    """
    if ray.is_initialized():
        return False
    if address is not None:
        check_address(address)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    options: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": True}
    # Ray's local processes are started in this process's group, where a terminal's Ctrl-C
    # lands: they inherit SIGINT ignored, so the Ctrl-C reaches this driver alone, which
    # stops the tasks in order (train_job restores Python's handler, for ray.cancel).
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if address is None else None
    try:
        if address is None:
            ray.init(num_cpus=workers, include_dashboard=False, **options)
        else:
            ray.init(address=address, **options)
    except (ConnectionError, RuntimeError, ValueError) as error:
        where = address or "a local Ray"
        raise AmuledError(
            f"--ray {where}: cannot connect ({error}); start the cluster with 'ray start "
            "--head' on its head node, or give no address for a local Ray"
        ) from error
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    return True


def pack(folder: Path) -> bytes:
    """Return ``folder``'s files as an uncompressed tar archive (paths relative to it)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as archive:
        if folder.is_dir():
            for path in sorted(folder.rglob("*")):
                if path.is_file() and path.name != ".amuled.lock":
                    archive.add(path, arcname=str(path.relative_to(folder)), recursive=False)
    return buffer.getvalue()


def unpack(data: bytes, folder: Path) -> None:
    """Write the files of a :func:`pack` archive into ``folder`` (created if needed)."""
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as archive:
        archive.extractall(folder, filter="data")


def _sees_driver_files(job: TrainJob, token: str) -> bool:
    mark = Path(job.run_dir) / SHARED_TOKEN
    try:
        return mark.read_text() == token
    except OSError:
        return False


@ray.remote(num_cpus=0)
class SweepBoard:
    """Ray actor shared by a sweep's tasks: their iteration counts, for the driver's bar.

    Tasks only send to it (never wait on it: a task blocked in ``ray.get`` lends its CPU
    to another task, and the machine would run more jobs than it has cores).
    """

    def __init__(self) -> None:
        self.counts: list[int] = []

    def add(self, iterations: int) -> None:
        """Count iterations a task has run since its last report."""
        self.counts.append(iterations)

    def take(self) -> int:
        """Return and reset the iterations reported since the last call."""
        total, self.counts = sum(self.counts), []
        return total


def _stopping(job: TrainJob, sweep: str) -> bool:
    """Whether the driver is stopping this sweep (its mark in the run folder)."""
    try:
        return (Path(job.run_dir) / STOP_MARK).read_text() == sweep
    except OSError:
        return False


def _report(board: Any) -> Callable[[Any, int], None]:
    pending, last = 0, time.monotonic()

    def on_iteration(_trainer: Any, _iteration: int) -> None:
        nonlocal pending, last
        pending += 1
        if time.monotonic() - last > REPORT_EVERY_S:
            board.add.remote(pending)
            pending, last = 0, time.monotonic()

    return on_iteration


@ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)
def train_job(
    job: TrainJob,
    sweep: str,
    token: str,
    inputs: dict[str, bytes] | None,
    board: Any,
    stores: dict[str, Any],
    driver_node: str,
    *needed: tuple[JobResult, str, bool, dict[str, bytes]],
) -> tuple[JobResult, str, bool, dict[str, bytes]]:
    """Ray task: train one job (``needed``: the results of the jobs it needs, done).

    Args:
        job: The job (absolute paths).
        sweep: This sweep's id: a job folder marked with it was started by an earlier
            attempt of this task, whose checkpoint the job resumes.
        token: The driver's token in the run folder (read back: shared file system).
        inputs: Folders (path -> :func:`pack` archive) a node without the driver's files
            needs: the job's own partial folder, a base trained before this sweep; None
            when files are not shipped (a local Ray: one machine).
        board: The sweep's :class:`SweepBoard` (iteration counts).
        stores: Belief store path -> its :class:`~amuled_ma.experiments.ray_store.BeliefStoreActor`
            on the driver's node; a job on another node opens these instead of the files.
        driver_node: The driver's node id.
        *needed: ``(result, node, shared, files)`` of each job this one needs.

    Returns:
        The job's result, the id of the node that trained it, whether that node sees the
        driver's files, and its folder packed when files are shipped (else empty).

    """
    import torch

    from amuled_ma.experiments.plans import train_variant  # here: it imports torch

    if threading.current_thread() is threading.main_thread():
        # ray.cancel interrupts a task as a SIGINT would: Python's handler must be set
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if _stopping(job, sweep):  # queued before a Ctrl-C: do not begin
        raise KeyboardInterrupt
    from amuled_ma.beliefs.store_service import serve_store_from
    from amuled_ma.experiments.ray_store import RemoteStore

    os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
    torch.set_num_threads(1)
    shared = _sees_driver_files(job, token)
    if not shared:
        if inputs is None:
            raise AmuledError(
                f"{job.name}: this Ray node does not see the run folder {job.run_dir}; run "
                "the sweep with files shipped (any --ray ADDRESS does) or share the folder"
            )
        for path, data in inputs.items():
            unpack(data, Path(path))
        for _result, _node, _shared, files in needed:
            for path, data in files.items():
                unpack(data, Path(path))
    out_dir = Path(job.out_dir)
    mark = out_dir / SWEEP_MARK
    retry = mark.is_file() and mark.read_text() == sweep
    out_dir.mkdir(parents=True, exist_ok=True)
    mark.write_text(sweep)
    node = ray.get_runtime_context().get_node_id()
    if retry:
        state = checkpoint_state(out_dir / LAST) or {}
        print(
            f"{job.name}: run again after its worker or node was lost; resuming from "
            f"iteration {state.get('iteration', 0)} on Ray node {node[:8]}",
            flush=True,
        )
    elif inputs is not None:  # on a cluster: say where each job trains
        print(f"{job.name}: starts on Ray node {node[:8]}", flush=True)
    away = node != driver_node  # not the driver's machine: its store through the actor
    for path, actor in stores.items():
        serve_store_from(path, RemoteStore(actor) if away else None)
    try:
        result = train_variant(
            job.scenario,
            job.run_dir,
            job.variant,
            resume=job.resume or retry,
            force=job.force and not retry,
            progress=False,
            hint="",
            seed=job.seed,
            out_dir=job.out_dir,
            base_variant=job.base_variant,
            base_dir=job.base_dir,
            on_iteration=_report(board),
        )
    finally:
        for path in stores:
            serve_store_from(path, None)
    # with files shipped, every job returns its folder: a fine-tune on a node without the
    # driver's files needs its base's, wherever the base was trained
    return result, node, shared, ({str(out_dir): pack(out_dir)} if inputs is not None else {})


def _absolute(job: TrainJob) -> TrainJob:
    """The job with absolute folders (a worker's working directory is not the driver's)."""
    import dataclasses

    return dataclasses.replace(
        job,
        run_dir=Path(job.run_dir).resolve(),
        out_dir=Path(job.out_dir).resolve(),
        base_dir=Path(job.base_dir).resolve() if job.base_dir is not None else None,
    )


def _inputs(job: TrainJob, in_sweep: set[str]) -> dict[str, bytes]:
    """Folders a node without the driver's files needs for ``job``, packed.

    Its own folder (a partial checkpoint to resume), and for a fine-tune whose base is not
    trained in this sweep, the base's folder (a base trained in the sweep reaches the
    fine-tune with the base task's result).
    """
    folders = [Path(job.out_dir)]
    if job.variant.finetuning and not any(n in in_sweep for n in job.needs):
        folders.append(Path(job.base_dir or job.run_dir) / job.base_variant)
    return {str(f): pack(f) for f in folders if f.is_dir()}


def run_on_ray(
    jobs: Sequence[TrainJob],
    *,
    address: str | None,
    workers: int,
    progress: bool,
    hint: str,
    describe: Callable[[Any], str],
    resource: str | None = None,
    ship_files: bool | None = None,
) -> dict[str, JobResult]:
    """Train ``jobs`` (each after the jobs it needs) as Ray tasks; return results by name.

    Args:
        jobs: The jobs to train (skipped ones left out).
        address: The Ray cluster, or None for a local Ray with ``workers`` CPUs.
        workers: CPUs of a local Ray.
        progress: Show one progress bar of all jobs' iterations.
        hint: The command that re-runs the graph (printed with ``--resume`` on a stop).
        describe: Turns each finished result into the line printed about it.
        resource: A custom Ray resource each job needs one unit of (nodes started with
            ``--resources '{"NAME": k}'`` take k jobs at once; others take none).
        ship_files: Pack the folders a job needs into its task, for nodes without the
            driver's file system (default: only with an ``address``).

    Raises:
        AmuledError: A job failed (after the running ones finished), or Ray is unreachable.
        KeyboardInterrupt: Ctrl-C, after every running job wrote its checkpoint.

    """
    from tqdm.auto import tqdm

    ours = connect(address, workers)
    ship = address is not None if ship_files is None else ship_files
    sweep, token = uuid.uuid4().hex, uuid.uuid4().hex
    jobs = [_absolute(j) for j in jobs]
    by_name = {j.name: j for j in jobs}
    for run_dir in {j.run_dir for j in jobs}:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / SHARED_TOKEN).write_text(token)
    driver_node = ray.get_runtime_context().get_node_id()
    # on the driver's node: an actor on a node that dies would take the bar with it
    here = NodeAffinitySchedulingStrategy(driver_node, soft=False)
    board = SweepBoard.options(scheduling_strategy=here).remote()
    stores = start_store_actors(
        store_path(j.scenario, j.run_dir) for j in jobs if j.variant.asks_panel
    )
    options: dict[str, Any] = {"resources": {resource: 1}} if resource else {}
    refs: dict[str, Any] = {}
    for job in jobs:  # in graph order: each job's needs are submitted before it
        needed = [refs[n] for n in job.needs if n in refs]
        inputs = _inputs(job, set(by_name)) if ship else None
        refs[job.name] = train_job.options(name=job.name, **options).remote(
            job, sweep, token, inputs, board, stores, driver_node, *needed
        )
    names = {ref: name for name, ref in refs.items()}
    bar = tqdm(
        total=sum(planned_iterations(j.scenario, finetune=j.variant.finetuning) for j in jobs),
        desc=f"{len(jobs)} jobs on Ray",
        unit="it",
        disable=not progress,
        dynamic_ncols=True,
    )

    def drain() -> None:
        # the bar only (a lost count is no lost work: the jobs' results are the refs)
        with contextlib.suppress(ray.exceptions.RayError):
            bar.update(ray.get(board.take.remote()))

    done: dict[str, JobResult] = {}
    failure: BaseException | None = None
    waiting = list(refs.values())
    try:
        while waiting:
            finished, waiting = ray.wait(waiting, num_returns=1, timeout=REPORT_EVERY_S)
            drain()
            for ref in finished:
                name = names[ref]
                try:
                    result, node, shared, files = ray.get(ref)
                except ray.exceptions.RayTaskError as error:
                    cause = error.cause if isinstance(error.cause, BaseException) else error
                    if failure is None:
                        failure = cause
                        bar.write(f"  ✗ {name}: {type(cause).__name__}: {cause}", file=sys.stderr)
                    continue
                except ray.exceptions.RayError as error:  # a dependency failed, or retries ran out
                    if failure is None:
                        failure = AmuledError(f"job {name!r} did not run: {error}")
                    continue
                if not shared:  # trained where the driver's files are not: write them here
                    for path, data in files.items():
                        unpack(data, Path(path))
                done[name] = result
                bar.write(describe(result) + (f" [Ray node {node[:8]}]" if ship else ""))
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (errors.Terminated)
        bar.write("stopping: every running job writes its checkpoint ...", file=sys.stderr)
        # before any cancel frees a CPU that Ray could give a queued task: the stop mark,
        # then the queued tasks (submitted last) first
        for run_dir in {j.run_dir for j in jobs}:
            (run_dir / STOP_MARK).write_text(sweep)
        for ref in reversed(waiting):
            ray.cancel(ref)
        for ref in waiting:
            with contextlib.suppress(ray.exceptions.RayError, KeyboardInterrupt):
                ray.get(ref)
        failure = stop
    finally:
        drain()
        bar.close()
        for path, actor in stores.items():
            figures = ray.get(actor.figures.remote())
            if figures["lookup"]:
                print(
                    f"  belief store {path} served the jobs on other nodes: "
                    f"{figures['keys_looked_up']:,} keys looked up in {figures['lookup']:,} "
                    f"calls, {figures['rows_written']:,} rows written",
                    flush=True,
                )
            ray.get(actor.close.remote())
        if ours:
            ray.shutdown()
        for run_dir in {j.run_dir for j in jobs}:
            for mark in (SHARED_TOKEN, STOP_MARK):
                (run_dir / mark).unlink(missing_ok=True)
    if isinstance(failure, KeyboardInterrupt):
        if hint:
            print(f"resume with: {hint} --resume", file=sys.stderr)
        raise failure
    if failure is not None:
        if hint:
            print(f"after fixing it, continue with: {hint} --resume", file=sys.stderr)
        raise failure
    return done
