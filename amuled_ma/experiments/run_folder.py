"""The run folder: what a run directory holds, and the state of each variant folder in it.

A run directory holds one folder per trained variant::

    runs/findmilk/
      config.json                 the fully resolved scenario and the command
      base/ shaped/               base training (c = 0, c = 1)
      finetune-human/ finetune-amuled/
      base.seed1/ finetune-amuled.seed1/ ...       seed replicas (``.seed<k>``)
      ablate-clusters/finetune-cluster-care/ ...   ablations (anchored to ../base)
      results.json results.csv report.md *.png

Each variant folder holds ``model_last.pt`` (rsl-rl checkpoint; ``infos["completed"]``
tells whether it finished), ``config.json`` (the resolved scenario it was trained with and,
under ``"training"``, the settings that decide what it learns: a resume or a skip checks
them against the current ones), ``train_cfg.json`` (the rsl-rl config as given, before
rsl-rl mutates its copy), ``curve.json``, TensorBoard events under ``tb/`` and, for
fine-tunes, ``feedback.json`` (fused-belief diagnostics).

This module names the replica folders (:func:`replica_folder`,
:func:`split_replica`), records a job and its result (:class:`TrainJob`,
:class:`JobResult`), and decides what a job does with its folder: start, resume or skip
(:func:`prepare_variant`, :func:`finished_with`, :func:`base_checkpoint`; the settings
compared are :func:`~amuled_ma.experiments.training_settings.training_config`). The
planner (:mod:`amuled_ma.experiments.plans`) and the job runner
(:mod:`amuled_ma.experiments.jobs`) both build on it.
"""

from __future__ import annotations

import json
import re
import shlex
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from amuled_ma.errors import AmuledError, CheckpointError
from amuled_ma.experiments.training_settings import (
    differences,
    learned_only,
    without_keys_added_since,
)
from amuled_ma.learn.checkpoints import LAST, checkpoint_infos
from amuled_ma.records import PanelRecord, RunRecord, State
from amuled_ma.safe_files import checked_read_path, write_text_atomic
from amuled_ma.scenario import MORAL_AGENT, Scenario
from amuled_ma.variants import Variant

if TYPE_CHECKING:
    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.deliberation.plan import PanelPlan
    from amuled_ma.learn.job_shape import JobShape
    from amuled_ma.learn.population import TrainOutcome


# -- folder names -------------------------------------------------------------------
#: A seed replica's folder: ``<variant folder>.seed<k>`` (the first seed keeps the plain name).
_REPLICA = re.compile(r"^(?P<folder>.+)\.seed(?P<seed>\d+)$")


def replica_folder(folder: str, seed: int, first_seed: int) -> str:
    """Folder of one seed replica: the plain name for the first seed, else ``.seed<k>`` added."""
    return folder if seed == first_seed else f"{folder}.seed{seed}"


def split_replica(folder: str) -> tuple[str, int | None]:
    """``finetune-amuled.seed3`` -> ``("finetune-amuled", 3)``; a plain name -> ``(name, None)``."""
    match = _REPLICA.match(folder)
    if match is None:
        return folder, None
    return match["folder"], int(match["seed"])


# -- records ------------------------------------------------------------------------
#: What a job does with its folder: start it, continue its checkpoint, or keep it as it is.
Action = Literal["new", "resume", "skip"]


@dataclass(frozen=True)
class Rerun:
    """The command that re-runs a graph, as fields: ``amuled COMMAND ARGS --run-dir DIR OPTIONS``.

    Attributes:
        command: ``run``, ``ablate``, ``train`` or ``finetune``.
        args: The words before ``--run-dir`` (the scenario first).
        options: The words after it, ``--name`` aside.
        name: A fine-tune's ``--name`` (None: not given).

    """

    command: str
    args: tuple[str, ...]
    options: tuple[str, ...] = ()
    name: str | None = None

    def line(self, run_dir: Path, *more: str, name: str | None = None) -> str:
        """The shell command into ``run_dir`` (``name`` instead of :attr:`name`), ``more`` added."""
        name = name or self.name
        named = ("--name", name) if name else ()
        words = ["amuled", self.command, *self.args, "--run-dir", str(run_dir)]
        return shlex.join([*words, *self.options, *named, *more])


