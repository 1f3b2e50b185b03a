"""Experiments: the paper's pipeline and ablations, as resumable jobs over a run directory.

A run directory holds one folder per trained variant::

    runs/findmilk/
      config.json                 the fully resolved scenario and the command
      base/ shaped/               base training (c = 0, c = 1)
      finetune-human/ finetune-amuled/
      ablate-clusters/finetune-cluster-care/ ...   ablations (anchored to ../base)
      results.json results.csv report.md *.png

Each variant folder holds ``model_last.pt`` (rsl-rl checkpoint; ``infos["completed"]``
tells whether it finished), ``config.json`` (the resolved scenario it was trained with and,
under ``"training"``, the settings that decide what it learns: a resume or a skip checks
them against the current ones), ``train_cfg.json`` (the rsl-rl config as given, before
rsl-rl mutates its copy), ``curve.json``, TensorBoard events under ``tb/`` and, for
fine-tunes, ``feedback.json`` (fused-belief diagnostics).
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
import sys
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from amuled_ma.errors import AmuledError, CheckpointError, ScenarioError
from amuled_ma.learn.checkpoints import checkpoint_infos
from amuled_ma.learn.feedback import (
    MORAL_AGENT,
    make_feedback,
    panel_of,
    parse_variant,
    with_cluster_sources,
)
from amuled_ma.learn.jobs import TrainJob
from amuled_ma.learn.trainer import LAST, Trainer, TrainOutcome
from amuled_ma.scenario import Scenario

#: The variants of the paper's main figure, in order.
MAIN_VARIANTS = ("base", "shaped", "finetune:human", "finetune:amuled")
#: What ``amuled ablate --what`` accepts.
ABLATIONS = ("clusters", "aggregation", "models", "kl")
#: The lambda_KL sweep of the ``kl`` ablation (the paper's value is 2.5).
KL_SWEEP = (0.0, 0.5, 1.0, 2.5, 5.0, 10.0)


#: A seed replica's folder: ``<variant folder>.seed<k>`` (the first seed keeps the plain name).
_REPLICA = re.compile(r"^(?P<folder>.+)\.seed(?P<seed>\d+)$")


def training_seeds(scenario: Scenario, seed: int | None = None, count: int = 1) -> list[int]:
    """The training seeds of a run: ``count`` consecutive seeds from ``seed`` or ``[task].seed``.

    Raises:
        AmuledError: ``count`` is below 1.

    """
    if count < 1:
        raise AmuledError(f"--seeds must be at least 1, got {count}")
    first = scenario.task.seed if seed is None else seed
    return [first + k for k in range(count)]


def replica_folder(folder: str, seed: int, first_seed: int) -> str:
    """Folder of one seed replica: the plain name for the first seed, else ``.seed<k>`` added."""
    return folder if seed == first_seed else f"{folder}.seed{seed}"


def split_replica(folder: str) -> tuple[str, int | None]:
    """``finetune-amuled.seed3`` -> ``("finetune-amuled", 3)``; a plain name -> ``(name, None)``."""
    match = _REPLICA.match(folder)
    if match is None:
        return folder, None
    return match["folder"], int(match["seed"])


def default_run_dir(scenario: Scenario) -> Path:
    """``<output.runs_dir>/<scenario name>``, relative to the current directory.

    The name is a single safe path component, so the run stays inside ``runs_dir``
    (:meth:`~amuled_ma.scenario.Scenario.default_run_dir`).
    """
    return scenario.default_run_dir()


def variant_dir_name(variant: str) -> str:
    """Folder name of a variant (``finetune:cluster:care`` -> ``finetune-cluster-care``)."""
    return variant.replace(":", "-").replace(" ", "_").replace("/", "_")


def checkpoint_state(path: Path) -> dict[str, Any] | None:
    """Return a checkpoint's ``infos`` (None when there is no checkpoint)."""
    return checkpoint_infos(path)


@dataclass
class JobResult:
    """One trained (or skipped) variant.

    Attributes:
        variant: The variant name.
        out_dir: Its folder.
        skipped: True when a completed checkpoint was already there.
        outcome: The training outcome (None when skipped).

    """

    variant: str
    out_dir: Path
    skipped: bool = False
    outcome: TrainOutcome | None = None


