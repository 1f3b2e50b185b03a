"""Fine-tunes per hour: populations of P = 1, 8, 32, 128 beside the same jobs one by one.

With the authors' recipe, fine-tunes of a short base (seeds 42, 43, ...; lambda_KL cycling
0.5, 1, 2.5, 5) are timed alone and as populations for ``--warmup`` + ``--iterations`` and
extrapolated to 1,000 iterations: setup + warm-up + (1,000 - warm-up) x steady mean;
fine-tunes per hour = P x 3,600 s / that. CPU seconds, one torch thread. Target: at P = 32,
at least 10x the one-by-one throughput on 2 cores. ``--welch N`` compares N seeds alone and
as one population instead (Welch's t per metric).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path
from statistics import mean, stdev
from typing import TYPE_CHECKING, Any

from amuled_ma.bench._output import authors_scenario, output_folder

if TYPE_CHECKING:
    from amuled_ma.beliefs.store.service import StoreService
    from amuled_ma.learn.population import TrainOutcome
    from amuled_ma.learn.population_groups import MemberSpec
    from amuled_ma.scenario import EvaluationConfig, PPOConfig, Scenario, TaskConfig

#: The authors' recipe's fine-tune length, to which the measured iterations extrapolate.
RECIPE_ITERATIONS = 1000
#: lambda_KL of the members, in turn (members differ in seed and KL weight).
LAMBDAS = (0.5, 1.0, 2.5, 5.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument("--tasks", default="findmilk,driving", help="comma-separated tasks")
    parser.add_argument("--sizes", default="1,8,32,128", help="population sizes P")
    parser.add_argument(
        "--warmup", type=int, default=20, help="iterations timed as warm-up (cold memos)"
    )
    parser.add_argument(
        "--iterations", type=int, default=10, help="iterations measured after the warm-up"
    )
    parser.add_argument(
        "--lone", type=int, default=1, help="fine-tunes timed one by one before each population"
    )
    parser.add_argument(
        "--base-steps", type=int, default=10_240, help="env steps of the short base policy"
    )
    parser.add_argument("--device", default="cpu", help="device of the populations (cpu, cuda)")
    parser.add_argument(
        "--welch",
        type=int,
        default=0,
        metavar="N",
        help="instead: N seeds trained alone and N as one population, full runs, their "
        "metrics compared with Welch's t (docs/learning.md)",
    )
    parser.add_argument(
        "--welch-iterations", type=int, default=None, help="iterations of --welch runs (1,000)"
    )
    parser.add_argument("--out", type=Path, default=None, help="keep the runs in this folder")


def _rss_mib() -> float:
    """This process's resident memory now [MiB] (Linux; 0 elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _clocks() -> tuple[float, float]:
    """``(wall, cpu)`` seconds now."""
    return time.perf_counter(), time.process_time()


def _timed(jobs: list[MemberSpec], args: argparse.Namespace, device: str) -> dict[str, Any]:
    """Train ``jobs`` as one population for ``--warmup`` + ``--iterations``; its timing.

    Returns ``wall_s``/``cpu_s`` of a `RECIPE_ITERATIONS` run (setup + warm-up + the rest at
    the steady mean), ``wall_it``/``cpu_it`` per steady iteration, ``setup`` and ``rss_mib``.
    """
    from amuled_ma.learn.population import PopulationTrainer

    marks: list[tuple[float, float]] = []
    for job in jobs:
        job.iterations = args.warmup + args.iterations
    jobs[0].on_iteration = lambda _trainer, _iteration: marks.append(_clocks())
    begin = _clocks()
    population = PopulationTrainer(jobs, device=device)
    start = _clocks()
    setup = (start[0] - begin[0], start[1] - begin[1])
    population.train()
    out: dict[str, Any] = {"setup": setup, "rss_mib": _rss_mib()}
    for job in jobs:
        job.feedback.close()
    for clock, name in enumerate(("wall", "cpu")):
        first = marks[args.warmup - 1][clock] if args.warmup else start[clock]
        steady = (marks[-1][clock] - first) / (len(marks) - args.warmup)
        warm = first - start[clock]
        out[f"{name}_s"] = setup[clock] + warm + (RECIPE_ITERATIONS - args.warmup) * steady
        out[f"{name}_it"] = steady
    return out


def _scenario(task: str, base_steps: int) -> tuple[Scenario, str]:
    """The task's authors' scenario for the bench, and the name of its feedback source."""
    scenario = authors_scenario(task, base_steps)
    recording = scenario.recording_path()
    if recording.exists():
        return scenario, f"replay of {recording.name}"
    return scenario.replace("feedback", source="rules"), "rules (no recording found)"