@dataclass(frozen=True)
class TrainJob:
    """One job of a run: what it trains and where, planned once and carried to its trainer.

    The first fields say what to train (:func:`~amuled_ma.experiments.plans.plan_run`);
    :func:`~amuled_ma.experiments.plans.plan_job` fills the planned ones (``action`` set:
    planned), and every later stage reads them instead of deriving them again.

    Attributes:
        name: Unique name of the job in its graph (shown in messages).
        scenario: The scenario it trains on.
        run_dir: The run directory (belief store, default folders).
        variant: What it trains.
        out_dir: Its folder.
        seed: Training seed (None: the scenario's).
        base_variant: Folder (under ``base_dir``) of the base checkpoint a fine-tune anchors to.
        needs: Names of the jobs that must finish first.
        resume: Continue an unfinished checkpoint; skip a finished one.
        force: Start over even where a checkpoint exists.
        base_dir: The folder holding ``base_variant`` (default: ``run_dir``), e.g. the
            authors' imported base, ``runs/authors/findmilk``.
        iterations: An override of the planned number of iterations (tests, benchmarks).
        panel: A fine-tune's panel plan (planned).
        shape: Its run shape (planned).
        settings: What decides what it learns, with the inputs' hashes (planned;
            :func:`~amuled_ma.experiments.training_settings.training_config`).
        base_checkpoint: A fine-tune's base checkpoint (planned).
        store: A fine-tune's belief store file (planned;
            :meth:`~amuled_ma.scenario.Scenario.store_path`).
        action: What it does with its folder (planned).

    """

    name: str
    scenario: Scenario
    run_dir: Path
    variant: Variant
    out_dir: Path
    seed: int | None = None
    base_variant: str = "base"
    needs: tuple[str, ...] = ()
    resume: bool = False
    force: bool = False
    base_dir: Path | None = None
    iterations: int | None = None
    panel: PanelPlan | None = None
    shape: JobShape | None = None
    settings: dict[str, Any] | None = None
    base_checkpoint: Path | None = None
    store: Path | None = None
    action: Action | None = None

    @property
    def base_folder(self) -> Path:
        """The folder of the base a fine-tune anchors to (``base_dir / base_variant``)."""
        return Path(self.base_dir or self.run_dir) / self.base_variant


@dataclass
class JobResult:
    """One trained (or skipped) variant.

    Attributes:
        variant: What was trained.
        out_dir: Its folder.
        skipped: True when a completed checkpoint was already there.
        outcome: The training outcome (None when skipped).

    """

    variant: Variant
    out_dir: Path
    skipped: bool = False
    outcome: TrainOutcome | None = None


# -- the state of a variant folder --------------------------------------------------
def checkpoint_state(path: Path) -> dict[str, Any] | None:
    """Return a checkpoint's ``infos`` (None when there is no checkpoint)."""
    return checkpoint_infos(path)


def base_checkpoint(base_folder: Path, scenario_name: str) -> Path:
    """Return the completed base checkpoint a fine-tune is anchored to.

    Args:
        base_folder: The base's variant folder.
        scenario_name: The scenario file or name, for the command that makes the base.

    Raises:
        CheckpointError: Missing or unfinished, naming the command that makes it.

    """
    path = Path(base_folder) / LAST
    state = checkpoint_state(path)
    make = (
        f"amuled train {scenario_name} --variant {Path(base_folder).name} "
        f"--run-dir {Path(base_folder).parent}"
    )
    if state is None:
        raise CheckpointError(f"no base checkpoint at {path}; make one with: {make}")
    if not state.get("completed"):
        raise CheckpointError(
            f"the base checkpoint {path} is unfinished (iteration {state.get('iteration')}/"
            f"{state.get('total_iterations')}); finish it with: {make} --resume"
        )
    return path


def saved_training_config(out_dir: Path) -> dict[str, Any] | None:
    """The ``"training"`` settings a variant folder's record (``config.json``) holds, if any.

    Returns:
        The settings, or None for a folder without them (none trained yet).

    Raises:
        AmuledError: ``config.json`` exists but is not a run record.

    """
    record = read_record(out_dir, checkpoint=False)
    return None if record is None else record.training


def training_differences(out_dir: Path, training: dict[str, Any]) -> list[str]:
    """``key: saved -> now`` for each setting a variant folder was trained with and now lacks.

    Empty when they match, or when the folder saved none (an older version's).

    Raises:
        AmuledError: ``config.json`` exists but is not a run record.

    """
    saved = saved_training_config(out_dir)
    if saved is None:
        return []
    saved = learned_only(saved)
    training = without_keys_added_since(saved, training)
    return differences(
        {k: v for k, v in saved.items() if k != "iterations"},
        {k: v for k, v in training.items() if k != "iterations"},
    )


