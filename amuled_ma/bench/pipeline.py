"""The paper's whole offline pipeline, timed: run + ablate clusters + ablate aggregation.

Each task and ``--jobs`` setting (``--ray`` adds a column) in a fresh run directory, each
stage timed. Target: both tasks in under 15 minutes, Ray's overhead under 10%. ``--recipe
authors --seeds 5`` times the paper's full comparison: target under 30 minutes on 2 cores
(populations; ``--no-population`` adds a column without them).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from amuled_ma.bench._output import output_folder
from amuled_ma.commands._experiment import add_overrides_argument

#: The issue's target for the whole pipeline, both tasks [s].
TARGET_S = 15 * 60
#: The target of the paper's full comparison with ``--recipe authors --seeds 5`` [s].
FULL_TARGET_S = 30 * 60
#: The stages, as ``amuled`` arguments after the scenario.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("run", ("run",)),
    ("ablate clusters", ("ablate", "--what", "clusters")),
    ("ablate aggregation", ("ablate", "--what", "aggregation")),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument(
        "--jobs",
        default="0",
        help="comma-separated --jobs values to time side by side, e.g. 1,0 "
        "(1 = one process, 0 = one worker per core; default: 0)",
    )
    parser.add_argument(
        "--tasks",
        default="findmilk,driving",
        help="comma-separated shipped scenarios (default: findmilk,driving)",
    )
    parser.add_argument(
        "--ray",
        action="store_true",
        help="add a column: every stage with --ray (a local Ray, one CPU per core)",
    )
    parser.add_argument(
        "--recipe",
        choices=("equation", "authors"),
        default=None,
        help="passed to every stage: 'authors' runs the paper's comparison as its authors "
        "ran it (scenarios/<task>-authors.toml; with --seeds 5 the 30-minute target)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        default=1,
        metavar="N",
        help="training seeds of every variant, passed to every stage (default: 1)",
    )
    parser.add_argument(
        "--tasks-at-once",
        action="store_true",
        help="run each task's stages in its own process, the tasks at the same time (e.g. "
        "with --jobs 1: one population per stage per task, one task per core); the total "
        "is then the wall clock of the whole, not the sum of the stages",
    )
    parser.add_argument(
        "--no-population",
        action="store_true",
        help="add a column: every stage with --no-population (every job alone; hours with "
        "--recipe authors --seeds 5)",
    )
    add_overrides_argument(
        parser
    )  # passed to every stage; figures then leave the target's conditions
    parser.add_argument(
        "--out", type=Path, default=None, help="folder for the runs (default: a temp folder)"
    )


def _jobs_values(text: str) -> list[int]:
    from amuled_ma.errors import AmuledError

    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or any(v < 0 for v in values):
        raise AmuledError(f"--jobs {text!r}: expected comma-separated counts >= 0, e.g. 1,0")
    return values


def _subprocess_amuled(args: list[str]) -> tuple[int, float]:
    """Run ``amuled ARGS`` in a process of its own; its exit status and CPU seconds."""
    proc = subprocess.Popen([sys.executable, "-m", "amuled_ma", *args])
    _pid, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_utime + usage.ru_stime


def _in_process_amuled(args: list[str]) -> tuple[int, float | None]:
    """Run ``amuled ARGS`` in this process; its exit status (CPU seconds: not measured)."""
    from amuled_ma.cli import main as amuled

    return amuled(args), None


def time_pipeline(
    tasks: list[str],
    jobs: int | str,
    out: Path,
    overrides: list[str],
    extra: Sequence[str] = (),
    *,
    run: Callable[[list[str]], tuple[int, float | None]] = _in_process_amuled,
    cpu: dict[tuple[str, str], float] | None = None,
) -> dict[tuple[str, str], float]:
    """Run every stage of every task into ``out/<task>``; return seconds per (task, stage).

    ``jobs`` is a ``--jobs`` count, ``"ray"`` or ``"alone"`` (``--no-population``); ``run`` runs
    one ``amuled`` command and gives its CPU seconds when measured, kept in ``cpu``.
    """
    from amuled_ma.errors import AmuledError

    seconds: dict[tuple[str, str], float] = {}
    sets = [a for text in overrides for a in ("--set", text)]
    where = {"ray": ["--ray"], "alone": ["--no-population"]}.get(str(jobs), ["--jobs", str(jobs)])
    for task in tasks:
        for stage, (command, *rest) in STAGES:
            args = [command, task, *rest, "--run-dir", str(out / task), *where, *extra]
            args += ["--no-progress", *sets]
            print(f"[jobs={jobs}] amuled {' '.join(args)}", flush=True)
            t0 = time.perf_counter()
            code, cpu_s = run(args)
            seconds[(task, stage)] = time.perf_counter() - t0
            if cpu is not None and cpu_s is not None:
                cpu[(task, stage)] = cpu_s
            if code != 0:
                raise AmuledError(f"'amuled {' '.join(args)}' exited with status {code}")
    return seconds


def time_tasks_at_once(
    tasks: list[str], jobs: int | str, out: Path, overrides: list[str], extra: Sequence[str]
) -> tuple[dict[tuple[str, str], float], float]:
    """`time_pipeline` of every task at once, each in its own processes; also the total wall."""
    seconds: dict[tuple[str, str], float] = {}
    cpu: dict[tuple[str, str], float] = {}
    t0 = time.perf_counter()
    with ThreadPoolExecutor(len(tasks)) as pool:  # a failed stage's error is raised here
        for part in pool.map(
            lambda task: time_pipeline(
                [task], jobs, out, overrides, extra, run=_subprocess_amuled, cpu=cpu
            ),
            tasks,
        ):
            seconds.update(part)
    wall = time.perf_counter() - t0
    per_task = {task: sum(v for (t, _), v in cpu.items() if t == task) for task in tasks}
    print(f"[jobs={jobs}] CPU seconds of each stage's process (user + system):", flush=True)
    for (task, stage), value in cpu.items():
        print(f"  {task}: {stage}: {value:.0f} CPU s in {seconds[(task, stage)]:.0f} s", flush=True)
    print(
        f"[jobs={jobs}] per task {', '.join(f'{t} {v:.0f}' for t, v in per_task.items())} CPU "
        f"s in {wall:.0f} s of wall clock: with a core of its own for each task (the stages "
        f"are single-threaded), the whole takes about {max(per_task.values()):.0f} s",
        flush=True,
    )
    return seconds, wall


def main(args: argparse.Namespace) -> int:
    """Time the pipeline for every ``--jobs`` value and print the table."""
    from amuled_ma.experiments.jobs import available_cpus

    values: list[int | str] = [
        *(["alone"] if args.no_population else []),
        *_jobs_values(args.jobs),
        *(["ray"] if args.ray else []),
    ]
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    extra = (["--recipe", args.recipe] if args.recipe else []) + ["--seeds", str(args.seeds)]
    timings, walls = {}, {}
    with output_folder(args.out, "amuled-bench-pipeline-") as root:
        for jobs in values:
            if args.tasks_at_once:
                timings[jobs], walls[jobs] = time_tasks_at_once(
                    tasks, jobs, root / f"jobs{jobs}", args.overrides, extra
                )
            else:
                timings[jobs] = time_pipeline(
                    tasks, jobs, root / f"jobs{jobs}", args.overrides, extra
                )
                walls[jobs] = sum(timings[jobs].values())
    cpus = available_cpus()
    named = {
        "ray": "--ray (local Ray)",
        "alone": "--no-population (every job alone, one per core)",
        1: "--jobs 1 (one process)",
    }
    labels = [named.get(j, f"--jobs {j} (Ray, {j or cpus} CPUs)") for j in values]
    full = args.recipe == "authors" and args.seeds >= 5
    target = FULL_TARGET_S if full else TARGET_S
    print()
    print(
        f"Pipeline wall-clock [s], {len(tasks)} task(s), {cpus} CPU core(s), "
        f"recipe {args.recipe or 'of the scenario'}, {args.seeds} seed(s):"
    )
    print("| stage | " + " | ".join(labels) + " |")
    print("|---|" + "---|" * len(values))
    for task in tasks:
        for stage, _ in STAGES:
            cells = [f"{timings[j][(task, stage)]:.1f}" for j in values]
            print(f"| {task}: {stage} | " + " | ".join(cells) + " |")
    totals = [walls[j] for j in values]
    if args.tasks_at_once:
        print("(the tasks ran at the same time, each in its own processes: the total is the "
              "wall clock of the whole)")  # fmt: skip
    print("| **total** | " + " | ".join(f"**{t:.1f}** ({t / 60:.1f} min)" for t in totals) + " |")
    if len(values) > 1:
        print(f"speed-up of {labels[-1]} over {labels[0]}: "
              f"{totals[0] / totals[-1]:.2f}x")  # fmt: skip
    verdict = "met" if totals[-1] < target else "NOT met"
    print(f"target: the whole pipeline in < {target / 60:.0f} min with {labels[-1]}: "
          f"{verdict} ({totals[-1] / 60:.1f} min)")  # fmt: skip
    if args.overrides:
        print("(scenario overrides given: not the target's conditions)")
    return 0