def _jobs(
    scenario: Scenario, run: Path, base: Path, count: int, tag: str, store: StoreService
) -> list[MemberSpec]:
    """``count`` fine-tune jobs of ``base`` in ``run/tag``: seeds 42.., lambda_KL in turn.

    Each job's feedback is built on ``store`` (shared), cached in ``run``.
    """
    from amuled_ma.deliberation.build import build_feedback
    from amuled_ma.deliberation.plan import plan_panel
    from amuled_ma.learn.population_groups import MemberSpec
    from amuled_ma.records.variants import Variant

    jobs: list[MemberSpec] = []
    for k in range(count):
        seed = 42 + k
        job = scenario.replace("finetune", lambda_kl=LAMBDAS[k % len(LAMBDAS)])
        out = run / tag / f"finetune-amuled.seed{seed}"
        plan = plan_panel("amuled", job)
        feedback = build_feedback(plan, store, state_dir=out, seed=seed, cache_dir=run)
        jobs.append(
            MemberSpec(
                job, out, variant=Variant.finetune("amuled"), feedback=feedback,
                base_checkpoint=base, seed=seed,
            )
        )  # fmt: skip
    return jobs


def train_base(spec: MemberSpec) -> Path:
    """Train a base policy alone (a population of one); its final checkpoint."""
    from amuled_ma.learn.population import PopulationTrainer

    return PopulationTrainer([spec]).train()[0].checkpoint