def settings_refusal(
    job: TrainJob, diffs: list[str], rerun: Rerun | None = None, hint: str = ""
) -> str:
    """The one-line refusal of a variant folder trained with other settings than now.

    It names the differing keys (saved -> now) and the one command for each thing the
    user may have meant (:func:`recovery_commands`): train the new settings beside the
    old folder, or retrain that folder alone.

    Args:
        job: The job whose folder was trained with other settings.
        diffs: Its differences (:func:`training_differences`).
        rerun: The command that was run, as fields (None: the options are named).
        hint: That command's text (for a ``--force`` without ``rerun``).

    """
    out_dir = job.out_dir
    keys = ", ".join(d.split(":", 1)[0] for d in diffs[:8])
    keys += f" and {len(diffs) - 8} more" if len(diffs) > 8 else ""
    shown = "; ".join(diffs[:8]) + (f"; and {len(diffs) - 8} more" if len(diffs) > 8 else "")
    beside, again = recovery_commands(job, diffs, rerun, hint)
    return (
        f"{out_dir} was trained with other settings or inputs than now ({keys} differ; "
        f"saved -> now: {shown}; saved in {Path(out_dir) / 'config.json'}); to keep it and "
        f"train the new settings beside it: {beside}; to retrain this folder alone with "
        f"them: {again}"
    )


def _tag(diffs: list[str]) -> str:
    """A short folder-name tag from the first difference's new value (``ollama``)."""
    now = diffs[0].rsplit(" -> ", 1)[-1] if diffs else ""
    tag = re.sub(r"[^A-Za-z0-9]+", "-", now).strip("-").lower()[:24].strip("-")
    return tag or "new"


def recovery_commands(
    job: TrainJob, diffs: list[str], rerun: Rerun | None = None, hint: str = ""
) -> tuple[str, str]:
    """The commands that do what the user meant when a folder's settings changed.

    Args:
        job: The job whose folder was trained with other settings.
        diffs: Its differences (:func:`training_differences`).
        rerun: The command that was run, as fields (None: the options are named).
        hint: That command's text (``--force`` is added to it without ``rerun``).

    Returns:
        ``(beside, again)``: a fine-tune under a new name (``--name``; another
        ``--run-dir`` for a base or a whole run), and that variant alone retrained
        (``--force`` for ``finetune``/``train``; for ``run``/``ablate`` the same command with
        ``--retrain`` and the job's name, which resumes the other variants and rewrites the
        report).

    """
    if rerun is None:
        again = f"{hint} --force" if hint else "--force"
        return "another --run-dir (or --name NAME for a fine-tune)", again
    tag = _tag(diffs)
    if rerun.command == "finetune":
        label = split_replica(job.out_dir.name)[0].removeprefix("finetune-")
        beside = rerun.line(job.run_dir, name=f"{label}-{tag}")
        return beside, rerun.line(job.run_dir, "--force")
    beside = rerun.line(Path(f"{str(job.run_dir).rstrip('/')}-{tag}"))
    if rerun.command in ("run", "ablate"):
        # one command: this folder retrained, the others resumed, the report rewritten
        return beside, rerun.line(job.run_dir, "--retrain", job.name)
    again = rerun.line(job.run_dir, "--force")
    if rerun.command == "train":
        return beside, again
    return beside, f"{again} (retrains every variant of the run)"


