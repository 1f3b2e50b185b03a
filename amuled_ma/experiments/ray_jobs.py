"""Train a job graph on Ray: a local Ray started for the run, or a cluster at an address.

One Ray task per group of jobs; a fine-tune's task takes its base's task as an argument, so
Ray holds it back. A node without the driver's files gets its folders packed in and returns
them packed. A dead worker's task is retried and resumes its checkpoint (`SWEEP_MARK`).
Ctrl-C or SIGTERM cancels every task, each writing its checkpoint. A local Ray listens on
loopback only. Results are bit-identical to ``--jobs 1``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import ipaddress
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
from typing import TYPE_CHECKING, Any

import psutil
import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from amuled_ma.clusters.plugins import allowed_plugins, set_allowed_plugins
from amuled_ma.errors import AmuledError, Terminated, TerminatedWhileStarting
from amuled_ma.experiments.plans import population_failure, train_population_jobs
from amuled_ma.experiments.ray_store import start_store_actors
from amuled_ma.experiments.ray_switches import SINGLE_MACHINE_ENV
from amuled_ma.experiments.run_folder import (
    JobResult,
    TrainJob,
    prepare_variant,
)
from amuled_ma.experiments.third_party_log import ray_to_log
from amuled_ma.files.safe import write_text_atomic
from amuled_ma.learn.checkpoints import LAST, checkpoint_infos

if TYPE_CHECKING:
    from types import FrameType

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


class RayProcesses:
    """The local Ray's processes: what ``ray.init`` starts under this driver, and theirs.

    A thread reads this process's tree every 50 ms while ``ray.init`` runs: the raylet's agents
    are known even when Ray's SIGTERM handler ends the raylet and orphans them.
    """

    def __init__(self) -> None:
        self.seen: dict[int, psutil.Process] = {}
        self._before = {child.pid for child in psutil.Process().children(recursive=True)}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="ray-processes", daemon=True)

    def _watch(self) -> None:
        while not self._stop.wait(0.05):
            self.add(psutil.Process())

    def add(self, parent: psutil.Process) -> None:
        """Add ``parent``'s descendants that are not the driver's own earlier children."""
        with contextlib.suppress(psutil.Error):
            for child in parent.children(recursive=True):
                if child.pid not in self._before:
                    self.seen.setdefault(child.pid, child)

    def __enter__(self) -> RayProcesses:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.add(psutil.Process())

    def end(self, grace: float = 3.0) -> None:
        """SIGKILL those still running ``grace`` s from now (after ``ray.shutdown``)."""
        _gone, alive = psutil.wait_procs(list(self.seen.values()), timeout=grace)
        for process in alive:
            with contextlib.suppress(psutil.Error):
                process.kill()
        psutil.wait_procs(alive, timeout=grace)


#: The processes of the local Ray this driver started (None: no local Ray of its own).
_local_ray: RayProcesses | None = None


def _first_line(error: BaseException) -> str:
    """The first line of an error's message (Ray's carry tracebacks and actor details)."""
    text = str(error).strip()
    line = text.splitlines()[0].strip() if text else type(error).__name__
    return line if len(line) <= 300 else line[:297] + "..."


#: The signals that stop a command (Ctrl-C and SIGTERM).
_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


class _SigtermCount:
    """Count SIGTERMs while a sweep waits on Ray, chained to the handler before.

    Ray turns a handler's exception into a bare ``KeyboardInterrupt``; the count tells a
    SIGTERM (exit 143) from a Ctrl-C (130). An ignored SIGTERM stays ignored.
    """

    def __init__(self) -> None:
        self.count = 0
        self.previous: Any = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.getsignal(signal.SIGTERM)
            if previous not in (signal.SIG_IGN, None):
                self.previous = previous
                signal.signal(signal.SIGTERM, self)

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.count += 1
        if callable(self.previous):
            self.previous(signum, frame)
        raise Terminated(signum)

    def restore(self) -> None:
        """Put the handler before back."""
        if self.previous is not None:
            signal.signal(signal.SIGTERM, self.previous)
            self.previous = None


class SignalsSeen:
    """The signals this process received in a ``with`` block, whatever their handlers did.

    A handler's exception is lost in after-fork hooks, ``__del__`` or weakref callbacks, which
    ``ray.init`` triggers; ``signal.set_wakeup_fd`` records each signal number before any Python
    handler runs. Lost ``SystemExit``/``KeyboardInterrupt`` are not printed. Main thread only.
    """

    def __init__(self) -> None:
        self.numbers: set[int] = set()
        self._pipe: tuple[int, int] | None = None
        self._previous = -1
        self._hook = sys.unraisablehook

    def _unraisable(self, unraisable: Any) -> None:
        if not isinstance(unraisable.exc_value, SystemExit | KeyboardInterrupt):
            self._hook(unraisable)

    def __enter__(self) -> SignalsSeen:
        if threading.current_thread() is threading.main_thread():
            read, write = os.pipe()
            os.set_blocking(read, False)
            os.set_blocking(write, False)
            self._pipe = (read, write)
            self._previous = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
            self._hook = sys.unraisablehook
            sys.unraisablehook = self._unraisable
        return self

    def __exit__(self, *_exc: object) -> None:
        if self._pipe is None:
            return
        signal.set_wakeup_fd(self._previous)
        sys.unraisablehook = self._hook
        read, write = self._pipe
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(read, 512):
                self.numbers.update(chunk)
        os.close(read)
        os.close(write)
        self._pipe = None


def connect(address: str | None, workers: int) -> bool:
    """Start a local Ray with ``workers`` CPUs, or join ``address``; True: ``disconnect`` is ours.

    This process's SIGTERM handler is kept.

    Raises:
        AmuledError: No cluster answers at ``address``, naming it and the fix.
        KeyboardInterrupt: SIGTERM or Ctrl-C while connecting; what Ray started is shut down.
    """
    if ray.is_initialized():
        return False
    if address is not None:
        check_address(address)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    options: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": True}
    # Ray's local processes are started in this process's group, where a terminal's Ctrl-C
    # lands: they inherit SIGINT ignored, so the Ctrl-C reaches this driver alone, which
    # stops the tasks in order (train_group restores Python's handler, for ray.cancel).
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if address is None else None
    previous_term = signal.getsignal(signal.SIGTERM)
    ray_to_log()  # Ray's own notices (token authentication, ...) go to the log
    global _local_ray
    processes = _local_ray = RayProcesses() if address is None else None
    seen = SignalsSeen()
    # Joining a cluster, a signal taken inside ray.init's native code left it waiting for ever:
    # the join runs with SIGTERM and SIGINT blocked (as do the threads it starts, which inherit
    # the mask), and a signal sent meanwhile is taken as the mask is restored. A local start
    # keeps them open: the processes it starts would inherit the mask.
    joining = address is not None and threading.current_thread() is threading.main_thread()
    try:
        try:
            with seen, processes or contextlib.nullcontext():
                held = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS) if joining else None
                try:
                    if address is None:
                        ray.init(num_cpus=workers, include_dashboard=False, **options)
                    else:
                        ray.init(address=address, **options)
                finally:
                    if held is not None:
                        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        finally:  # the SIGTERM handler ray.init replaced (Ray's aborts, no checkpoint)
            if previous_term is not None and threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, previous_term)
            if previous is not None:
                signal.signal(signal.SIGINT, previous)
        stopped = None
    except (ConnectionError, RuntimeError, ValueError, SystemExit, KeyboardInterrupt) as error:
        stopped = error
    # A SIGTERM while ray.init ran stops the command, whatever ray.init did after it: Ray's
    # handlers for that time call sys.exit (a local node's after killing its processes,
    # which may fail ray.init with a ConnectionError), or their exception was lost.
    if signal.SIGTERM in seen.numbers and previous_term not in (signal.SIG_IGN, None):
        stopped = SystemExit(signal.SIGTERM)
    if isinstance(stopped, SystemExit | KeyboardInterrupt):
        disconnect()
        if isinstance(stopped, SystemExit):  # only Ray's SIGTERM handlers call sys.exit here
            raise TerminatedWhileStarting(signal.SIGTERM) from None
        raise stopped
    if stopped is not None:
        where = address or "a local Ray"
        raise AmuledError(
            f"--ray {where}: cannot connect ({_first_line(stopped)}); start the cluster with "
            "'ray start --head' on its head node, or give no address for a local Ray"
        ) from stopped
    if address is None and not ipaddress.ip_address(ray.util.get_node_ip_address()).is_loopback:
        print(
            f"amuled: note: the local Ray listens on {ray.util.get_node_ip_address()} too, "
            f"not on loopback only: Ray was imported before {SINGLE_MACHINE_ENV}=0 was set "
            "(set it before importing Ray)",
            file=sys.stderr,
        )
    return True


def disconnect() -> None:
    """Shut down the Ray this process started, or leave the cluster it joined.

    ``ray.shutdown`` after a start that a signal cut short leaves the raylet's agents
    running (dashboard, runtime env): what is left of `RayProcesses` is ended.
    """
    global _local_ray
    if _local_ray is not None:
        for process in list(_local_ray.seen.values()):
            _local_ray.add(process)  # workers started since, under the raylet
    with contextlib.suppress(Exception):
        ray.shutdown()
    if _local_ray is not None:
        _local_ray.end()
        _local_ray = None


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
    """Write the files of a `pack` archive into ``folder`` (created if needed)."""
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as archive:
        archive.extractall(folder, filter="data")


def _run_mark_is(job: TrainJob, mark: str, text: str) -> bool:
    """Whether the run folder's ``mark`` file reads ``text`` (`SHARED_TOKEN`, `STOP_MARK`)."""
    try:
        return (Path(job.run_dir) / mark).read_text() == text
    except OSError:
        return False


