"""One experiment as one call: `run_pipeline` plans, checks, trains, evaluates and reports.

`train_alone` is one job through the same checks, lock and record, not evaluated.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.errors import AmuledError, ScenarioError
from amuled_ma.experiments.jobs import (
    JobsOutcome,
    RayTarget,
    ray_connection,
    resolve_workers,
    run_jobs,
)
from amuled_ma.experiments.run_folder import (
    JobResult,
    Rerun,
    TrainJob,
    split_replica,
    write_config,
)
from amuled_ma.files.run_lock import run_folder_lock
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario

if TYPE_CHECKING:
    from amuled_ma.evaluate.results import Results


def say_line(message: str) -> None:
    """Print one progress line on stdout at once (stderr stays free for errors)."""
    print(message, flush=True)


@dataclass(frozen=True)
class PipelineRequest:
    """One experiment to run: what to plan, where, and how to train it.

    ``ablation`` None is the paper's main comparison (``amuled run``), else one of
    `ABLATIONS`, written into ``run_dir/ablate-<what>/``; ``seed`` None is ``[task].seed``,
    ``seeds`` the replicas of every variant; ``episodes`` None is ``[evaluation].episodes``;
    ``base`` a finished base folder every fine-tune of the main comparison starts from (None:
    each seed's own, or the authors' imported base with ``[finetune].recipe = "authors"``);
    ``retrain`` the job names retrained while the others resume; ``jobs`` the jobs at once
    (0: one per core, or 1 with live feedback); ``population`` False trains every job alone;
    ``hint`` the shell command that re-runs it (default: ``rerun``'s line); ``offline``
    never fetches the authors' recordings.

    Raises:
        ScenarioError: An unknown ablation.
        AmuledError: ``base`` given with an ablation.
    """

    scenario: Scenario
    run_dir: Path
    ablation: str | None = None
    seed: int | None = None
    seeds: int = 1
    episodes: int | None = None
    base: Path | None = None
    resume: bool = False
    force: bool = False
    retrain: tuple[str, ...] = ()
    jobs: int = 0
    ray: RayTarget | None = None
    population: bool = True
    progress: bool = True
    hint: str = ""
    rerun: Rerun | None = None
    title: str | None = None
    offline: bool = False

    def __post_init__(self) -> None:
        if self.rerun is not None and not self.hint:
            object.__setattr__(self, "hint", self.rerun.line(self.run_dir))
        from amuled_ma.experiments.plans import ABLATIONS  # here: it imports torch

        if self.ablation is not None and self.ablation not in ABLATIONS:
            raise ScenarioError(
                f"unknown ablation {self.ablation!r}; expected one of {', '.join(ABLATIONS)}"
            )
        if self.ablation is not None and self.base is not None:
            raise AmuledError(
                "a base folder applies to the main comparison (amuled run --base), not to "
                "an ablation: drop it, an ablation fine-tunes the run's own bases"
            )


@dataclass(frozen=True)
class PipelineOutcome:
    """What `run_pipeline` did: where the results and report are, what was trained, how long.

    ``out_dir`` is the run folder or its ``ablate-<what>/``; ``variants`` the variants planned.
    """

    out_dir: Path
    variants: tuple[str, ...]
    seeds: tuple[int, ...]
    training: JobsOutcome
    results: Results = field(repr=False)
    report: Path
    wall_s: float


def run_pipeline(
    request: PipelineRequest, *, say: Callable[[str], None] = say_line
) -> PipelineOutcome:
    """Plan, check, train, evaluate and report one experiment (``amuled run``/``ablate``/``demo``).

    ``say`` prints a progress line.

    Raises:
        AmuledError: An input is missing or a folder clashes (before any folder is made),
            another process writes the run folder, or a job failed.
        KeyboardInterrupt: Ctrl-C or SIGTERM, after every running job wrote its checkpoint.
    """
    from amuled_ma.authors.download import (
        ensure_recordings,
        models_ablation_recordings,
        replayed_recordings,
    )
    from amuled_ma.experiments.plans import (
        MAIN_VARIANTS,
        ablation_variants,
        plan_ablation,
        plan_jobs,
        plan_run,
        retrain_jobs,
        training_seeds,
    )
    from amuled_ma.experiments.run_folder import read_record, variant_records
    from amuled_ma.scenario.memory import check_seed_replicas

    start = time.perf_counter()
    check_seed_replicas(request.seeds, variants=1)  # before a job per seed is planned
    sc, run_dir, what = request.scenario, Path(request.run_dir), request.ablation
    seeds = training_seeds(sc.task.seed if request.seed is None else request.seed, request.seeds)
    # the authors' recordings found nowhere here are fetched (never with ``offline``)
    fetch = functools.partial(ensure_recordings, sc.resolve, offline=request.offline, say=say)
    resume, force = request.resume, request.force
    if what is None:  # the main comparison: MAIN_VARIANTS per seed
        base, imported = request.base, Path(sc.output.runs_dir) / "authors" / sc.task.name / "base"
        if base is None and sc.finetune.recipe == "authors":
            if (imported / "model_last.pt").is_file():
                base = imported
                say(f"  fine-tunes start from the authors' imported base {imported}")
            else:
                say(
                    f"  fine-tunes start from this run's own bases (no imported authors' base "
                    f"at {imported}; 'amuled import authors PATH' makes one)"
                )
        jobs = plan_run(sc, run_dir, seeds, resume=resume, force=force, base=base)
        out_dir, variants, extra_dirs = run_dir, tuple(str(v) for v in MAIN_VARIANTS), []
        config: dict[str, Any] = {"variants": list(variants), "seeds": seeds}
        announce, title = f"run {sc.name} -> {run_dir}", f"{sc.name}: the paper's main comparison"
    else:  # the run's bases, then the ablation's fine-tunes in ablate-<what>/
        if what == "models":  # it plans one fine-tune per recording found beside
            fetch(models_ablation_recordings(sc.feedback, sc.task.name, sc.resolve))
        where = str(sc.path or sc.name)
        listed = ablation_variants(what, sc.feedback, sc.task.name, sc.resolve, where)
        variants = tuple(variant.folder for variant, _ in listed)
        jobs = plan_ablation(what, sc, run_dir, seeds, resume=resume, force=force)
        out_dir = run_dir / f"ablate-{what}"
        # the run's folders an ablation evaluates with its own: the bases, and fine-tunes the
        # run already finished with the same settings (not trained again)
        shared = [job.out_dir.name for job in jobs if job.out_dir.parent == run_dir]
        extra_dirs = [run_dir / name for name in shared]
        config = {"ablation": what, "variants": list(variants), "seeds": seeds, "shared": shared}
        announce = (
            f"ablate {sc.name} --what {what}: {len(variants)} fine-tunes x {len(seeds)} "
            f"seed(s) -> {out_dir}"
        )
        title = f"{sc.name}: ablation of {what}"
    replayed = [job.scenario.feedback for job in jobs if job.variant.finetuning]
    fetch(list(dict.fromkeys(v for feedback in replayed for v in replayed_recordings(feedback))))
    if request.retrain:
        jobs = retrain_jobs(jobs, request.retrain)
    # before the lock: a refused run makes no folder
    jobs = plan_jobs(jobs, request.hint, request.rerun)
    say_live_costs(jobs, say)
    # after the checks: a refused run answers before torch and matplotlib are imported
    from amuled_ma.evaluate.evaluator import evaluate_run, variant_dirs
    from amuled_ma.evaluate.report import evaluation_outputs, write_report
    from amuled_ma.files.safe import check_write_targets

    check_write_targets(evaluation_outputs(out_dir))  # before training, as the inputs
    workers = resolve_workers(request.jobs, jobs)
    with run_folder_lock(run_dir):
        say(announce)
        # Ray first: a SIGTERM while it starts leaves no run folder (the lock removes it)
        with ray_connection(jobs, workers=workers, ray=request.ray):
            write_config(out_dir, sc.to_dict(), config)
            where = "" if request.ray is None else f" on Ray ({request.ray.address or 'local'})"
            say(f"  {len(jobs)} training jobs, {workers} at a time{where}")
            training = run_jobs(
                jobs,
                workers=workers,
                progress=request.progress,
                hint=request.hint,
                describe=describe_job,
                ray=request.ray,
                population=request.population,
            )
            say(f"  training done in {training.wall_s:.1f} s on {training.workers} worker(s)")
        records = variant_records([*variant_dirs(out_dir), *extra_dirs])
        results = evaluate_run(
            out_dir,
            scenario_name=sc.name,
            task_config=sc.task,
            evaluation=sc.evaluation,
            ppo=sc.ppo,
            episodes=request.episodes,
            progress=request.progress,
            extra_dirs=extra_dirs or None,
            records=records,
        )
        report = write_report(
            out_dir,
            results,
            title=request.title or title,
            ablation=what,
            run=read_record(out_dir),
            records=records,
        )
    return PipelineOutcome(
        out_dir=out_dir,
        variants=variants,
        seeds=tuple(seeds),
        training=training,
        results=results,
        report=report,
        wall_s=time.perf_counter() - start,
    )


def say_live_costs(jobs: Sequence[TrainJob], say: Callable[[str], None]) -> None:
    """Print each fine-tune's live model costs (`live_costs`), each distinct line once."""
    from amuled_ma.deliberation.build import live_costs

    said: set[str] = set()
    for job in jobs:
        if job.panel is None or job.store is None:
            continue  # a base, or a fine-tune whose feedback asks no panel
        lines = live_costs(job.panel, job.store, lambda text: say(f"  {text}"))
        for line in lines:
            if line not in said:
                said.add(line)
                say(f"  {line}")


def train_alone(
    request: PipelineRequest,
    variant: Variant,
    *,
    base_variant: str = "base",
    base_dir: Path | None = None,
    config: dict[str, Any] | None = None,
    iterations: int | None = None,
) -> JobResult:
    """Train one job (``amuled train`` / ``finetune``): planned, locked, trained; not evaluated.

    ``base_variant`` is a fine-tune's base folder in ``base_dir`` (default: the run folder);
    ``config`` holds run-level ``config.json`` fields to write (None: left alone);
    ``iterations`` overrides the planned number.

    Raises:
        AmuledError: As `run_pipeline`.
        KeyboardInterrupt: Ctrl-C or SIGTERM, after the job wrote its checkpoint.
    """
    from amuled_ma.experiments.plans import plan_jobs  # here: a slow import

    run_dir = Path(request.run_dir)
    job = TrainJob(
        name=variant.folder,
        scenario=request.scenario,
        run_dir=run_dir,
        variant=variant,
        out_dir=run_dir / variant.folder,
        seed=request.seed,
        base_variant=base_variant,
        resume=request.resume,
        force=request.force,
        base_dir=base_dir,
        iterations=iterations,
    )
    # before the lock: a refused job makes no folder
    jobs = plan_jobs([job], request.hint, request.rerun)
    say_live_costs(jobs, say_line)
    with run_folder_lock(run_dir):
        if config is not None:
            write_config(run_dir, request.scenario.to_dict(), config)
        outcome = run_jobs(
            jobs, progress=request.progress, hint=request.hint, describe=describe_job
        )
    return outcome.results[0]


def describe_job(job: JobResult) -> str:
    """One line about a skipped or trained job, then the feedback's and failing agents' lines."""
    from amuled_ma.deliberation.summaries import distill_line, summary_lines

    seed = split_replica(Path(job.out_dir).name)[1]
    name = job.variant if seed is None else f"{job.variant} [seed {seed}]"
    out = job.outcome
    if job.skipped or out is None:
        return f"  = {name}: already trained ({job.out_dir})"
    rate = out.env_steps / max(out.wall_s, 1e-9)
    line = (
        f"  ✓ {name}: {out.iterations} iterations, {out.env_steps:,} env steps in "
        f"{out.wall_s:.1f} s ({rate:,.0f} steps/s)"
    )
    if out.feedback:
        line += f", {out.feedback['unique_states']} distinct states"
        line += f", replay miss rate {100 * out.feedback['miss_rate']:.2f}%"
        line += f", not answered {100 * out.feedback.get('failure_rate', 0.0):.2f}%"
        if out.feedback.get("distill"):
            line += "\n  " + distill_line(out.feedback["distill"])
        # per agent, the agents that left states unanswered (abstained, errors, misses)
        failing = {
            name: row
            for name, row in (out.feedback.get("agents") or {}).items()
            if row.get("failed")
        }
        shown = summary_lines({**out.feedback, "agents": failing, "distill": None})[1:]
        line += "".join("\n    " + text for text in shown)
    return line