def finished_with(out_dir: Path, training: dict[str, Any]) -> bool:
    """Whether a folder holds a finished checkpoint trained with exactly ``training``.

    Args:
        out_dir: A variant folder.
        training: A :func:`~amuled_ma.experiments.training_settings.training_config`
            (its number of iterations included).

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
        and learned_only(saved) == training
        and state.get("iteration") == training["iterations"]
    )


def prepare_variant(
    job: TrainJob, training: dict[str, Any], *, hint: str = "", rerun: Rerun | None = None
) -> Action:
    """Decide what a job does with its folder: ``new``, ``resume`` or ``skip``.

    Args:
        job: The job (its folder, ``resume`` and ``force``).
        training: The job's :func:`~amuled_ma.experiments.training_settings.training_config`;
            a resume or a skip requires the folder's saved settings to match it, and a
            finished checkpoint is skipped only when it trained to the job's number of
            iterations (fewer: it is resumed to that number).
        hint: The command that re-runs the job (for the error message).
        rerun: The same command as fields (the recovery commands of a refusal).

    Raises:
        AmuledError: It holds a checkpoint and neither ``resume`` nor ``force`` is set (the
            message names both options), or ``resume`` is set and the checkpoint was
            trained with other settings (:func:`settings_refusal`) or past the job's
            number of iterations.

    """
    out_dir = job.out_dir
    state = checkpoint_state(Path(out_dir) / LAST)
    if state is None or job.force:
        return "new"
    diffs = training_differences(out_dir, training)
    if diffs:  # a resume is refused, and so is a plain rerun: name what does what was meant
        raise AmuledError(settings_refusal(job, diffs, rerun, hint))
    if job.resume:
        done = state.get("iteration") or 0
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


# -- the run record (config.json) ---------------------------------------------------
#: A run's and a variant folder's record.
CONFIG = "config.json"
#: Largest ``config.json`` read [bytes]: a record holds the scenario, the panel and the
#: inputs' digests, about 6 KB (a sweep's variant folders' are alike); 4 MB is 600 times
#: that, and a record is read whole, several at a time (``view``, ``evaluate``).
MAX_RECORD_BYTES = 4_000_000


def read_record(folder: Path, *, checkpoint: bool = True) -> RunRecord | None:
    """A folder's ``config.json`` as a :class:`~amuled_ma.records.RunRecord`.

    Args:
        folder: A run directory or a variant folder.
        checkpoint: Take the iterations done and the state from the folder's checkpoint
            (``model_last.pt``: the truth of how far it trained), when it has one.

    Returns:
        The record, or None when the folder has no ``config.json``.

    Raises:
        AmuledError: ``config.json`` is not a run record, or is larger than
            :data:`MAX_RECORD_BYTES` (refused before it is read); the message names the file.
        UnsafePathError: ``config.json`` is a link or not a regular file (nothing read).

    """
    from pydantic import ValidationError

    from amuled_ma.file_limits import read_bounded_bytes

    path = checked_read_path(folder, CONFIG)
    if not path.is_file():
        return None
    try:
        raw = read_bounded_bytes(
            path,
            MAX_RECORD_BYTES,
            "run record",
            note="a record is about 6 KB",
            fix="is it the right folder? Retrain with --force, or move the folder out of the run",
        )
        record = RunRecord.model_validate_json(raw)
    except OSError as err:
        raise AmuledError(f"{path}: not a readable config ({err}); retrain with --force") from None
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "the file"
        raise AmuledError(
            f"{path}: not a readable config ({where}: {first['msg']}); retrain with --force, "
            "or move the folder out of the run"
        ) from None
    return _with_checkpoint(Path(folder), record) if checkpoint else record


def _with_checkpoint(folder: Path, record: RunRecord) -> RunRecord:
    """The record with its checkpoint's iteration and state (complete or not)."""
    infos = checkpoint_infos(folder / LAST)
    if infos is None:
        return record
    planned = infos.get("total_iterations", record.iterations_planned)  # a resume may lengthen
    if infos.get("completed"):
        state = "complete"
    else:
        state = "failed" if record.state == "failed" else "interrupted"
    return record.model_copy(
        update={
            "iterations_done": infos.get("iteration"),
            "iterations_planned": planned,
            "state": state,
        }
    )


def write_record(folder: Path, record: RunRecord) -> Path:
    """Write a folder's ``config.json`` whole or not at all, never through a link.

    Through :func:`~amuled_ma.safe_files.write_text_atomic` (a reader never sees half a
    file; a full disk leaves the old file and no temporary one).

    Raises:
        UnsafePathError: ``config.json`` is a link or not a regular file; nothing written.
        FileWriteError: The write failed (a full disk), naming the file; an ``OSError``
            too, so a job marked failed on a full disk ends with its own error.

    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(folder / CONFIG, record.to_json())


def mark_state(folder: Path, state: State, iterations: int | None = None) -> None:
    """Record a variant folder's state (and iterations done) when its training ends."""
    record = read_record(folder, checkpoint=False)
    if record is not None:
        update: dict[str, Any] = {"state": state}
        if iterations is not None:
            update["iterations_done"] = iterations
        write_record(folder, record.model_copy(update=update))