@ray.remote(num_cpus=0)
class SweepBoard:
    """Ray actor shared by a sweep's tasks: their iteration counts, for the driver's bar.

    Tasks never wait on it: a task blocked in ``ray.get`` lends its CPU to another task.
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


#: What `train_group` returns: results by job name, node id, whether the node sees
#: the driver's files, the packed folders, the lines of jobs that failed alone.
GroupReturn = tuple[dict[str, JobResult], str, bool, dict[str, bytes], list[str]]


@ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)
def train_group(
    group: list[TrainJob],
    sweep: str,
    token: str,
    inputs: dict[str, bytes] | None,
    board: Any,
    stores: dict[str, Any],
    driver_node: str,
    *needed: GroupReturn,
    plugins: tuple[str, ...] = (),
) -> GroupReturn:
    """Ray task: train a group of jobs (one alone, more as a population) after ``needed``.

    ``inputs`` are packed folders for a node without the driver's files (None: a local Ray);
    ``stores`` map belief store paths to their actors on the driver's node.
    """
    import torch

    if threading.current_thread() is threading.main_thread():
        # ray.cancel interrupts a task as a SIGINT would: Python's handler must be set
        signal.signal(signal.SIGINT, signal.default_int_handler)
    first = group[0]
    if _run_mark_is(first, STOP_MARK, sweep):  # queued before a Ctrl-C: do not begin
        raise KeyboardInterrupt
    from amuled_ma.experiments.ray_store import RemoteStore

    os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
    torch.set_num_threads(1)
    set_allowed_plugins(plugins)  # the driver's --allow-plugin: a worker allows no more
    shared = _run_mark_is(first, SHARED_TOKEN, token)
    if not shared:
        if inputs is None:
            raise AmuledError(
                f"{first.name}: this Ray node does not see the run folder {first.run_dir}; "
                "run the sweep with files shipped (any --ray ADDRESS does) or share the folder"
            )
        for path, data in inputs.items():
            unpack(data, Path(path))
        for returned in needed:
            for path, data in returned[3].items():
                unpack(data, Path(path))
    node = ray.get_runtime_context().get_node_id()
    away = node != driver_node  # not the driver's machine: its store through the actor

    def store_for(job: TrainJob) -> Any:
        actor = stores.get(str(job.store))
        return RemoteStore(actor) if away and actor is not None else None

    pending, last = 0, time.monotonic()

    def on_iteration(_trainer: Any, _iteration: int) -> None:
        nonlocal pending, last
        pending += 1
        if time.monotonic() - last > REPORT_EVERY_S:
            board.add.remote(pending)
            pending, last = 0, time.monotonic()

    jobs = [_marked(job, sweep, node, announce=inputs is not None) for job in group]
    results, failures = train_population_jobs(
        jobs,
        progress=False,
        hint="",
        on_iteration=on_iteration,
        store_for=store_for,
        announce=False,  # the driver prints each failure once, when the group returns
    )
    # with files shipped, every job returns its folder: a fine-tune on a node without the
    # driver's files needs its base's, wherever the base was trained
    files = (
        {str(job.out_dir): pack(Path(job.out_dir)) for job in jobs} if inputs is not None else {}
    )
    return results, node, shared, files, failures


def _marked(job: TrainJob, sweep: str, node: str, *, announce: bool) -> TrainJob:
    """Mark a job's folder with the sweep; a retry of the same sweep resumes the job."""
    out_dir = Path(job.out_dir)
    mark = out_dir / SWEEP_MARK
    retry = mark.is_file() and mark.read_text() == sweep
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(mark, sweep)
    if retry:
        state = checkpoint_infos(out_dir / LAST) or {}
        print(
            f"{job.name}: run again after its worker or node was lost; resuming from "
            f"iteration {state.get('iteration', 0)} on Ray node {node[:8]}",
            flush=True,
        )
    elif announce:  # on a cluster: say where each job trains
        print(f"{job.name}: starts on Ray node {node[:8]}", flush=True)
    if not retry:
        return job
    # its checkpoint is this sweep's: continue it (the plan said new, or resume from earlier)
    settings = job.settings
    assert settings is not None
    job = dataclasses.replace(job, resume=True, force=False)
    return dataclasses.replace(job, action=prepare_variant(job, settings))