def measure_task(task: str, args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """Time the lone fine-tunes and every population size of one task."""
    from amuled_ma.deliberation.build import run_store
    from amuled_ma.learn.population_groups import MemberSpec, member_memory_bytes
    from amuled_ma.tasks import get_task

    scenario, source = _scenario(task, args.base_steps)
    run = out / task
    t0 = time.perf_counter()
    base = train_base(MemberSpec(scenario, run / "base"))
    store = run_store(scenario.store_path(run))
    base_s = time.perf_counter() - t0
    rows = []
    for size in [int(s) for s in args.sizes.split(",") if s.strip()]:
        # the same jobs one by one, timed right before the population (the load of a
        # shared machine drifts: each population is compared with its neighbours)
        lone = [
            _timed([job], args, "cpu")  # alone: a population of one
            for job in _jobs(scenario, run, base, args.lone, f"lone{size}", store)
        ]
        alone = {key: mean(t[key] for t in lone) for key in ("wall_s", "cpu_s", "cpu_it")}
        times = _timed(_jobs(scenario, run, base, size, f"p{size}", store), args, args.device)
        rows.append({"size": size, "alone": alone, **times})
        print(
            f"  {task} P={size}: {size * 3600 / times['cpu_s']:.1f} fine-tunes/h, one by one "
            f"{3600 / alone['cpu_s']:.1f} (CPU time)",
            flush=True,
        )
    shape = _jobs(scenario, run, base, 1, "shape", store)[0].shape()
    task_obj = get_task(scenario.task.name)
    return {
        "task": task,
        "source": source,
        "base_s": base_s,
        "rows": rows,
        "member_bytes": member_memory_bytes(
            shape, obs_dim=len(task_obj.obs_names), num_actions=len(task_obj.action_names)
        ),
    }


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures side by side; returns 0."""
    import torch

    torch.set_num_threads(1)
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    results = []
    with output_folder(args.out, "amuled-bench-population-") as out:
        for task in tasks:
            if args.welch:
                print_welch(task, welch(task, args, out))
                continue
            print(f"{task}: base policy, {args.lone} fine-tunes alone, populations ...", flush=True)
            results.append(measure_task(task, args, out))
    if args.welch:
        return 0
    print()
    print(
        f"Fine-tunes per hour, authors' recipe ({RECIPE_ITERATIONS:,} iterations x 128 steps, "
        "8 epochs x 4 mini-batches), extrapolated from "
        f"{args.warmup} warm-up + {args.iterations} measured iterations per run; "
        f"populations on {args.device}, one torch thread, {os.cpu_count()} cores."
    )
    header = (
        f"{'task':<9} {'P':>4} {'one by one/h':>13} {'population/h':>13} {'speed-up':>9} "
        f"{'wall: 1x1/h':>12} {'pop./h':>7} {'speed-up':>9} {'s/it':>6} {'setup s':>8} "
        f"{'RSS MiB':>8}"
    )
    for result in results:
        rows = result["rows"]
        lone_it = sum(row["alone"]["cpu_it"] for row in rows) / len(rows)
        lone_s = sum(row["alone"]["cpu_s"] for row in rows) / len(rows)
        print(
            f"\n{result['task']}: feedback {result['source']}; one by one (alone): "
            f"{lone_it:.3f} CPU s/iteration, {lone_s / 60:.1f} CPU min per fine-tune "
            f"(mean of {len(rows) * args.lone} runs); memory per member (estimate, tensors "
            f"+ objects + its feedback): {result['member_bytes'] / 2**20:.2f} MiB"
        )
        print(header)
        print("-" * len(header))
        for row in rows:
            size, alone = row["size"], row["alone"]
            cpu_lone, cpu_pop = 3600 / alone["cpu_s"], size * 3600 / row["cpu_s"]
            wall_lone, wall_pop = 3600 / alone["wall_s"], size * 3600 / row["wall_s"]
            print(
                f"{result['task']:<9} {size:>4} {cpu_lone:>13.1f} {cpu_pop:>13.1f} "
                f"{cpu_pop / cpu_lone:>8.1f}x {wall_lone:>12.1f} {wall_pop:>7.1f} "
                f"{wall_pop / wall_lone:>8.1f}x {row['cpu_it']:>6.2f} {row['setup'][1]:>8.1f} "
                f"{row['rss_mib']:>8.0f}"
            )
    print(
        "\nper hour: from this process's CPU time (the machine may be shared; one torch "
        "thread); wall: from the wall clock. s/it: CPU seconds per steady iteration of the "
        "population. RSS: this process's resident memory after the population's run."
    )
    return 0


def _run_metrics(
    outcome: TrainOutcome, task_config: TaskConfig, evaluation: EvaluationConfig, ppo: PPOConfig
) -> dict[str, float]:
    """A finished fine-tune's figures: its evaluation's means and its last 100 iterations."""
    from amuled_ma.commands.demo import evaluate_folder

    evaluated = evaluate_folder(outcome.out_dir, ppo, task_config, evaluation)
    out = {
        f"{mode}/{key}": stat["mean"]
        for mode, entry in evaluated.items()
        for key, stat in entry["metrics"].items()
    }
    tail = outcome.curve[-100:]
    for key in ("feedback/feedback_reward", "feedback/kl", "losses/value", "losses/entropy"):
        values = [row[key] for row in tail if row.get(key) is not None]
        if values:
            out[f"training/{key}"] = sum(values) / len(values)
    return out


def welch(task: str, args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """Train ``args.welch`` seeds alone and as one population; each run's figures."""
    from amuled_ma.deliberation.build import run_store
    from amuled_ma.learn.population import PopulationTrainer
    from amuled_ma.learn.population_groups import MemberSpec

    scenario, source = _scenario(task, args.base_steps)
    scenario = scenario.replace("finetune", lambda_kl=2.5)
    run = out / task
    base = train_base(MemberSpec(scenario, run / "base"))
    store = run_store(scenario.store_path(run))
    groups: dict[str, list[dict[str, float]]] = {}
    times: dict[str, float] = {}
    for group in ("alone", "population"):
        jobs = _jobs(scenario, run, base, args.welch, group, store)
        for job in jobs:
            job.scenario = scenario  # lambda_KL 2.5 for every seed
            job.iterations = args.welch_iterations
        start = time.process_time()
        if group == "population":
            outcomes = PopulationTrainer(jobs, device=args.device).train()
        else:
            outcomes = []
            for job in jobs:
                outcomes.append(PopulationTrainer([job]).train()[0])
                print(f"  {task}: seed {job.training_seed} alone done", flush=True)
        times[group] = time.process_time() - start
        for job in jobs:
            job.feedback.close()
        groups[group] = [
            _run_metrics(outcome, scenario.task, scenario.evaluation, scenario.ppo)
            for outcome in outcomes
        ]
    return {"task": task, "source": source, "groups": groups, "cpu_s": times}


def welch_t(a: list[float], b: list[float]) -> tuple[float, float | None]:
    """Welch's t of ``mean(b) - mean(a)`` and its two-sided p (None without variance)."""
    from scipy import stats

    if max(a) == min(a) and max(b) == min(b):
        return 0.0 if a[0] == b[0] else math.inf, None
    result = stats.ttest_ind(b, a, equal_var=False)
    return float(result.statistic), float(result.pvalue)


def print_welch(task: str, result: dict[str, Any]) -> None:
    """Print each metric's mean and sd per group, Welch's t and p."""
    alone, together = result["groups"]["alone"], result["groups"]["population"]
    n = len(alone)
    print(
        f"\n{task}: {n} seeds alone vs the same {n} as one population, full runs; feedback "
        f"{result['source']}; CPU time alone {result['cpu_s']['alone'] / 60:.1f} min, as a "
        f"population {result['cpu_s']['population'] / 60:.1f} min"
    )
    header = f"{'metric':<34} {'alone':>17} {'population':>17} {'Welch t':>8} {'p':>6}"
    print(header)
    print("-" * len(header))
    for key in sorted(alone[0]):
        a = [run[key] for run in alone]
        b = [run[key] for run in together]
        t, p = welch_t(a, b)
        stat_a, stat_b = (f"{mean(v):.3f} ± {stdev(v):.3f}" for v in (a, b))
        shown_p = "-" if p is None else f"{p:.2f}"
        print(f"{key:<34} {stat_a:>17} {stat_b:>17} {t:>8.2f} {shown_p:>6}")
