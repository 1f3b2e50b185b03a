"""The run folder: what a run directory holds, and the state of each variant folder in it.

A run directory holds ``config.json``, one folder per variant (``base/``, ``finetune-amuled/``,
seed replicas ``<name>.seed<k>``, ``ablate-<what>/...``) and the report. A variant folder
holds ``model_last.pt`` (``infos["completed"]``: finished), ``config.json`` (the scenario and,
under ``"training"``, the settings a resume or skip compares), ``train_cfg.json``,
``curve.json``, ``tb/`` and, for fine-tunes, ``feedback.json``.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
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
from amuled_ma.files.safe import checked_read_path, write_text_atomic
from amuled_ma.learn.checkpoints import LAST, checkpoint_infos
from amuled_ma.records.run_record import PanelRecord, RunRecord, State
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import MORAL_AGENT, Scenario

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
    """The command that re-runs a graph: ``amuled COMMAND ARGS --run-dir DIR OPTIONS``."""

    command: str
    args: tuple[str, ...]
    options: tuple[str, ...] = ()
    name: str | None = None

    def line(self, run_dir: Path, *more: str, name: str | None = None) -> str:
        """The shell command into ``run_dir`` (``name`` instead of `name`), ``more`` added."""
        name = name or self.name
        named = ("--name", name) if name else ()
        words = ["amuled", self.command, *self.args, "--run-dir", str(run_dir)]
        return shlex.join([*words, *self.options, *named, *more])


@dataclass(frozen=True)
class TrainJob:
    """One job of a run: what it trains and where, planned once and carried to its trainer.

    `plan_job` fills the fields from ``panel`` on (``action`` set: planned). ``base_variant`` is
    the folder under ``base_dir`` (default ``run_dir``) of the base a fine-tune anchors to.
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
    """One trained (or skipped: a completed checkpoint was there, ``outcome`` None) variant."""

    variant: Variant
    out_dir: Path
    skipped: bool = False
    outcome: TrainOutcome | None = None


# -- the state of a variant folder --------------------------------------------------
def base_checkpoint(base_folder: Path, scenario_name: str) -> Path:
    """The completed base checkpoint a fine-tune is anchored to.

    Raises:
        CheckpointError: Missing or unfinished, naming the command that makes it.
    """
    path = Path(base_folder) / LAST
    state = checkpoint_infos(path)
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


def training_differences(out_dir: Path, training: dict[str, Any]) -> list[str]:
    """``key: saved -> now`` for each setting that differs; empty when none (or none saved).

    Raises:
        AmuledError: ``config.json`` exists but is not a run record.
    """
    record = read_record(out_dir, checkpoint=False)
    if record is None or record.training is None:
        return []
    saved = learned_only(record.training)
    training = without_keys_added_since(saved, training)
    return differences(
        {k: v for k, v in saved.items() if k != "iterations"},
        {k: v for k, v in training.items() if k != "iterations"},
    )


def settings_refusal(
    job: TrainJob, diffs: list[str], rerun: Rerun | None = None, hint: str = ""
) -> str:
    """The one-line refusal of a folder trained with other settings, with the fixes."""
    out_dir = job.out_dir
    more = f" and {len(diffs) - 8} more" if len(diffs) > 8 else ""
    keys = ", ".join(d.split(":", 1)[0] for d in diffs[:8]) + more
    shown = "; ".join(diffs[:8]) + (f";{more}" if more else "")
    beside, again = recovery_commands(job, diffs, rerun, hint)
    return (
        f"{out_dir} was trained with other settings or inputs than now ({keys} differ; "
        f"saved -> now: {shown}; saved in {Path(out_dir) / 'config.json'}); to keep it and "
        f"train the new settings beside it: {beside}; to retrain this folder alone with "
        f"them: {again}"
    )


def recovery_commands(
    job: TrainJob, diffs: list[str], rerun: Rerun | None = None, hint: str = ""
) -> tuple[str, str]:
    """``(beside, again)``: the commands that train the new settings beside, or retrain that folder.

    ``beside``: a new ``--name`` (fine-tune) or ``--run-dir``; ``again``: ``--force``, or
    ``--retrain NAME`` for ``run``/``ablate``.
    """
    if rerun is None:
        again = f"{hint} --force" if hint else "--force"
        return "another --run-dir (or --name NAME for a fine-tune)", again
    # a short folder-name tag from the first difference's new value (``ollama``)
    now = diffs[0].rsplit(" -> ", 1)[-1] if diffs else ""
    tag = re.sub(r"[^A-Za-z0-9]+", "-", now).strip("-").lower()[:24].strip("-") or "new"
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
    """Whether ``model_last.pt`` is finished and ``config.json`` records exactly ``training``."""
    state = checkpoint_infos(Path(out_dir) / LAST)
    if not (state and state.get("completed")):
        return False
    try:
        record = read_record(out_dir, checkpoint=False)
    except AmuledError:
        return False
    return (
        record is not None
        and record.training is not None
        and learned_only(record.training) == training
        and state.get("iteration") == training["iterations"]
    )


