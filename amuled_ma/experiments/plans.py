"""Experiments: the paper's pipeline and ablations, as resumable jobs over a run directory.

:func:`plan_run` and :func:`plan_ablation` list the jobs of ``amuled run`` and ``amuled
ablate`` (:class:`~amuled_ma.experiments.run_folder.TrainJob`: a fine-tune needs its seed's
base); :func:`plan_jobs` plans each once (:func:`plan_job`: its panel plan and preflight,
run shape, settings, base checkpoint, new / resume / skip) before any folder exists;
:func:`prepare_job` builds a planned job's feedback and writes its record; and
:func:`train_variant` plans, prepares and trains one variant alone.
:mod:`amuled_ma.experiments.jobs` trains a planned graph.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.deliberation.build import build_feedback, checked_members, preflight, run_store
from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.errors import AmuledError, CheckpointError, ScenarioError
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
from amuled_ma.learn.job_shape import job_shape
from amuled_ma.scenario import Scenario
from amuled_ma.variants import AGGREGATIONS, Variant

if TYPE_CHECKING:
    from amuled_ma.beliefs.store_service import StoreService
    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.learn.population import TrainOutcome
    from amuled_ma.learn.population_groups import MemberSpec

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
#: with each of :data:`BUDGET_SELECTIONS`.
BUDGET_SWEEP = (1.0, 0.3, 0.1, 0.03)
#: The selections of the ``budget`` ablation (``[feedback.distill].selection``).
BUDGET_SELECTIONS = ("uncertainty", "random")


def training_seeds(first: int, count: int = 1) -> list[int]:
    """The training seeds of a run: ``count`` consecutive seeds from ``first``.

    Raises:
        AmuledError: ``count`` is below 1.

    """
    if count < 1:
        raise AmuledError(f"--seeds must be at least 1, got {count}")
    return [first + k for k in range(count)]


def plan_job(
    job: TrainJob,
    hint: str = "",
    planned: Collection[str] = (),
    *,
    rerun: Rerun | None = None,
    check_panel: bool = True,
) -> TrainJob:
    """Plan a job once: its panel plan, run shape, settings, base checkpoint and start.

    A fine-tune's feedback variant is resolved into its panel plan
    (:func:`~amuled_ma.deliberation.plan.plan_panel`: known clusters, shipped or in
    ``[feedback].clusters_dirs``, their sources) and its base checkpoint is found
    finished, unless the base is trained earlier in the same plan (``planned``); its
    settings (:func:`~amuled_ma.experiments.training_settings.training_config`, with the
    inputs' hashes) decide its folder's start
    (:func:`~amuled_ma.experiments.run_folder.prepare_variant`: new, resume or skip).
    With ``check_panel`` the panel's preflight runs
    (:func:`~amuled_ma.deliberation.build.preflight`: a recording holds the member's
    cluster and the task, a server has the model, a plug-in loads; its sources closed
    again). Nothing is written.

    Args:
        job: The job as the plan lists it.
        hint: The command that re-runs the job (named in a refusal).
        planned: The folder names the same plan trains (a base among them is not
            looked for yet).
        rerun: The command that re-runs the job, as fields (a refusal's recovery commands).
        check_panel: Run the panel's preflight (False: :func:`prepare_job` checks the
            sources it builds).

    Returns:
        The job with its planned fields set.

    Raises:
        AmuledError: The first thing missing or clashing, in one line naming the fix.

    """
    variant, scenario = job.variant, job.scenario
    panel = plan_panel(variant.feedback, scenario) if variant.feedback is not None else None
    if panel is not None and check_panel:
        preflight(panel)
    base = None
    if variant.finetuning:
        base = job.base_folder / LAST
        if job.base_variant not in planned:
            base = base_checkpoint(job.base_folder, str(scenario.path or scenario.name))
            check_base_fits(base, scenario)
    settings = training_config(
        scenario, variant, panel=panel, seed=job.seed, iterations=job.iterations
    )
    action = prepare_variant(job, settings, hint=hint, rerun=rerun)
    return dataclasses.replace(
        job,
        panel=panel,
        shape=job_shape(scenario, variant, job.iterations),
        settings=settings,
        base_checkpoint=base,
        store=scenario.store_path(job.run_dir) if variant.finetuning else None,
        action=action,
    )


def plan_jobs(
    jobs: Sequence[TrainJob], hint: str = "", rerun: Rerun | None = None
) -> list[TrainJob]:
    """Plan every job of a graph with its preflight (:func:`plan_job`), before any folder is made.

    Args:
        jobs: The graph, each job after the jobs it needs.
        hint: The command that re-runs the graph (named in a refusal).
        rerun: The same command as fields (a refusal's recovery commands).

    Returns:
        The planned jobs, in order.

    Raises:
        AmuledError: One problem as it was raised; several as one message listing each
            distinct problem once (``N of M jobs cannot start, nothing was trained``).

    """
    names = {job.out_dir.name for job in jobs}
    out: list[TrainJob] = []
    errors: dict[str, AmuledError] = {}
    failing = 0
    for job in jobs:
        try:
            out.append(plan_job(job, hint, names, rerun=rerun))
        except AmuledError as error:
            failing += 1
            errors.setdefault(str(error), error)
    problems = list(errors)
    if len(problems) == 1:
        raise errors[problems[0]]
    if problems:
        raise AmuledError(
            f"{failing} of {len(jobs)} jobs cannot start, nothing was trained:\n"
            + "\n".join(f"  - {problem}" for problem in problems)
        )
    return out


@dataclass
class PreparedJob:
    """A planned job ready to train: its folder's record written, its feedback built.

    Attributes:
        job: The planned job.
        feedback: A fine-tune's feedback (open: :meth:`close` it), else None.
        resume_hint: The command that resumes it (printed on Ctrl-C).

    """

    job: TrainJob
    feedback: Feedback | None
    resume_hint: str | None

    def close(self) -> None:
        """Close the feedback (its sources and store connections)."""
        if self.feedback is not None:
            self.feedback.close()

    def finished(self, outcome: TrainOutcome) -> JobResult:
        """Record the job complete; its result."""
        mark_state(self.job.out_dir, "complete", outcome.iterations)
        return JobResult(self.job.variant, self.job.out_dir, outcome=outcome)

    def failed(self) -> None:
        """Record the job failed (unless the disk is full: the error says so)."""
        with contextlib.suppress(OSError):
            mark_state(self.job.out_dir, "failed")

    def member(
        self,
        on_iteration: Callable[[Any, int], None] | None = None,
        task_factory: Callable[..., Any] | None = None,
    ) -> MemberSpec:
        """The population member that trains it (its feedback, base, resume).

        Args:
            on_iteration: Called as ``fn(member, iteration)`` after every iteration
                (:class:`~amuled_ma.learn.population.PopulationMember`).
            task_factory: Replaces the task constructor (tests).

        """
        from amuled_ma.learn.population_groups import MemberSpec  # here: it imports torch

        job = self.job
        return MemberSpec(
            job.scenario,
            job.out_dir,
            variant=job.variant,
            feedback=self.feedback,
            base_checkpoint=job.base_checkpoint,
            resume=job.action == "resume",
            seed=job.seed,
            iterations=job.iterations,
            resume_hint=self.resume_hint,
            on_iteration=on_iteration,
            task_factory=task_factory,
            planned_shape=job.shape,
        )


def check_base_fits(base: Path, scenario: Scenario) -> None:
    """Refuse a base whose actor does not fit the scenario's networks, before any folder.

    The fine-tune loads the base into networks of ``[ppo].hidden_dims``; a base trained
    with other dims (or for another task) would fail there, after its variant folder was
    made. Loading its actor here (:func:`~amuled_ma.learn.policies.load_policy`) finds it
    while nothing is written.

    Raises:
        CheckpointError: The actor does not fit; one line naming the base, the dims and
            the fix.

    """
    from amuled_ma.learn.policies import load_policy

    try:
        load_policy(base, scenario)
    except CheckpointError as error:
        if "does not fit" not in str(error):
            raise  # unreadable: the checkpoint's own line
        raise CheckpointError(
            f"base checkpoint {base}: its networks do not fit this scenario's "
            f"([ppo].hidden_dims = {list(scenario.ppo.hidden_dims)}, task "
            f"{scenario.task.name!r}); fine-tune with the [ppo] settings and task the base was "
            f"trained with (its record: {base.parent / 'config.json'}), or train a base with "
            "these; nothing was written"
        ) from None


def prepare_job(
    job: TrainJob,
    *,
    hint: str = "",
    store: StoreService | None = None,
    feedback_factory: Callable[[str], Feedback] | None = None,
) -> PreparedJob | JobResult:
    """Build a planned job's feedback and write its folder's record.

    A fine-tune's member sources are built and checked from its panel plan
    (:func:`~amuled_ma.deliberation.build.checked_members`) and its feedback is built of
    them; its base, when the same plan trained it, is checked finished.

    Args:
        job: The job, planned (:func:`plan_job`).
        hint: The command that re-runs the job (printed with ``--resume`` on a stop).
        store: The belief store of the fine-tune's panel (default: the run's file,
            ``[feedback].store``, opened on first use,
            :func:`~amuled_ma.deliberation.build.run_store`).
        feedback_factory: ``variant -> Feedback``, replaces the feedback built from the
            plan (tests).

    Returns:
        The prepared job, or the result of a job planned as ``skip``.

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
        if feedback_factory is not None:
            if members is not None:
                members.close()
            feedback = feedback_factory(job.variant.feedback)
        else:
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
            write_config(job.out_dir, job.scenario, fields)
    except BaseException:
        if feedback is not None:
            feedback.close()
        raise
    return PreparedJob(job, feedback, f"{hint} --resume" if hint else None)


def train_variant(
    scenario: Scenario,
    run_dir: Path,
    variant: Variant,
    *,
    resume: bool = False,
    force: bool = False,
    progress: bool = False,
    hint: str = "",
    iterations: int | None = None,
    seed: int | None = None,
    out_dir: Path | None = None,
    base_dir: Path | None = None,
    base_variant: str = "base",
    on_iteration: Callable[[Any, int], None] | None = None,
    task_factory: Callable[..., Any] | None = None,
    feedback_factory: Callable[[str], Feedback] | None = None,
    store: StoreService | None = None,
) -> JobResult:
    """Train one variant (``base``, ``shaped`` or ``finetune:<feedback>``) into the run.

    The job is planned (:func:`plan_job`), prepared (:func:`prepare_job`) and trained
    alone, as a population of one (:class:`~amuled_ma.learn.population.PopulationTrainer`:
    the one training loop of every job); its record says complete or failed.

    Args:
        scenario: The scenario.
        run_dir: The run directory.
        variant: What to train.
        resume: Continue an unfinished checkpoint.
        force: Start over even when a checkpoint exists.
        progress: Show a progress bar.
        hint: The command that re-runs this job (for messages and Ctrl-C).
        iterations: Override the number of iterations.
        seed: Override the scenario's seed.
        out_dir: Folder of the variant (default ``run_dir/<variant folder>``).
        base_dir: Run directory holding the base checkpoint (default ``run_dir``).
        base_variant: Folder of the base checkpoint in ``base_dir`` (a seed replica's base).
        on_iteration: Called as ``fn(member, iteration)`` after every iteration.
        task_factory: Replaces the task constructor (tests).
        feedback_factory: ``variant -> Feedback``, replaces the feedback built from the
            plan (tests).
        store: The belief store of the fine-tune's panel (default: the run's file,
            ``[feedback].store``, opened on first use,
            :func:`~amuled_ma.deliberation.build.run_store`).

    Returns:
        The job result.

    Raises:
        AmuledError: An input is missing or the folder clashes (nothing written).
        MemberFailed: Its feedback failed or its gradient was not finite (its checkpoint
            before that iteration is written).

    """
    run_dir = Path(run_dir)
    job = TrainJob(
        name=variant.folder,
        scenario=scenario,
        run_dir=run_dir,
        variant=variant,
        out_dir=Path(out_dir) if out_dir else run_dir / variant.folder,
        seed=seed,
        base_variant=base_variant,
        resume=resume,
        force=force,
        base_dir=Path(base_dir) if base_dir else None,
        iterations=iterations,
    )
    planned = plan_job(job, hint, check_panel=False)  # prepare_job checks what it builds
    prepared = prepare_job(planned, hint=hint, store=store, feedback_factory=feedback_factory)
    if isinstance(prepared, JobResult):
        return prepared
    # after the checks: torch and rsl-rl load here, so that a refused job answers fast
    from amuled_ma.learn.population import PopulationTrainer

    try:
        member = prepared.member(on_iteration, task_factory)
        outcome = PopulationTrainer([member], progress=progress).train()[0]
        return prepared.finished(outcome)
    except Exception:
        # not an interruption: the record says so
        prepared.failed()
        raise
    finally:
        prepared.close()


def ablation_variants(what: str, scenario: Scenario) -> list[tuple[Variant, Scenario]]:
    """List the fine-tunes of one ablation: ``(variant, scenario)``.

    ``budget``: AMULED with ``[feedback.distill]`` at each budget of
    :data:`BUDGET_SWEEP` (100% once, the others with each selection of
    :data:`BUDGET_SELECTIONS`; folders ``finetune-amuled-budget0.1-uncertainty``), and
    AMULED with every state asked (the full-feedback run, shared with ``amuled run`` when
    it finished there with the same settings).

    ``weights``: AMULED with the paper's fixed weights (``[feedback].weights`` emptied; shared
    with ``amuled run`` when it finished there with the same settings) and AMULED with the
    learned weights of ``[feedback].weights`` (folder ``finetune-amuled-learned-weights``),
    on the same seeds.

    Args:
        what: ``clusters``, ``aggregation``, ``models``, ``kl``, ``budget`` or ``weights``.
        scenario: The base scenario.

    Returns:
        The jobs, each with the (possibly modified) scenario it runs on.

    Raises:
        AmuledError: ``weights`` without ``[feedback].weights``.

    """
    if what == "weights" and not scenario.feedback.weights.strip():
        raise AmuledError(
            f"{scenario.path or scenario.name}: ablate --what weights compares the paper's "
            "fixed weights with learned ones, but [feedback].weights names no file; pass "
            "--weights FILE (written by 'amuled study fit-weights STUDY') or set "
            "[feedback].weights"
        )
    needs_members = ("clusters", "aggregation", "budget", "weights")
    if what in needs_members and scenario.feedback.cluster_recording:
        # these need each cluster's belief: a fused-only recording cannot serve them
        scenario = scenario.replace("feedback", recording=scenario.feedback.cluster_recording)
    if what == "clusters":
        jobs = [(Variant.finetune(f"cluster:{c}"), scenario) for c in scenario.feedback.clusters]
        jobs.append((Variant.finetune("moral"), scenario))
        jobs.append((Variant.finetune("amuled"), scenario))
    elif what == "aggregation":
        jobs = [(Variant.finetune(f"agg:{rule}"), scenario) for rule in AGGREGATIONS]
        jobs.append((Variant.finetune("amuled"), scenario))
    elif what == "weights":
        fixed = scenario.replace("feedback", weights="")
        jobs = [
            (Variant.finetune("amuled"), fixed),
            (Variant.finetune("amuled", label=LEARNED_WEIGHTS_LABEL), scenario),
        ]
    elif what == "kl":
        jobs = [
            (
                Variant.finetune("amuled", label=f"amuled-kl{lam:g}"),
                scenario.replace("finetune", lambda_kl=lam),
            )
            for lam in KL_SWEEP
        ]
    elif what == "budget":
        full = scenario.replace("feedback", **{"distill.enabled": False})
        jobs = []
        for budget in BUDGET_SWEEP:
            for selection in BUDGET_SELECTIONS[: 1 if budget == 1.0 else None]:
                label = f"amuled-budget{budget:g}" + ("" if budget == 1.0 else f"-{selection}")
                sc = scenario.replace(
                    "feedback",
                    **{"distill.enabled": True, "distill.budget": budget,
                       "distill.selection": selection},
                )  # fmt: skip
                jobs.append((Variant.finetune("amuled", label=label), sc))
        jobs.append((Variant.finetune("amuled"), full))
    elif what == "models":
        jobs = []
        if scenario.feedback.source == "replay":
            rec = scenario.recording_path()
            task = scenario.task.name
            for path in sorted(rec.parent.glob(f"{task}-*.json")):
                model = path.stem[len(task) + 1 :]
                sc = scenario.replace("feedback", recording=str(path), model=model)
                jobs.append((Variant.finetune("amuled", label=f"amuled-{model}"), sc))
        else:
            label = f"amuled-{scenario.feedback.model}"
            jobs.append((Variant.finetune("amuled", label=label), scenario))
        if not jobs:
            raise AmuledError(f"no recordings for task {scenario.task.name!r} next to {rec}")
    else:
        raise ScenarioError(f"unknown ablation {what!r}; expected one of {', '.join(ABLATIONS)}")
    return jobs


def _task_has_human_feedback(task: str) -> bool:
    """``BatchedTask.human_feedback`` of a task that is not the paper's (imports its class)."""
    from amuled_ma.tasks import get_task

    return get_task(task).human_feedback


def plan_run(
    scenario: Scenario,
    run_dir: Path,
    seeds: Sequence[int],
    *,
    resume: bool = False,
    force: bool = False,
    base: Path | None = None,
) -> list[TrainJob]:
    """The jobs of ``amuled run``: :data:`MAIN_VARIANTS` for every seed.

    The ``human`` fine-tune is planned only for a task with synthetic human feedback
    (``BatchedTask.human_feedback``: the paper's two tasks). Each seed's fine-tunes need
    (and anchor to) that seed's base policy, or, with ``base``
    (a finished variant folder such as the authors' imported ``runs/authors/findmilk/base``),
    all anchor to that one.
    """
    from amuled_ma.tasks.names import TASK_NAMES

    # the paper's tasks have it, known by name so a refused run imports no torch; another
    # task's class says (importing it)
    human = scenario.task.name in TASK_NAMES or _task_has_human_feedback(scenario.task.name)
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
    """The plan with ``names`` retrained from scratch and every other job resumed.

    ``amuled run/ablate --retrain NAME``: the one command that retrains a variant whose
    settings changed and rewrites the report, while the run's other variants are kept
    (resumed, or skipped where finished). A job that needs a retrained one (a fine-tune of
    a retrained base) is retrained too: its anchor changed.

    Args:
        jobs: The planned jobs.
        names: Job names (``finetune-amuled``, ``ablate-clusters/finetune-care``,
            ``base.seed43``) or variant folder names (``finetune-care``).

    Returns:
        The jobs with ``force`` / ``resume`` set per job.

    Raises:
        AmuledError: A name that is no job of the plan; the message lists the plan's jobs.

    """
    import dataclasses

    if not names:
        return list(jobs)
    chosen = set()
    for name in names:
        hits = {job.name for job in jobs if name in (job.name, job.out_dir.name)}
        if not hits:
            known = ", ".join(job.name for job in jobs)
            raise AmuledError(f"--retrain {name}: not a variant of this run; its variants: {known}")
        chosen |= hits
    grew = True
    while grew:  # a job that needs a retrained one is retrained too
        more = {job.name for job in jobs if chosen.intersection(job.needs)} - chosen
        chosen |= more
        grew = bool(more)
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
    """The jobs of ``amuled ablate --what WHAT``: each seed's base, then its fine-tunes.

    A seed's base is trained only when its folder lacks a finished checkpoint (it is shared
    with ``amuled run``); the fine-tunes go to ``<run_dir>/ablate-<what>/``, except a
    fine-tune that ``amuled run`` already finished with exactly the same settings (its
    AMULED fine-tune, :func:`finished_with`): that job points at the run's folder and is
    skipped, so the same policy is not trained twice.
    """
    run_dir = Path(run_dir)
    out = run_dir / f"ablate-{what}"
    variants = ablation_variants(what, scenario)
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
            if _finished_in_run(job, run_dir / replica):
                job = dataclasses.replace(
                    job, name=replica, out_dir=run_dir / replica, resume=True, force=False
                )
            jobs.append(job)
    return jobs


def _finished_in_run(job: TrainJob, trained: Path) -> bool:
    """Whether the run's folder ``trained`` finished ``job`` with exactly its settings."""
    assert job.variant.feedback is not None
    try:
        panel = plan_panel(job.variant.feedback, job.scenario)
    except AmuledError:
        return False  # plan_jobs names the problem
    settings = training_config(job.scenario, job.variant, panel=panel, seed=job.seed)
    return finished_with(trained, settings)
