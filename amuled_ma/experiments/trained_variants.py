"""A run's trained variants, resolved from its records for ``amuled view`` and ``explain``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.errors import AmuledError, CheckpointError
from amuled_ma.evaluate.episode_trace import TrainedVariant
from amuled_ma.evaluate.evaluator import variant_dirs
from amuled_ma.experiments.run_folder import read_record, scenario_of_run, split_replica
from amuled_ma.learn.checkpoints import LAST, checkpoint_infos

if TYPE_CHECKING:
    from amuled_ma.evaluate.viewer import ViewResult


def trained_variant(run_dir: Path, variant_dir: Path) -> TrainedVariant:
    """A variant folder of a run as a `TrainedVariant` (its record's scenario, else the run's).

    Raises:
        CheckpointError: The folder holds no trained policy.
        AmuledError: Neither folder holds a record with a scenario.
    """
    run_dir, variant_dir = Path(run_dir), Path(variant_dir)
    if not (variant_dir / LAST).is_file():
        raise CheckpointError(
            f"{run_dir}: no trained variant {variant_dir.name!r} (no {variant_dir / LAST}); "
            "variants are the folders with a checkpoint"
        )
    record = read_record(variant_dir, checkpoint=False)
    own = record is not None and record.scenario is not None
    # the base a fine-tune was anchored to: the record's (else the checkpoint's), as given or
    # by folder name in the run; then the run's base folder (base.seed<k> first for a replica)
    recorded = record.base_checkpoint if record is not None else None
    if not recorded:
        try:
            recorded = (checkpoint_infos(variant_dir / LAST) or {}).get("base_checkpoint")
        except AmuledError:
            recorded = None
    candidates: list[Path] = []
    if recorded:
        recorded_path = Path(str(recorded))
        candidates += [recorded_path, run_dir / recorded_path.parent.name / LAST]
        candidates.append(run_dir.parent / recorded_path.parent.name / LAST)
    seed = split_replica(variant_dir.name)[1]
    if seed is not None:
        candidates.append(run_dir / f"base.seed{seed}" / LAST)
    candidates += [run_dir / "base" / LAST, run_dir.parent / "base" / LAST]
    own_checkpoint = (variant_dir / LAST).resolve()
    base = next((p for p in candidates if p.is_file() and p.resolve() != own_checkpoint), None)
    return TrainedVariant(
        name=variant_dir.name,
        checkpoint=variant_dir / LAST,
        scenario=scenario_of_run(variant_dir if own else run_dir),
        variant=record.variant if record is not None else None,
        base_checkpoint=base,
    )


def choose_variants(run_dir: Path, names: Sequence[str] | None = None) -> list[Path]:
    """The variant folders to show: the named ones, else every fine-tuned variant's first replica.

    Raises:
        CheckpointError: A named folder has no checkpoint, or the run has no fine-tuned variant.
    """
    run_dir = Path(run_dir)
    found = variant_dirs(run_dir)
    listing = ", ".join(d.name for d in found) or "none"
    if names:
        for name in names:
            if not (run_dir / name / LAST).is_file():
                raise CheckpointError(
                    f"{run_dir}: no trained variant {name!r} (no {run_dir / name / LAST}); "
                    f"variants found: {listing}"
                )
        return [run_dir / name for name in names]
    chosen = []
    for folder in found:
        record = read_record(folder, checkpoint=False)
        if record is not None and record.finetuning and split_replica(folder.name)[1] is None:
            chosen.append(folder)
    if not chosen:
        raise CheckpointError(
            f"{run_dir}: no fine-tuned variant (*/{LAST} of a 'finetune' folder); "
            f"variants found: {listing}; fine-tune one with 'amuled finetune', or name one "
            "with --variant"
        )
    return chosen


def evaluated_episodes(run_dir: Path, planned: int) -> int:
    """The episodes per policy of the run's evaluation (a sampled episode depends on it).

    The run's ``results.json``'s episodes, else ``planned`` (``[evaluation].episodes``).
    """
    from amuled_ma.evaluate.results import read_results

    if (Path(run_dir) / "results.json").is_file():
        episodes = read_results(Path(run_dir)).episodes
        if episodes is not None:
            return int(episodes)
    return int(planned)


def write_run_view(
    run_dir: Path,
    names: Sequence[str] | None = None,
    episodes: int | None = None,
    output: Path | None = None,
    *,
    episode: int = 0,
    mode: str = "greedy",
    say: Callable[[str], None],
) -> ViewResult:
    """Write the viewer page of a run's `choose_variants` (``amuled view``, the demo's page).

    ``episodes`` None: `evaluated_episodes`; ``say`` gets the progress lines.

    Raises:
        AmuledError: The folder is no run (no record with a scenario).
        CheckpointError: See `choose_variants`.
    """
    from amuled_ma.evaluate.viewer import write_view

    run_dir = Path(run_dir)
    scenario = scenario_of_run(run_dir)
    chosen = [trained_variant(run_dir, d) for d in choose_variants(run_dir, names)]
    if episodes is None:
        episodes = evaluated_episodes(run_dir, scenario.evaluation.episodes)
    say(f"view {run_dir}: episode {episode} of {episodes}, {mode} actions")
    return write_view(
        run_dir,
        chosen,
        output,
        scenario_name=scenario.name,
        task_name=scenario.task.name,
        evaluation=scenario.evaluation,
        episode=episode,
        mode=mode,
        episodes=episodes,
        say=say,
    )