def prepare_variant(
    job: TrainJob, training: dict[str, Any], *, hint: str = "", rerun: Rerun | None = None
) -> Action:
    """Decide what a job does with its folder: ``new``, ``resume`` or ``skip``.

    A resume or skip needs the saved settings to match ``training``.

    Raises:
        AmuledError: A checkpoint without ``resume`` or ``force``, or ``resume`` over other
            settings (`settings_refusal`) or past the job's iterations.
    """
    out_dir = job.out_dir
    state = checkpoint_infos(Path(out_dir) / LAST)
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
    """A folder's ``config.json`` as a `RunRecord`, or None without one.

    With ``checkpoint`` the iterations done and state come from ``model_last.pt``.

    Raises:
        AmuledError: Not a run record, or larger than `MAX_RECORD_BYTES` (not read).
        UnsafePathError: ``config.json`` is a link or not a regular file.
    """
    from pydantic import ValidationError

    from amuled_ma.files.limits import read_bounded_bytes

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
    infos = checkpoint_infos(Path(folder) / LAST) if checkpoint else None
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
    """Write a folder's ``config.json`` atomically, never through a link.

    Raises:
        UnsafePathError: ``config.json`` is a link or not a regular file; nothing written.
        FileWriteError: The write failed (a full disk), naming the file.
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
    """Write a run's or variant folder's ``config.json`` and return its path.

    It holds ``scenario`` (``Scenario.to_dict``), the command line and ``extra``: more
    `RunRecord` fields (``variants``, ``seeds``, ``training``, ``panel``, ...).
    """
    import torch  # here: reading a run folder needs no torch

    data: dict[str, Any] = {
        "scenario": json.loads(json.dumps(dict(scenario), default=str)),
        "command": list(sys.argv),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "torch": torch.__version__,
    }
    with contextlib.suppress(importlib.metadata.PackageNotFoundError):
        data["rsl_rl"] = importlib.metadata.version("rsl-rl-lib")
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
    """The record's fields of a variant folder about to train (`write_config`'s ``extra``)."""
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
        from amuled_ma.deliberation.panel_feedback import FusedReplayFeedback

        # the panel, from the settings; a fused-only replay has no members
        settings = training.get("feedback") or {}  # none for the human (it asks no panel)
        kind, arg = variant.feedback_kind
        members, rule = list(settings.get("clusters") or []), settings.get("fusion")
        if kind in ("cluster", "moral"):
            members, rule = [str(arg) if kind == "cluster" else MORAL_AGENT], "mean"
        elif kind == "agg":
            rule = arg
        fused_only = isinstance(feedback, FusedReplayFeedback)
        if fused_only:
            members, rule = [], None
        finetune = training.get("finetune") or {}
        fields.update(
            panel=PanelRecord(
                feedback=str(variant.feedback),
                members=members,
                source=settings.get("source"),
                model=settings.get("model"),
                recording=settings.get("recording"),
                fused_only=fused_only,
                fusion=rule,
                agent_sources=dict(settings.get("agents") or {}),
                distill=settings.get("distill"),
                weights=settings.get("weights") if kind == "amuled" and not fused_only else None,
            ),
            recipe=finetune.get("recipe"),
            lambda_kl=finetune.get("lambda_kl"),
        )
        if base_checkpoint is not None:
            fields["base_checkpoint"] = str(base_checkpoint)
    return {k: v for k, v in fields.items() if v is not None}


def variant_records(folders: list[Path]) -> dict[str, RunRecord]:
    """``{folder name: record}`` of the variant folders that hold one (for the evaluation)."""
    records = {Path(folder).name: read_record(folder) for folder in folders}
    return {name: record for name, record in records.items() if record is not None}


def scenario_of_run(run_dir: Path) -> Scenario:
    """Rebuild the scenario a run (or a variant folder) was made with, from its record.

    Raises:
        AmuledError: No ``config.json`` with a scenario; names the commands that make a run.
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
