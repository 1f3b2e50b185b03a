"""Experiments: the paper's pipeline and ablations, as resumable jobs over a run directory.

:func:`plan_run` and :func:`plan_ablation` list the jobs of ``amuled run`` and ``amuled
ablate`` (:class:`~amuled_ma.experiments.run_folder.TrainJob`: a fine-tune needs its seed's
base), :func:`check_inputs` checks what a job needs before anything trains, and
:func:`train_variant` trains one variant into its folder. The layout of a run directory,
and whether a variant folder is new, resumed or skipped, are in
:mod:`amuled_ma.experiments.run_folder`; :mod:`amuled_ma.experiments.jobs` runs the planned jobs.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from amuled_ma.deliberation.build import Members, build_feedback, checked_members, run_store
from amuled_ma.deliberation.plan import PanelPlan, plan_panel
from amuled_ma.errors import AmuledError, ScenarioError
from amuled_ma.experiments.run_folder import (
    JobResult,
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
from amuled_ma.scenario import Scenario
from amuled_ma.variants import AGGREGATIONS, Variant

if TYPE_CHECKING:
    from amuled_ma.beliefs.store_service import StoreService
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


def training_seeds(scenario: Scenario, seed: int | None = None, count: int = 1) -> list[int]:
    """The training seeds of a run: ``count`` consecutive seeds from ``seed`` or ``[task].seed``.

    Raises:
        AmuledError: ``count`` is below 1.

    """
    if count < 1:
        raise AmuledError(f"--seeds must be at least 1, got {count}")
    first = scenario.task.seed if seed is None else seed
    return [first + k for k in range(count)]


class CheckedInputs(NamedTuple):
    """What :func:`checked_inputs` found: a fine-tune's panel plan, its sources, its base.

    Attributes:
        plan: The feedback's panel plan (None: not a fine-tune).
        members: The panel's member sources, built and checked, open (None: no member
            source); close them, or hand them to
            :func:`~amuled_ma.deliberation.build.build_feedback`.
        base_checkpoint: The finished base checkpoint (None: not a fine-tune, or its base
            is trained earlier in the same plan).

    """

    plan: PanelPlan | None = None
    members: Members | None = None
    base_checkpoint: Path | None = None

    def close(self) -> None:
        """Close the member sources (when they were not handed to a feedback)."""
        if self.members is not None:
            self.members.close()


def check_inputs(
    scenario: Scenario,
    variant: Variant | str,
    run_dir: Path,
    base_variant: str = "base",
    planned: Collection[str] = (),
) -> None:
    """Check, before anything trains or any folder is made, every input a job needs.

    :func:`checked_inputs`, the sources it built closed again.

    Raises:
        AmuledError: As :func:`checked_inputs`.

    """
    checked_inputs(scenario, variant, run_dir, base_variant, planned).close()


def checked_inputs(
    scenario: Scenario,
    variant: Variant | str,
    run_dir: Path,
    base_variant: str = "base",
    planned: Collection[str] = (),
) -> CheckedInputs:
    """Check, before anything trains or any folder is made, every input a job needs.

    A fine-tune needs a known feedback variant whose agents are known clusters (shipped
    or in ``[feedback].clusters_dirs``), a panel whose every member can answer (the
    preflight of its plan, :func:`amuled_ma.deliberation.build.preflight`: a replayed
    recording found, of the task, holding each member it serves and, with
    ``[feedback.distill]``, per-cluster beliefs; an Ollama server that answers with the
    model; a plug-in that loads; a policy file) and a finished base checkpoint, unless the
    base is trained earlier in the same plan (``planned``). Nothing is written.

    Returns:
        The plan, the member sources the preflight built (open: the job's feedback is
        built from them, :func:`train_variant`) and the base checkpoint.

    Raises:
        AmuledError: The first missing input, in one line naming the member and the ways
            to give it beliefs, or the command or setting that fixes it; nothing is left
            open.

    """
    variant = Variant.parse(variant)
    if not variant.finetuning:
        return CheckedInputs()
    assert variant.feedback is not None
    plan = plan_panel(variant.feedback, scenario)
    members = checked_members(plan)
    checked = CheckedInputs(plan, members)
    if base_variant not in planned:
        try:
            base = base_checkpoint(run_dir, scenario, base_variant)
        except BaseException:
            checked.close()
            raise
        checked = checked._replace(base_checkpoint=base)
    return checked


@dataclass
class PreparedJob:
    """A job ready to train: its folder written, its feedback built (:func:`prepare_job`).

    Attributes:
        variant: What it trains.
        out_dir: Its folder (its ``config.json`` written).
        action: ``"new"`` or ``"resume"``.
        feedback: A fine-tune's feedback (open: :meth:`close` it), else None.
        base_checkpoint: A fine-tune's base policy.
        trainer_kwargs: The other fields of its
            :class:`~amuled_ma.learn.population_groups.MemberSpec` (``seed``,
            ``iterations``, ``resume_hint``, ``task_factory``).

    """

    variant: Variant
    out_dir: Path
    action: str
    feedback: Any
    base_checkpoint: Path | None
    trainer_kwargs: dict[str, Any]

    def close(self) -> None:
        """Close the feedback (its sources and store connections)."""
        if self.feedback is not None:
            self.feedback.close()

    def finished(self, outcome: TrainOutcome) -> JobResult:
        """Record the job complete; its result."""
        mark_state(self.out_dir, "complete", outcome.iterations)
        return JobResult(self.variant, self.out_dir, outcome=outcome)

    def failed(self) -> None:
        """Record the job failed (unless the disk is full: the error says so)."""
        with contextlib.suppress(OSError):
            mark_state(self.out_dir, "failed")


def prepare_job(
    scenario: Scenario,
    run_dir: Path,
    variant: Variant | str,
    *,
    resume: bool = False,
    force: bool = False,
    hint: str = "",
    iterations: int | None = None,
    seed: int | None = None,
    out_dir: Path | None = None,
    base_dir: Path | None = None,
    base_variant: str = "base",
    task_factory: Callable[..., Any] | None = None,
    feedback_factory: Callable[[str], Any] | None = None,
    store: StoreService | None = None,
) -> PreparedJob | JobResult:
    """Check a job's inputs, decide new / resume / skip, build its feedback, write its record.

    The arguments are :func:`train_variant`'s.

    Returns:
        The prepared job, or the result of a job that is already trained (skipped).

    """
    variant = Variant.parse(variant)
    run_dir = Path(run_dir)
    out = Path(out_dir) if out_dir else run_dir / variant.folder
    # the preflight builds and checks the panel's sources once; the feedback is built of them
    checked = checked_inputs(scenario, variant, Path(base_dir or run_dir), base_variant)
    try:
        training = training_config(scenario, variant, seed, iterations)
        action = prepare_variant(out, resume=resume, force=force, hint=hint, training=training)
        if action == "skip":
            return JobResult(variant, out, skipped=True)
        feedback = None
        base_ckpt = checked.base_checkpoint
        if variant.finetuning:
            assert variant.feedback is not None and checked.plan is not None
            if feedback_factory is not None:
                feedback = feedback_factory(variant.feedback)
            else:
                plan, members = checked.plan, checked.members
                checked = checked._replace(members=None)
                feedback = build_feedback(
                    plan,
                    store if store is not None else run_store(scenario, run_dir),
                    members=members,  # handed over: the feedback closes them
                    state_dir=out,
                    resume=action == "resume",
                    seed=seed,
                    cache_dir=run_dir,
                )
    finally:
        checked.close()
    try:
        if action == "new" or not (out / "config.json").is_file():
            fields = variant_fields(
                variant, out, training, base_checkpoint=base_ckpt, feedback=feedback
            )
            write_config(out, scenario, fields)
    except BaseException:
        if feedback is not None:
            feedback.close()
        raise
    return PreparedJob(
        variant,
        out,
        action,
        feedback,
        base_ckpt,
        {
            "seed": seed,
            "iterations": iterations,
            "resume_hint": f"{hint} --resume" if hint else None,
            "task_factory": task_factory,
        },
    )


def train_variant(
    scenario: Scenario,
    run_dir: Path,
    variant: Variant | str,
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
    feedback_factory: Callable[[str], Any] | None = None,
    store: StoreService | None = None,
) -> JobResult:
    """Train one variant (``base``, ``shaped`` or ``finetune:<feedback>``) into the run.

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
            checked plan (tests).
        store: The belief store of the fine-tune's panel (default: the run's file,
            ``[feedback].store``, opened on first use,
            :func:`~amuled_ma.deliberation.build.run_store`).

    Returns:
        The job result.

    """
    prepared = prepare_job(
        scenario,
        run_dir,
        variant,
        resume=resume,
        force=force,
        hint=hint,
        iterations=iterations,
        seed=seed,
        out_dir=out_dir,
        base_dir=base_dir,
        base_variant=base_variant,
        task_factory=task_factory,
        feedback_factory=feedback_factory,
        store=store,
    )
    if isinstance(prepared, JobResult):
        return prepared
    return train_prepared(scenario, prepared, progress=progress, on_iteration=on_iteration)


def train_prepared(
    scenario: Scenario,
    prepared: PreparedJob,
    *,
    progress: bool = False,
    on_iteration: Callable[[Any, int], None] | None = None,
) -> JobResult:
    """Train a job :func:`prepare_job` prepared, alone; record it complete or failed.

    A job alone is a population of one (:class:`~amuled_ma.learn.population.
    PopulationTrainer`): the one training loop of every job.

    Args:
        scenario: The job's scenario.
        prepared: The prepared job (closed here).
        progress: Show a progress bar.
        on_iteration: Called as ``fn(member, iteration)`` after every iteration
            (:class:`~amuled_ma.learn.population.PopulationMember`).

    Returns:
        The job result.

    Raises:
        MemberFailed: Its feedback failed or its gradient was not finite (its checkpoint
            before that iteration is written).

    """
    # after the checks: torch and rsl-rl load here, so that a refused job answers fast
    from amuled_ma.learn.population import PopulationTrainer

    try:
        member = member_of(scenario, prepared, on_iteration)
        outcome = PopulationTrainer([member], progress=progress).train()[0]
        return prepared.finished(outcome)
    except Exception:
        # not an interruption: the record says so
        prepared.failed()
        raise
    finally:
        prepared.close()


def member_of(
    scenario: Scenario,
    prepared: PreparedJob,
    on_iteration: Callable[[Any, int], None] | None = None,
) -> MemberSpec:
    """The population member that trains a prepared job (its feedback, base, resume)."""
    from amuled_ma.learn.population_groups import MemberSpec  # here: it imports torch

    return MemberSpec(
        scenario,
        prepared.out_dir,
        variant=prepared.variant,
        feedback=prepared.feedback,
        base_checkpoint=prepared.base_checkpoint,
        resume=prepared.action == "resume",
        on_iteration=on_iteration,
        **prepared.trainer_kwargs,
    )


def prepare_planned_job(
    job: TrainJob, *, hint: str, store: StoreService | None = None
) -> PreparedJob | JobResult:
    """:func:`prepare_job` with a planned job's own settings (alone or in a population).

    Args:
        job: The job (its scenario, run and variant folders, seed, base, resume / force).
        hint: The command that re-runs this job (for messages and Ctrl-C).
        store: The belief store of the fine-tune's panel (default: the run's file).

    Returns:
        The prepared job, or the result of a job that is already trained (skipped).

    """
    return prepare_job(
        job.scenario,
        job.run_dir,
        job.variant,
        resume=job.resume,
        force=job.force,
        hint=hint,
        seed=job.seed,
        out_dir=job.out_dir,
        base_dir=job.base_dir,
        base_variant=job.base_variant,
        store=store,
    )


def train_one_job(
    job: TrainJob,
    *,
    progress: bool,
    hint: str,
    on_iteration: Callable[[Any, int], None] | None = None,
    store: StoreService | None = None,
) -> JobResult:
    """Train one planned job alone: :func:`train_variant` with the job's own settings.

    Args:
        job: The job (its scenario, run and variant folders, seed, base, resume / force).
        progress: Show a progress bar.
        hint: The command that re-runs this job (for messages and Ctrl-C).
        on_iteration: Called as ``fn(member, iteration)`` after every iteration.
        store: The belief store of the fine-tune's panel (default: the run's file).

    Returns:
        The job result.

    """
    prepared = prepare_planned_job(job, hint=hint, store=store)
    if isinstance(prepared, JobResult):
        return prepared
    return train_prepared(job.scenario, prepared, progress=progress, on_iteration=on_iteration)


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


def _job(
    name: str, scenario: Scenario, run_dir: Path, variant: Variant, out_dir: Path, seed: int,
    base: str, *, resume: bool, force: bool, base_dir: Path | None = None,
) -> TrainJob:  # fmt: skip
    """A job of a plan; a fine-tune needs (and anchors to) the base folder ``base``.

    With ``base_dir`` the base is a finished folder outside the plan (nothing to wait for).
    """
    tune = variant.finetuning
    if base_dir is not None:
        return TrainJob(
            name=name, scenario=scenario, run_dir=run_dir, variant=variant, out_dir=out_dir,
            seed=seed, base_variant=base, resume=resume, force=force, base_dir=base_dir,
        )  # fmt: skip
    return TrainJob(
        name=name,
        scenario=scenario,
        run_dir=run_dir,
        variant=variant,
        out_dir=out_dir,
        seed=seed,
        base_variant=base,
        needs=(base,) if tune else (),
        resume=resume,
        force=force,
    )


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

    Each seed's fine-tunes need (and anchor to) that seed's base policy, or, with ``base``
    (a finished variant folder such as the authors' imported ``runs/authors/findmilk/base``),
    all anchor to that one.
    """
    run_dir = Path(run_dir)
    jobs = []
    for seed in seeds:
        own = replica_folder("base", seed, seeds[0])
        for variant in MAIN_VARIANTS:
            folder = replica_folder(variant.folder, seed, seeds[0])
            if base is not None and variant.finetuning:
                jobs.append(
                    _job(folder, scenario, run_dir, variant, run_dir / folder, seed, base.name,
                         resume=resume, force=force, base_dir=base.parent)
                )  # fmt: skip
                continue
            jobs.append(
                _job(folder, scenario, run_dir, variant, run_dir / folder, seed, own,
                     resume=resume, force=force)
            )  # fmt: skip
    return jobs