def _ray_failure(name: str, error: BaseException) -> AmuledError:
    """One line for a job that Ray could not run or finish (a lost worker, node or actor)."""
    return AmuledError(
        f"job {name!r} did not finish on Ray: {type(error).__name__}: {_first_line(error)} "
        "(see 'ray status' and the Ray logs of the node); its last checkpoint is kept"
    )


def _absolute(job: TrainJob) -> TrainJob:
    """The job with absolute folders (a worker's working directory is not the driver's)."""
    return dataclasses.replace(
        job,
        run_dir=Path(job.run_dir).resolve(),
        out_dir=Path(job.out_dir).resolve(),
        base_dir=Path(job.base_dir).resolve() if job.base_dir is not None else None,
        base_checkpoint=(
            Path(job.base_checkpoint).resolve() if job.base_checkpoint is not None else None
        ),
        store=Path(job.store).resolve() if job.store is not None else None,
    )


def _inputs(group: Sequence[TrainJob], in_sweep: set[str]) -> dict[str, bytes]:
    """Folders a node without the driver's files needs for a group's jobs, packed."""
    folders: list[Path] = []
    for job in group:
        folders.append(Path(job.out_dir))
        if job.variant.finetuning and not any(n in in_sweep for n in job.needs):
            folders.append(Path(job.base_dir or job.run_dir) / job.base_variant)
    return {str(f): pack(f) for f in dict.fromkeys(folders) if f.is_dir()}


