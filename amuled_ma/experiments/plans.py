"""The jobs of a run: planned once (`plan_jobs`), prepared and trained in groups.

A population costs a fixed ~0.26 s of CPU per iteration whatever its size, so a level of the
graph is cut into as few populations as fill the workers (`population_groups`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.deliberation.build import build_feedback, checked_members, preflight, run_store
from amuled_ma.deliberation.plan import NoHumanRule, plan_panel
from amuled_ma.errors import AmuledError, CheckpointError
from amuled_ma.experiments.run_folder import (
    JobResult,
    Rerun,
    TrainJob,
    base_checkpoint,
    finished_with,
    mark_state,
    prepare_variant,
    replica_folder,
    variant_fields,
    write_config,
)
from amuled_ma.experiments.training_settings import training_config
from amuled_ma.learn.checkpoints import LAST
from amuled_ma.learn.population_groups import (
    MemberSpec,
    memory_budget_bytes,
    population_key,
    split_populations,
)
from amuled_ma.records.variants import AGGREGATIONS, Variant
from amuled_ma.scenario import Changes, FeedbackConfig, Scenario
from amuled_ma.scenario.paths import find_recording

if TYPE_CHECKING:
    from amuled_ma.beliefs.store.service import StoreService
    from amuled_ma.deliberation.feedback_base import Feedback

#: The variants of the paper's main figure, in order.
MAIN_VARIANTS = (
    Variant("base"),
    Variant("shaped"),
    Variant.finetune("human"),
    Variant.finetune("amuled"),
)
#: What ``amuled ablate --what`` accepts.
ABLATIONS = ("clusters", "aggregation", "models", "kl", "budget", "weights")
#: The folder label of the ``weights`` ablation's fine-tune on the learned weights.
LEARNED_WEIGHTS_LABEL = "amuled-learned-weights"
#: The lambda_KL sweep of the ``kl`` ablation (the paper's value is 2.5).
KL_SWEEP = (0.0, 0.5, 1.0, 2.5, 5.0, 10.0)
#: The budgets of the ``budget`` ablation: shares of the distinct states visited that the
#: panel is asked about (``[feedback.distill].budget``); 100% is asked once, the others
#: with each of `BUDGET_SELECTIONS`.
BUDGET_SWEEP = (1.0, 0.3, 0.1, 0.03)
#: The selections of the ``budget`` ablation (``[feedback.distill].selection``).
BUDGET_SELECTIONS = ("uncertainty", "random")


def training_seeds(first: int, count: int = 1) -> list[int]:
    """``count`` consecutive training seeds from ``first`` (AmuledError below 1)."""
    if count < 1:
        raise AmuledError(f"--seeds must be at least 1, got {count}")
    return [first + k for k in range(count)]


def plan_job(
    job: TrainJob,
    hint: str = "",
    planned: Collection[str] = (),
    *,
    rerun: Rerun | None = None,
) -> TrainJob:
    """Plan a job once: panel plan (its `preflight` run), run shape, settings, base, start.

    Writes nothing. A base in ``planned`` (trained earlier in the same plan) is not looked
    for yet.

    Raises:
        AmuledError: The first thing missing or clashing, in one line naming the fix.
    """
    variant, scenario = job.variant, job.scenario
    panel = plan_panel(variant.feedback, scenario) if variant.feedback is not None else None
    if panel is not None:
        preflight(panel)
    base = None
    if variant.finetuning:
        base = job.base_folder / LAST
        if job.base_variant not in planned:
            from amuled_ma.learn.policies import load_policy

            base = base_checkpoint(job.base_folder, str(scenario.path or scenario.name))
            try:  # a base whose actor does not fit [ppo].hidden_dims is refused here
                load_policy(base, scenario.ppo)
            except CheckpointError as error:
                if "does not fit" not in str(error):
                    raise  # unreadable: the checkpoint's own line
                raise CheckpointError(
                    f"base checkpoint {base}: its networks do not fit this scenario's "
                    f"([ppo].hidden_dims = {list(scenario.ppo.hidden_dims)}, task "
                    f"{scenario.task.name!r}); fine-tune with the [ppo] settings and task the "
                    f"base was trained with (its record: {base.parent / 'config.json'}), or "
                    "train a base with these; nothing was written"
                ) from None
    settings = training_config(job, panel)
    action = prepare_variant(job, settings, hint=hint, rerun=rerun)
    return dataclasses.replace(
        job,
        panel=panel,
        shape=member_spec(job).shape(),
        settings=settings,
        base_checkpoint=base,
        store=scenario.store_path(job.run_dir) if variant.finetuning else None,
        action=action,
    )


def plan_jobs(
    jobs: Sequence[TrainJob], hint: str = "", rerun: Rerun | None = None
) -> list[TrainJob]:
    """Plan every job of a graph with its preflight (`plan_job`), before any folder is made.

    Raises:
        AmuledError: One problem as raised; several as one message listing each once.
    """
    names = {job.out_dir.name for job in jobs}
    out: list[TrainJob] = []
    errors: dict[str, AmuledError] = {}
    for job in jobs:
        try:
            out.append(plan_job(job, hint, names, rerun=rerun))
        except AmuledError as error:
            errors.setdefault(str(error), error)
    problems = list(errors)
    if len(problems) == 1:
        raise errors[problems[0]]
    if problems:
        raise AmuledError(
            f"{len(jobs) - len(out)} of {len(jobs)} jobs cannot start, nothing was trained:\n"
            + "\n".join(f"  - {problem}" for problem in problems)
        )
    return out


def member_spec(job: TrainJob) -> MemberSpec:
    """The population member of a planned job before it is prepared (for grouping only)."""
    return MemberSpec(
        job.scenario,
        job.out_dir,
        variant=job.variant,
        seed=job.seed,
        iterations=job.iterations,
        resume=job.action == "resume",
        planned_shape=job.shape,
    )


def prepare_job(
    job: TrainJob,
    *,
    hint: str = "",
    store: StoreService | None = None,
) -> MemberSpec | JobResult:
    """Build a planned job's feedback and write its folder's record.

    Returns:
        The job's population member (its feedback open: the caller closes it), or the result
        of a job planned as ``skip``.

    Raises:
        AmuledError: A member cannot answer, or the base the plan trained is unfinished.
    """
    assert job.action is not None and job.settings is not None, "prepare_job takes a planned job"
    if job.action == "skip":
        return JobResult(job.variant, job.out_dir, skipped=True)
    feedback: Feedback | None = None
    if job.variant.finetuning:
        assert job.variant.feedback is not None and job.panel is not None and job.store
        members = checked_members(job.panel)
        try:
            base_checkpoint(job.base_folder, str(job.scenario.path or job.scenario.name))
        except BaseException:
            if members is not None:
                members.close()
            raise
        feedback = build_feedback(
            job.panel,
            store if store is not None else run_store(job.store),
            members=members,  # handed over: the feedback closes them
            state_dir=job.out_dir,
            resume=job.action == "resume",
            seed=job.seed,
            cache_dir=job.run_dir,
        )
    try:
        if job.action == "new" or not (job.out_dir / "config.json").is_file():
            fields = variant_fields(
                job.variant,
                job.out_dir,
                job.settings,
                base_checkpoint=job.base_checkpoint,
                feedback=feedback,
            )
            write_config(job.out_dir, job.scenario.to_dict(), fields)
    except BaseException:
        if feedback is not None:
            feedback.close()
        raise
    return dataclasses.replace(
        member_spec(job),
        feedback=feedback,
        base_checkpoint=job.base_checkpoint,
        resume_hint=f"{hint} --resume" if hint else None,
    )


def population_groups(
    jobs: Sequence[TrainJob],
    *,
    workers: int = 1,
    memory_budget: int | None = None,
) -> list[list[TrainJob]]:
    """Group the jobs to train into populations, needs in earlier groups.

    Each level of the graph is cut into at least ``workers`` populations where it has the jobs,
    each within its share of ``memory_budget`` (default: half this machine's memory).
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


def train_population_jobs(
    jobs: Sequence[TrainJob],
    *,
    progress: bool = False,
    hint: str = "",
    on_iteration: Callable[[Any, int], None] | None = None,
    store_for: Callable[[TrainJob], Any] | None = None,
    announce: bool = True,
) -> tuple[dict[str, JobResult], list[str]]:
    """Train a group of planned jobs as populations (split by `population_key`).

    A job that fails alone is marked ``failed`` and the others finish; ``announce`` prints a
    line when one fails (a Ray worker leaves it to the driver). Returns the results of the
    jobs that finished, by name, and a line per failure.

    Raises:
        AmuledError: A job's inputs are missing (before anything trains).
        KeyboardInterrupt: Ctrl-C or SIGTERM, after every member wrote its checkpoint.
    """
    from amuled_ma.learn.population import train_population  # here: it imports torch

    failures: list[str] = []
    prepared: list[tuple[TrainJob, MemberSpec]] = []
    done: dict[str, JobResult] = {}
    try:
        for job in jobs:
            ready = prepare_job(
                job, hint=hint, store=store_for(job) if store_for is not None else None
            )
            if isinstance(ready, JobResult):
                done[job.name] = ready
            else:
                ready.on_iteration = on_iteration
                prepared.append((job, ready))
        specs = [spec for _, spec in prepared]
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
                    _mark_failed(prepared[i][0])
                raise
            for i, result in zip(members, trained, strict=True):
                job = prepared[i][0]
                if isinstance(result, BaseException):
                    _mark_failed(job)
                    failures.append(str(result))
                else:
                    mark_state(job.out_dir, "complete", result.iterations)
                    done[job.name] = JobResult(job.variant, job.out_dir, outcome=result)
    finally:
        for _, spec in prepared:
            if spec.feedback is not None:
                spec.feedback.close()
    return {job.name: done[job.name] for job in jobs if job.name in done}, failures


def _mark_failed(job: TrainJob) -> None:
    """Record the job failed (unless the disk is full: the error says so)."""
    with contextlib.suppress(OSError):
        mark_state(job.out_dir, "failed")


def population_failure(failures: Sequence[str], hint: str) -> AmuledError:
    """The sweep's closing error for jobs that failed alone (each named when it failed)."""
    count = f"{len(failures)} jobs" if len(failures) > 1 else "a job"
    then = f"; after fixing it, continue with: {hint} --resume" if hint else ""
    return AmuledError(
        f"{count} of a population failed alone (named above; their last checkpoints are "
        f"kept) and the other members finished{then}"
    )


def ablation_variants(
    what: str, feedback: FeedbackConfig, task: str, resolve: Callable[[str], Path], where: str
) -> list[tuple[Variant, Changes]]:
    """The fine-tunes of one ablation: ``(variant, changes to the scenario)``.

    ``resolve`` resolves the recording's path against the scenario file's folder; ``where``
    names the scenario in messages.

    Raises:
        AmuledError: ``weights`` without ``[feedback].weights``.
    """
    if what == "weights" and not feedback.weights.strip():
        raise AmuledError(
            f"{where}: ablate --what weights compares the paper's "
            "fixed weights with learned ones, but [feedback].weights names no file; pass "
            "--weights FILE (written by 'amuled study fit-weights STUDY') or set "
            "[feedback].weights"
        )
    base: Changes = ()
    needs_members = ("clusters", "aggregation", "budget", "weights")
    if what in needs_members and feedback.cluster_recording:
        # these need each cluster's belief: a fused-only recording cannot serve them
        base = (("feedback", {"recording": feedback.cluster_recording}),)
    jobs: list[tuple[Variant, Changes]]
    if what == "clusters":
        jobs = [(Variant.finetune(f"cluster:{c}"), base) for c in feedback.clusters]
        jobs.append((Variant.finetune("moral"), base))
        jobs.append((Variant.finetune("amuled"), base))
    elif what == "aggregation":
        jobs = [(Variant.finetune(f"agg:{rule}"), base) for rule in AGGREGATIONS]
        jobs.append((Variant.finetune("amuled"), base))
    elif what == "weights":
        jobs = [
            (Variant.finetune("amuled"), (*base, ("feedback", {"weights": ""}))),
            (Variant.finetune("amuled", label=LEARNED_WEIGHTS_LABEL), base),
        ]
    elif what == "kl":
        jobs = [
            (
                Variant.finetune("amuled", label=f"amuled-kl{lam:g}"),
                (*base, ("finetune", {"lambda_kl": lam})),
            )
            for lam in KL_SWEEP
        ]
    elif what == "budget":
        jobs = []
        for budget in BUDGET_SWEEP:
            for selection in BUDGET_SELECTIONS[: 1 if budget == 1.0 else None]:
                label = f"amuled-budget{budget:g}" + ("" if budget == 1.0 else f"-{selection}")
                distill = {"distill.enabled": True, "distill.budget": budget,
                           "distill.selection": selection}  # fmt: skip
                jobs.append(
                    (Variant.finetune("amuled", label=label), (*base, ("feedback", distill)))
                )
        full = (*base, ("feedback", {"distill.enabled": False}))
        jobs.append((Variant.finetune("amuled"), full))
    else:  # "models" (an unknown ablation is refused by `PipelineRequest` and the CLI)
        jobs = []
        if feedback.source == "replay":
            rec = find_recording(feedback.recording, resolve, where=where)
            for path in sorted(rec.parent.glob(f"{task}-*.json")):
                model = path.stem[len(task) + 1 :]
                changes: Changes = (("feedback", {"recording": str(path), "model": model}),)
                jobs.append((Variant.finetune("amuled", label=f"amuled-{model}"), changes))
        else:
            jobs.append((Variant.finetune("amuled", label=f"amuled-{feedback.model}"), ()))
        if not jobs:
            raise AmuledError(f"no recordings for task {task!r} next to {rec}")
    return jobs


def plan_run(
    scenario: Scenario,
    run_dir: Path,
    seeds: Sequence[int],
    *,
    resume: bool = False,
    force: bool = False,
    base: Path | None = None,
) -> list[TrainJob]:
    """The jobs of ``amuled run``: `MAIN_VARIANTS` for every seed, bases first.

    ``human`` only for a task with synthetic human feedback (``BatchedTask.human_feedback``).
    Each seed's fine-tunes anchor to that seed's base, or all to ``base`` (a finished variant
    folder) when given. The first seed's folders carry no suffix.
    """
    from amuled_ma.tasks import get_task
    from amuled_ma.tasks.names import TASK_NAMES

    # known by name for the paper's tasks, so that a refused run imports no torch
    human = scenario.task.name in TASK_NAMES or get_task(scenario.task.name).human_feedback
    variants = [v for v in MAIN_VARIANTS if human or v != Variant.finetune("human")]
    run_dir = Path(run_dir)
    jobs = []
    for seed in seeds:
        own = replica_folder("base", seed, seeds[0])
        for variant in variants:
            folder = replica_folder(variant.folder, seed, seeds[0])
            job = TrainJob(
                name=folder, scenario=scenario, run_dir=run_dir, variant=variant,
                out_dir=run_dir / folder, seed=seed, base_variant=own, resume=resume, force=force,
            )  # fmt: skip
            if variant.finetuning and base is not None:  # a finished base outside the plan
                job = dataclasses.replace(job, base_variant=base.name, base_dir=base.parent)
            elif variant.finetuning:
                job = dataclasses.replace(job, needs=(own,))
            jobs.append(job)
    return jobs


def retrain_jobs(jobs: Sequence[TrainJob], names: Collection[str]) -> list[TrainJob]:
    """The plan with ``names`` (and the jobs that need them) retrained, the others resumed.

    Raises:
        AmuledError: A name that is no job of the plan; the message lists the plan's jobs.
    """
    if not names:
        return list(jobs)
    chosen = set()
    for name in names:
        hits = {job.name for job in jobs if name in (job.name, job.out_dir.name)}
        if not hits:
            known = ", ".join(job.name for job in jobs)
            raise AmuledError(f"--retrain {name}: not a variant of this run; its variants: {known}")
        chosen |= hits
    # a job that needs a retrained one is retrained too
    while more := {job.name for job in jobs if chosen.intersection(job.needs)} - chosen:
        chosen |= more
    return [
        dataclasses.replace(job, force=job.name in chosen, resume=job.name not in chosen)
        for job in jobs
    ]


def plan_ablation(
    what: str,
    scenario: Scenario,
    run_dir: Path,
    seeds: Sequence[int],
    *,
    resume: bool = False,
    force: bool = False,
) -> list[TrainJob]:
    """The jobs of ``amuled ablate --what WHAT``: each seed's base (resumed), then its fine-tunes.

    The fine-tunes go to ``<run_dir>/ablate-<what>/``, except one ``amuled run`` finished with
    exactly the same settings (`finished_with`): that job is the run's folder, skipped.

    Raises:
        AmuledError: See `ablation_variants`.
    """
    run_dir = Path(run_dir)
    out = run_dir / f"ablate-{what}"
    where = str(scenario.path or scenario.name)
    listed = ablation_variants(what, scenario.feedback, scenario.task.name, scenario.resolve, where)
    variants: list[tuple[Variant, Scenario]] = []
    for variant, changes in listed:
        changed = scenario.changed(changes)
        if variant == Variant.finetune("moral"):  # left out where its agent is the missing human
            problems = plan_panel("moral", changed).problems
            missing = [error for error, _ in problems if isinstance(error, NoHumanRule)]
            if missing:
                print(
                    f"amuled: note: no 'moral' row: the unprompted moral agent's source is the "
                    f"rules source, and {missing[0]}",
                    file=sys.stderr,
                )
                continue
        variants.append((variant, changed))
    jobs = []
    for seed in seeds:
        base = replica_folder("base", seed, seeds[0])
        jobs.append(
            TrainJob(name=base, scenario=scenario, run_dir=run_dir, variant=Variant("base"),
                     out_dir=run_dir / base, seed=seed, base_variant=base, resume=True)
        )  # fmt: skip
        for variant, sc in variants:
            replica = replica_folder(variant.folder, seed, seeds[0])
            job = TrainJob(
                name=f"{out.name}/{replica}", scenario=sc, run_dir=run_dir, variant=variant,
                out_dir=out / replica, seed=seed, base_variant=base, needs=(base,),
                resume=resume, force=force,
            )  # fmt: skip
            assert variant.feedback is not None
            try:
                settings = training_config(job, plan_panel(variant.feedback, sc))
            except AmuledError:
                settings = None  # plan_jobs names the problem
            if settings is not None and finished_with(run_dir / replica, settings):
                job = dataclasses.replace(
                    job, name=replica, out_dir=run_dir / replica, resume=True, force=False
                )
            jobs.append(job)
    return jobs