def check_jobs(jobs: Sequence[TrainJob], hint: str = "") -> dict[str, str]:
    """Check every planned job before anything is made or trained, and decide its start.

    Each job's inputs go through :func:`check_inputs` (its feedback agents, recording or
    sources, and a finished base unless the plan trains it), then its folder through
    :func:`~amuled_ma.experiments.run_folder.prepare_variant` (new, resume or skip; a
    checkpoint without ``--resume``/``--force``, or trained with other settings, is
    refused). Nothing is written, no folder is made.

    Args:
        jobs: The planned graph.
        hint: The command that re-runs the graph (named in a refusal).

    Returns:
        ``{job name: "new" | "resume" | "skip"}``.

    Raises:
        AmuledError: One problem as it was raised; several as one message listing each
            distinct problem once (``N of M jobs cannot start, nothing was trained``).

    """
    planned = {job.out_dir.name for job in jobs}
    actions: dict[str, str] = {}
    problems: list[str] = []
    failing = 0
    for job in jobs:
        try:
            check_inputs(job.scenario, job.variant, job.base_dir or job.run_dir,
                         job.base_variant, planned)  # fmt: skip
            training = training_config(job.scenario, job.variant, job.seed)
            actions[job.name] = prepare_variant(
                job.out_dir, resume=job.resume, force=job.force, hint=hint, training=training
            )
        except AmuledError as error:
            failing += 1
            if str(error) not in problems:
                problems.append(str(error))
    if len(problems) == 1:
        raise AmuledError(problems[0])
    if problems:
        raise AmuledError(
            f"{failing} of {len(jobs)} jobs cannot start, nothing was trained:\n"
            + "\n".join(f"  - {problem}" for problem in problems)
        )
    return actions


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
            _job(base, scenario, run_dir, Variant("base"), run_dir / base, seed, base,
                 resume=True, force=False)
        )  # fmt: skip
        for variant, sc in variants:
            replica = replica_folder(variant.folder, seed, seeds[0])
            trained = run_dir / replica
            if finished_with(trained, training_config(sc, variant, seed)):
                jobs.append(_job(replica, sc, run_dir, variant, trained, seed, base,
                                 resume=True, force=False))  # fmt: skip
                continue
            jobs.append(
                _job(f"{out.name}/{replica}", sc, run_dir, variant, out / replica,
                     seed, base, resume=resume, force=force)
            )  # fmt: skip
    return jobs