def run_on_ray(
    groups: Sequence[Sequence[TrainJob]],
    *,
    ship: bool,
    progress: bool,
    hint: str,
    describe: Callable[[Any], str],
    resource: str | None = None,
) -> dict[str, JobResult]:
    """Train groups of jobs (each after the groups it needs) as Ray tasks on the connected Ray.

    ``ship``: pack the folders a job needs into its task (a cluster's node may not see them);
    ``resource``: a custom Ray resource each job needs one unit of. Returns results by name.

    Raises:
        AmuledError: A job failed (after the running ones finished).
        KeyboardInterrupt: Ctrl-C, after every running job wrote its checkpoint.
    """
    from tqdm.auto import tqdm

    terms = _SigtermCount()
    sweep, token = uuid.uuid4().hex, uuid.uuid4().hex
    groups = [[_absolute(j) for j in group] for group in groups]
    jobs = [job for group in groups for job in group]
    in_sweep = {j.name for j in jobs}
    run_dirs = {j.run_dir for j in jobs}
    bar = tqdm(
        total=sum(j.shape.total_iterations for j in jobs if j.shape is not None),
        desc=f"{len(jobs)} jobs on Ray"
        + (f" in {len(groups)} tasks" if len(groups) < len(jobs) else ""),
        unit="it",
        disable=not progress,
        dynamic_ncols=True,
    )
    board: Any = None
    stores: dict[str, Any] = {}
    refs: dict[str, Any] = {}
    waiting: list[Any] = []  # the refs not finished yet

    def drain() -> None:
        # the bar only (a lost count is no lost work: the jobs' results are the refs)
        if board is not None:
            with contextlib.suppress(ray.exceptions.RayError):
                bar.update(ray.get(board.take.remote()))

    done: dict[str, JobResult] = {}
    failure: BaseException | None = None
    try:  # from here on a signal stops the jobs submitted so far, each with its checkpoint
        for run_dir in run_dirs:
            run_dir.mkdir(parents=True, exist_ok=True)
            write_text_atomic(run_dir / SHARED_TOKEN, token)
        driver_node = ray.get_runtime_context().get_node_id()
        # on the driver's node: an actor on a node that dies would take the bar with it
        here = NodeAffinitySchedulingStrategy(driver_node, soft=False)
        # mypy types a @ray.remote class as the class, not Ray's ActorClass with .options
        board = SweepBoard.options(scheduling_strategy=here).remote()  # type: ignore[attr-defined]
        stores = start_store_actors(
            j.store for j in jobs if j.variant.asks_panel and j.store is not None
        )
        options: dict[str, Any] = {"resources": {resource: 1}} if resource else {}
        plugins = tuple(sorted(allowed_plugins()))
        task_of: dict[str, str] = {}  # job name -> its task's name
        for group in groups:  # in graph order: each group's needs are submitted before it
            name = group[0].name if len(group) == 1 else f"{group[0].name}+{len(group) - 1}"
            needs = {task_of[n] for job in group for n in job.needs if n in task_of}
            needed = [refs[n] for n in sorted(needs)]
            inputs = _inputs(group, in_sweep) if ship else None
            refs[name] = train_group.options(name=name, **options).remote(
                group, sweep, token, inputs, board, stores, driver_node, *needed, plugins=plugins
            )
            task_of.update((job.name, name) for job in group)
            waiting.append(refs[name])
        names = {ref: name for name, ref in refs.items()}
        while waiting:
            finished, waiting = ray.wait(waiting, num_returns=1, timeout=REPORT_EVERY_S)
            drain()
            for ref in finished:
                name = names[ref]
                try:
                    results, node, shared, files, failures = ray.get(ref)
                except ray.exceptions.RayTaskError as error:
                    cause = error.cause if isinstance(error.cause, BaseException) else error
                    if isinstance(cause, ray.exceptions.RayError):  # Ray's, inside the task
                        cause = _ray_failure(name, cause)
                    if failure is None:
                        failure = cause
                        bar.write(f"  ✗ {name}: {type(cause).__name__}: {cause}", file=sys.stderr)
                    continue
                except ray.exceptions.RayError as error:  # a dependency failed, or retries ran out
                    if failure is None:
                        failure = _ray_failure(name, error)
                    continue
                if not shared:  # trained where the driver's files are not: write them here
                    for path, data in files.items():
                        unpack(data, Path(path))
                for job_name, result in results.items():
                    done[job_name] = result
                    bar.write(describe(result) + (f" [Ray node {node[:8]}]" if ship else ""))
                for line in failures:  # jobs that failed alone; their population finished
                    bar.write(f"  ✗ {line}", file=sys.stderr)
                if failures and failure is None:
                    failure = population_failure(failures, "")
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (errors.Terminated)
        if terms.count and not isinstance(stop, Terminated):
            stop = Terminated(signal.SIGTERM)  # Ray's wait turned it into a KeyboardInterrupt
        bar.write("stopping: every running job writes its checkpoint ...", file=sys.stderr)
        # before any cancel frees a CPU that Ray could give a queued task: the stop mark,
        # then the queued tasks (submitted last) first
        for run_dir in run_dirs:
            write_text_atomic(run_dir / STOP_MARK, sweep)
        for ref in reversed(waiting):
            ray.cancel(ref)
        for ref in waiting:
            with contextlib.suppress(ray.exceptions.RayError, KeyboardInterrupt):
                ray.get(ref)
        failure = stop
    finally:
        drain()
        bar.close()
        for path, actor in stores.items():  # the store actors, with what they served away
            try:
                figures = ray.get(actor.figures.remote())
                ray.get(actor.close.remote())
            except ray.exceptions.RayError as error:  # its node's agent died, say
                print(
                    f"  belief store {path}: its Ray actor was lost "
                    f"({type(error).__name__}); the rows written before are in the file",
                    file=sys.stderr,
                    flush=True,
                )
                continue
            if figures["lookup"]:
                print(
                    f"  belief store {path} served the jobs on other nodes: "
                    f"{figures['keys_looked_up']:,} keys looked up in {figures['lookup']:,} "
                    f"calls, {figures['rows_written']:,} rows written",
                    flush=True,
                )
        terms.restore()
        for run_dir in run_dirs:
            for mark in (SHARED_TOKEN, STOP_MARK):
                (run_dir / mark).unlink(missing_ok=True)
    if failure is not None:
        if hint:
            stopped = isinstance(failure, KeyboardInterrupt)
            then = "resume with" if stopped else "after fixing it, continue with"
            print(f"{then}: {hint} --resume", file=sys.stderr)
        raise failure
    return done