#: Scenario keys left out of :func:`training_config`: paths, logging and service keys, the
#: seed (the job's own seed is kept) and the run's length (kept as ``"iterations"``: a
#: resume may lengthen a run).
_NOT_LEARNED = {
    "task": ("seed",),
    "base": ("save_interval", "total_steps"),
    "finetune": ("save_interval", "iterations"),
    "feedback": ("host", "concurrency", "timeout_s", "store", "max_abstention", "name"),
}


def training_config(
    scenario: Scenario, variant: str, seed: int | None = None, iterations: int | None = None
) -> dict[str, Any]:
    """The settings that decide what a variant learns, as plain JSON data.

    A folder's saved copy (``config.json``, key ``"training"``) is compared with the current
    one before a resume or a skip, so that a run never continues, or passes off as
    finished, a variant trained with other settings. Left out: paths, logging and service
    keys (:data:`_NOT_LEARNED`), the recording's folder (its file name stays), and the
    feedback section for base training and for the rule-based human feedback. The run's
    length is kept apart, as the number of PPO iterations the job trains to.

    Args:
        scenario: The scenario of the job.
        variant: ``base``, ``shaped`` or ``finetune:<feedback>``.
        seed: The job's training seed (default: ``[task].seed``).
        iterations: An override of the number of iterations, if any.

    Returns:
        ``{"variant", "seed", "iterations", section: {key: value}, ...}``.

    """
    data = scenario.to_dict()
    if variant in ("base", "shaped"):
        sections: tuple[str, ...] = ("task", "ppo", "base")
        base = scenario.base
        total = max(1, base.total_steps // (base.num_envs * base.num_steps_per_env))
    else:
        sections = ("task", "ppo", "finetune")
        if not variant.startswith("finetune:human"):
            sections += ("feedback",)
        total = scenario.finetune.iterations
    out: dict[str, Any] = {
        "variant": variant,
        "seed": scenario.task.seed if seed is None else seed,
        "iterations": total if iterations is None else iterations,
    }
    for section in sections:
        skip = _NOT_LEARNED.get(section, ())
        out[section] = {k: v for k, v in data[section].items() if k not in skip}
    if out.get("feedback", {}).get("recording"):
        out["feedback"]["recording"] = Path(out["feedback"]["recording"]).name
        if out["feedback"].get("source") == "replay":
            out["inputs"] = {"recording_sha256": _file_sha256(scenario.recording_path())}
    for agent, spec in sorted((out.get("feedback", {}).get("agents") or {}).items()):
        if spec.get("source") == "replay" and spec.get("recording"):
            path = scenario.replace("feedback", recording=spec["recording"]).recording_path()
            out.setdefault("inputs", {})[f"recording_sha256[{agent}]"] = _file_sha256(path)
    return json.loads(json.dumps(out, default=str))


@functools.lru_cache(maxsize=64)
def _sha256_of(path: str, size: int, mtime_ns: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _file_sha256(path: Path) -> str | None:
    """SHA-256 of a file's content (memoised while its size and mtime stay), None if absent.

    The identity of an input such as a recording: a file replaced under the same name has
    another hash, and a resume compares it (:func:`check_training_config`).
    """
    try:
        info = path.stat()
    except OSError:
        return None
    return _sha256_of(str(path), info.st_size, info.st_mtime_ns)


def _differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    """``key: saved -> current`` for every leaf that differs between two JSON values."""
    if isinstance(saved, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(saved) | set(current), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            out += _differences(saved.get(key), current.get(key), name)
        return out
    return [] if saved == current else [f"{prefix}: {saved!r} -> {current!r}"]


def saved_training_config(out_dir: Path) -> dict[str, Any] | None:
    """The ``"training"`` settings a variant folder's ``config.json`` recorded, if any.

    Returns:
        The settings, or None for a folder without them (none trained yet, or written
        before settings were recorded).

    Raises:
        AmuledError: ``config.json`` exists but cannot be read as JSON.

    """
    path = Path(out_dir) / "config.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise AmuledError(f"{path}: not a readable config ({err}); retrain with --force") from err
    return data.get("training") if isinstance(data, dict) else None


def check_training_config(out_dir: Path, training: dict[str, Any]) -> None:
    """Refuse to resume or skip a variant trained with other settings.

    Args:
        out_dir: The variant folder (its ``config.json`` holds the saved settings; a folder
            without one, from an older version, is accepted).
        training: The current :func:`training_config`.

    Raises:
        AmuledError: The settings differ; the message lists each differing key with its
            saved and current value and names ``--force`` and ``--run-dir``.

    """
    saved = saved_training_config(out_dir)
    if saved is None:
        return
    saved = _learned_only(saved)
    training = _without_keys_added_since(saved, training)
    diffs = _differences(
        {k: v for k, v in saved.items() if k != "iterations"},
        {k: v for k, v in training.items() if k != "iterations"},
    )
    if diffs:
        shown = "; ".join(diffs[:8]) + (f"; and {len(diffs) - 8} more" if len(diffs) > 8 else "")
        raise AmuledError(
            f"{out_dir} was trained with other settings or inputs than now (saved -> now: {shown}; "
            f"saved in {Path(out_dir) / 'config.json'}); retrain it with --force, or keep it "
            "and train into another --run-dir"
        )


def _learned_only(saved: dict[str, Any]) -> dict[str, Any]:
    """A saved training config without the keys :data:`_NOT_LEARNED` now leaves out.

    A folder saved when such a key was still recorded (a service key like
    ``max_abstention``) is compared on what decides learning only.
    """
    out = dict(saved)
    for section, keys in _NOT_LEARNED.items():
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k not in keys}
    return out


def _without_keys_added_since(saved: dict[str, Any], training: dict[str, Any]) -> dict[str, Any]:
    """Drop from ``training`` what a folder saved by an older version could not record.

    The input hashes (``inputs``) and any scenario key added since, when it holds its
    default value (the old version behaved as that default); a key added since but set
    to another value stays, so the difference is reported.
    """
    defaults = Scenario().to_dict()
    out = {k: v for k, v in training.items() if k != "inputs" or "inputs" in saved}
    for section, values in training.items():
        if isinstance(values, dict) and isinstance(saved.get(section), dict):
            out[section] = {
                k: v
                for k, v in values.items()
                if k in saved[section] or v != defaults.get(section, {}).get(k, object())
            }
    return out


def finished_with(out_dir: Path, training: dict[str, Any]) -> bool:
    """Whether a folder holds a finished checkpoint trained with exactly ``training``.

    Args:
        out_dir: A variant folder.
        training: A :func:`training_config` (its number of iterations included).

    Returns:
        True when ``model_last.pt`` is finished and ``config.json`` records the same
        settings; False otherwise (also for folders written before settings were recorded).

    """
    state = checkpoint_state(Path(out_dir) / LAST)
    if not (state and state.get("completed")):
        return False
    try:
        saved = saved_training_config(out_dir)
    except AmuledError:
        return False
    return (
        saved is not None
        and _learned_only(saved) == training
        and state.get("iteration") == training["iterations"]
    )


def prepare_variant(
    out_dir: Path,
    *,
    resume: bool,
    force: bool,
    hint: str,
    training: dict[str, Any],
) -> str:
    """Decide what to do with a variant folder: ``new``, ``resume`` or ``skip``.

    Args:
        out_dir: The variant folder.
        resume: Continue an unfinished checkpoint, skip a finished one.
        force: Start over.
        hint: The command that re-runs the job (for the error message).
        training: The job's :func:`training_config`; a resume or a skip requires the
            folder's saved settings to match it, and a finished checkpoint is skipped only
            when it trained to the job's number of iterations (fewer: it is resumed to
            that number).

    Raises:
        AmuledError: It holds a checkpoint and neither ``resume`` nor ``force`` is set (the
            message names both options), or ``resume`` is set and the checkpoint was
            trained with other settings or past the job's number of iterations.

    """
    state = checkpoint_state(Path(out_dir) / LAST)
    if state is None:
        return "new"
    if force:
        return "new"
    if resume:
        done = state.get("iteration") or 0
        check_training_config(out_dir, training)
        target = training["iterations"]
        if done > target:
            raise AmuledError(
                f"{out_dir} holds a checkpoint at iteration {done}, past the {target} "
                "iterations asked for now; retrain it with --force, or ask for at least "
                f"{done} iterations"
            )
        if state.get("completed") and done == target:
            return "skip"
        return "resume"
    raise AmuledError(
        f"{out_dir} already holds a checkpoint (iteration {state.get('iteration')}/"
        f"{state.get('total_iterations')}); continue it with '{hint} --resume' or start over "
        "with --force"
    )


def check_inputs(
    scenario: Scenario,
    variant: str,
    run_dir: Path,
    base_variant: str = "base",
    planned: Collection[str] = (),
) -> None:
    """Check, before anything trains, every input a job needs, naming what is missing.

    A fine-tune needs a known feedback variant whose agents are known clusters (shipped
    or in ``[feedback].clusters_dirs``), its recording (for the replay source,
    found by :meth:`~amuled_ma.scenario.Scenario.recording_path`) and a finished base
    checkpoint, unless the base is trained earlier in the same plan (``planned``).

    Raises:
        AmuledError: The first missing input, with the command or setting that fixes it.

    """
    if not variant.startswith("finetune"):
        return
    feedback = variant.split(":", 1)[1] if ":" in variant else ""
    kind, _ = parse_variant(feedback)
    if kind != "human":
        agents, _ = panel_of(feedback, scenario)  # every agent is a known cluster
        scenario = with_cluster_sources(scenario, agents)
        if scenario.feedback.agents:
            from amuled_ma.beliefs.routing import preflight

            preflight(scenario, agents)  # every agent's own source answers
        elif scenario.feedback.source == "replay":
            scenario.recording_path(required=True)
    if base_variant not in planned:
        base_checkpoint(run_dir, scenario, base_variant)


def base_checkpoint(run_dir: Path, scenario: Scenario, base_variant: str = "base") -> Path:
    """Return the completed base checkpoint a fine-tune is anchored to.

    Raises:
        CheckpointError: Missing or unfinished, naming the command that makes it.

    """
    path = Path(run_dir) / base_variant / LAST
    state = checkpoint_state(path)
    make = (
        f"amuled train {scenario.path or scenario.name} --variant {base_variant} "
        f"--run-dir {run_dir}"
    )
    if state is None:
        raise CheckpointError(f"no base checkpoint at {path}; make one with: {make}")
    if not state.get("completed"):
        raise CheckpointError(
            f"the base checkpoint {path} is unfinished (iteration {state.get('iteration')}/"
            f"{state.get('total_iterations')}); finish it with: {make} --resume"
        )
    return path


def train_variant(
    scenario: Scenario,
    run_dir: Path,
    variant: str,
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
        on_iteration: Called as ``fn(trainer, iteration)`` after every iteration.
        task_factory: Replaces the task constructor (tests).
        feedback_factory: ``variant -> Feedback``, replaces :func:`make_feedback` (tests).

    Returns:
        The job result.

    """
    run_dir = Path(run_dir)
    out = Path(out_dir) if out_dir else run_dir / variant_dir_name(variant)
    check_inputs(scenario, variant, Path(base_dir or run_dir), base_variant)
    training = training_config(scenario, variant, seed, iterations)
    action = prepare_variant(out, resume=resume, force=force, hint=hint, training=training)
    if action == "skip":
        return JobResult(variant, out, skipped=True)
    feedback = None
    base_ckpt = None
    if variant.startswith("finetune"):
        fb_name = variant.split(":", 1)[1] if ":" in variant else ""
        parse_variant(fb_name)
        base_ckpt = base_checkpoint(base_dir or run_dir, scenario, base_variant)
        feedback = (feedback_factory or (lambda v: make_feedback(v, scenario, run_dir)))(fb_name)
    elif variant not in ("base", "shaped"):
        raise ScenarioError(
            f"unknown variant {variant!r}; expected base, shaped or finetune:<feedback>"
        )
    if action == "new" or not (out / "config.json").is_file():
        extra: dict[str, Any] = {"variant": variant, "training": training}
        if base_ckpt is not None:
            extra["base_checkpoint"] = str(base_ckpt)
        write_config(out, scenario, extra)
    try:
        trainer = Trainer(
            scenario,
            out,
            variant=variant,
            feedback=feedback,
            base_checkpoint=base_ckpt,
            resume=action == "resume",
            seed=seed,
            iterations=iterations,
            progress=progress,
            resume_hint=f"{hint} --resume" if hint else None,
            on_iteration=on_iteration,
            task_factory=task_factory,
        )
        outcome = trainer.train()
    finally:
        if feedback is not None:
            feedback.close()
    return JobResult(variant, out, outcome=outcome)


def write_config(run_dir: Path, scenario: Scenario, extra: dict[str, Any] | None = None) -> Path:
    """Write ``config.json``: the fully resolved scenario, the command line and extras."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "config.json"
    data = {
        "scenario": scenario.to_dict(),
        "command": sys.argv,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "torch": torch.__version__,
    }
    try:
        from importlib.metadata import version

        import rsl_rl  # noqa: F401

        data["rsl_rl"] = version("rsl-rl-lib")
    except Exception:  # pragma: no cover - metadata missing
        pass
    data.update(extra or {})
    path.write_text(json.dumps(data, indent=2, default=str))
    return path


def ablation_variants(what: str, scenario: Scenario) -> list[tuple[str, Scenario, str]]:
    """List the fine-tunes of one ablation: ``(feedback variant, scenario, folder name)``.

    Args:
        what: ``clusters``, ``aggregation``, ``models`` or ``kl``.
        scenario: The base scenario.

    Returns:
        The jobs, each with the (possibly modified) scenario it runs on.

    """
    if what in ("clusters", "aggregation") and scenario.feedback.cluster_recording:
        # these need each cluster's belief: a fused-only recording cannot serve them
        scenario = scenario.replace("feedback", recording=scenario.feedback.cluster_recording)
    if what == "clusters":
        jobs = [(f"cluster:{c}", scenario, "") for c in scenario.feedback.clusters]
        jobs.append(("moral", scenario, ""))
        jobs.append(("amuled", scenario, ""))
    elif what == "aggregation":
        jobs = [(f"agg:{rule}", scenario, "") for rule in ("mean", "max", "vote")]
        jobs.append(("amuled", scenario, ""))
    elif what == "kl":
        jobs = [
            ("amuled", scenario.replace("finetune", lambda_kl=lam), f"finetune-amuled-kl{lam:g}")
            for lam in KL_SWEEP
        ]
    elif what == "models":
        jobs = []
        if scenario.feedback.source == "replay":
            rec = scenario.recording_path()
            task = scenario.task.name
            for path in sorted(rec.parent.glob(f"{task}-*.json")):
                model = path.stem[len(task) + 1 :]
                sc = scenario.replace("feedback", recording=str(path), model=model)
                jobs.append(("amuled", sc, f"finetune-amuled-{model}"))
        else:
            jobs.append(("amuled", scenario, f"finetune-amuled-{scenario.feedback.model}"))
        if not jobs:
            raise AmuledError(f"no recordings for task {scenario.task.name!r} next to {rec}")
    else:
        raise ScenarioError(f"unknown ablation {what!r}; expected one of {', '.join(ABLATIONS)}")
    return [(v, sc, name or variant_dir_name(f"finetune:{v}")) for v, sc, name in jobs]


def cluster_names(variants: Sequence[str]) -> list[str]:
    """Return the clusters named by ``cluster:<name>`` variants (and the moral agent)."""
    out = []
    for v in variants:
        kind, arg = parse_variant(v)
        if kind == "cluster" and arg:
            out.append(arg)
        elif kind == "moral":
            out.append(MORAL_AGENT)
    return out


def _job(
    name: str, scenario: Scenario, run_dir: Path, variant: str, out_dir: Path, seed: int,
    base: str, *, resume: bool, force: bool, base_dir: Path | None = None,
) -> TrainJob:  # fmt: skip
    """A job of a plan; a fine-tune needs (and anchors to) the base folder ``base``.

    With ``base_dir`` the base is a finished folder outside the plan (nothing to wait for).
    """
    tune = variant.startswith("finetune")
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
            folder = replica_folder(variant_dir_name(variant), seed, seeds[0])
            if base is not None and variant.startswith("finetune"):
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
            _job(base, scenario, run_dir, "base", run_dir / base, seed, base,
                 resume=True, force=False)
        )  # fmt: skip
        for feedback, sc, folder in variants:
            replica = replica_folder(folder, seed, seeds[0])
            variant = f"finetune:{feedback}"
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
