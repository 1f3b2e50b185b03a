"""What the benchmarks share: output folder, best-of timing, ``--json`` figures, scenario."""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from amuled_ma.files.safe import write_text_atomic

if TYPE_CHECKING:
    from amuled_ma.scenario import Scenario

_Out = TypeVar("_Out")


@contextmanager
def output_folder(out: Path | None, prefix: str) -> Iterator[Path]:
    """Yield ``out`` (created) or a temporary folder named ``prefix...`` (deleted after)."""
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        yield Path(out)
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)


def best_time(func: Callable[[], _Out], repeats: int) -> tuple[_Out, float, float]:
    """Result of the last call, best wall-clock and best CPU seconds over ``repeats`` calls."""
    wall, cpu = float("inf"), float("inf")
    for _ in range(max(repeats, 1)):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        result = func()
        cpu = min(cpu, time.process_time() - start_cpu)
        wall = min(wall, time.perf_counter() - start_wall)
    return result, wall, cpu


def write_figures(path: Path | None, figures: object) -> None:
    """Write ``figures`` as indented JSON to ``path`` and say so; nothing when ``path`` is None."""
    if path:
        write_text_atomic(path, json.dumps(figures, indent=2))
        print(f"\nfigures written to {path}")


def authors_scenario(task: str, base_steps: int) -> Scenario:
    """``<task>-authors`` with a base of ``base_steps``, no TensorBoard, no abstention stop.

    A short base wanders into states the authors never asked: reward 0 there (their recipe),
    without the abstention stop meant for real runs.
    """
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario(f"{task}-authors").replace("base", total_steps=base_steps)
    return scenario.replace("output", tensorboard=False).replace("feedback", max_abstention=1.0)