def write_config(
    run_dir: Path, scenario: Mapping[str, Any], extra: dict[str, Any] | None = None
) -> Path:
    """Write ``config.json``: the resolved scenario, the command line and the record's fields.

    Args:
        run_dir: The run directory or variant folder.
        scenario: The resolved scenario as plain data (``Scenario.to_dict``).
        extra: More fields of :class:`~amuled_ma.records.RunRecord` (``variants``,
            ``seeds``, ``training``, ``panel``, ...).

    Returns:
        The file's path.

    """
    import torch  # here: reading a run folder needs no torch

    data: dict[str, Any] = {
        "scenario": json.loads(json.dumps(dict(scenario), default=str)),
        "command": list(sys.argv),
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
    return write_record(run_dir, RunRecord.model_validate(data))


def variant_fields(
    variant: Variant,
    out_dir: Path,
    training: dict[str, Any],
    *,
    base_checkpoint: Path | None = None,
    feedback: Feedback | None = None,
) -> dict[str, Any]:
    """The record's fields of a variant folder about to train (:func:`write_config`'s extra).

    Args:
        variant: What it trains.
        out_dir: Its folder (a seed replica ``<name>.seed<k>`` is named ``<name>``).
        training: Its :func:`~amuled_ma.experiments.training_settings.training_config`.
        base_checkpoint: The base a fine-tune starts from.
        feedback: The fine-tune's feedback (a replay of fused beliefs only is said so).

    Returns:
        ``{"variant", "label", "name", "seed", "training", "iterations_planned", "state",
        "panel", "recipe", "lambda_kl", "base_checkpoint"}`` (the fine-tune keys for a
        fine-tune only).

    """
    fields: dict[str, Any] = {
        "variant": str(variant),
        "label": variant.label,
        "name": split_replica(Path(out_dir).name)[0],
        "seed": training.get("seed"),
        "training": training,
        "iterations_planned": training.get("iterations"),
        "iterations_done": 0,
        "state": "interrupted",  # until its training completes (the checkpoint says so)
    }
    if variant.finetuning:
        finetune = training.get("finetune") or {}
        fields.update(
            panel=panel_of_training(variant, training, feedback),
            recipe=finetune.get("recipe"),
            lambda_kl=finetune.get("lambda_kl"),
        )
        if base_checkpoint is not None:
            fields["base_checkpoint"] = str(base_checkpoint)
    return {k: v for k, v in fields.items() if v is not None}


def panel_of_training(
    variant: Variant, training: dict[str, Any], feedback: Feedback | None = None
) -> PanelRecord:
    """The :class:`~amuled_ma.records.PanelRecord` of a fine-tune, from its settings.

    The members and rule follow the variant (``cluster:<name>`` and ``moral``: that agent
    alone, averaged; ``agg:<rule>``: the panel with that rule); a feedback replaying a
    recording of fused beliefs only has no members and no fusion of ours.
    """
    from amuled_ma.deliberation.panel_feedback import FusedReplayFeedback

    settings = training.get("feedback") or {}
    kind, arg = variant.feedback_kind
    members, rule = list(settings.get("clusters") or []), settings.get("fusion")
    if kind == "human":
        members, rule = [], None
    elif kind == "cluster":
        members, rule = [str(arg)], "mean"
    elif kind == "moral":
        members, rule = [MORAL_AGENT], "mean"
    elif kind == "agg":
        rule = arg
    fused_only = isinstance(feedback, FusedReplayFeedback)
    if fused_only:
        members, rule = [], None
    return PanelRecord(
        feedback=str(variant.feedback),
        members=members,
        source=settings.get("source") if kind != "human" else None,
        model=settings.get("model") if kind != "human" else None,
        recording=settings.get("recording") if kind != "human" else None,
        fused_only=fused_only,
        fusion=rule,
        agent_sources=dict(settings.get("agents") or {}),
        distill=settings.get("distill"),
        weights=settings.get("weights") if kind == "amuled" and not fused_only else None,
    )


def variant_records(folders: list[Path]) -> dict[str, RunRecord]:
    """``{folder name: record}`` of the variant folders that hold one (for the evaluation)."""
    out = {}
    for folder in folders:
        record = read_record(folder)
        if record is not None:
            out[Path(folder).name] = record
    return out


def scenario_of_run(run_dir: Path) -> Scenario:
    """Rebuild the scenario a run (or a variant folder) was made with, from its record.

    Raises:
        AmuledError: The folder has no ``config.json`` with a scenario; the message names
            the commands that make a run.

    """
    from amuled_ma.scenario import scenario_from_dict

    record = read_record(Path(run_dir), checkpoint=False)
    if record is None or record.scenario is None:
        raise AmuledError(
            f"{run_dir} is not a run directory (no config.json with a scenario); make one "
            "with 'amuled run SCENARIO' or 'amuled train SCENARIO'"
        )
    data = dict(record.scenario)
    source = data.pop("path", None)
    return scenario_from_dict(data, path=Path(source) if source else None)


def shared_folders(ablation_dir: Path) -> list[str]:
    """The run's folders an ablation is evaluated with: its record's ``shared``."""
    record = read_record(Path(ablation_dir), checkpoint=False)
    return list(record.shared or []) if record is not None else []
