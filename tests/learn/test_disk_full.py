"""A disk that fills up during a fine-tune: the last checkpoint stays valid, one line, no temp.

The disk is real: a 64 MiB tmpfs mounted for the test (root only; skipped with the reason
otherwise), filled to the last byte by a file written in the second iteration.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
import tiny_cli
from small_disk import small_disk as mounted_disk

from amuled_ma.cli import main
from amuled_ma.learn.checkpoints import (
    CheckpointWriteError,
    checkpoint_infos,
    read_checkpoint,
    write_checkpoints,
)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 64 MiB tmpfs mounted at a fresh folder, unmounted after the test."""
    with mounted_disk(tmp_path, "64m") as mount:
        yield mount


def fill(folder: Path) -> Path:
    """Write a file into ``folder`` until the disk has no byte left; return it."""
    filler = folder / "filler.bin"
    block = b"\0" * (1 << 20)
    with open(filler, "wb", buffering=0) as handle:
        for size in (1 << 20, 1 << 12, 1):
            with contextlib.suppress(OSError):
                while True:
                    handle.write(block[:size])
    return filler


def leftovers(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp")]


def test_write_checkpoint_on_a_full_disk_keeps_the_old_file(small_disk: Path) -> None:
    path = small_disk / "model_last.pt"
    write_checkpoints([(path, lambda tmp: Path(tmp).write_bytes(b"old checkpoint"))])
    filler = fill(small_disk)
    with pytest.raises(CheckpointWriteError) as caught:
        write_checkpoints([(path, lambda tmp: Path(tmp).write_bytes(b"x" * (1 << 20)))])
    line = str(caught.value)
    assert "\n" not in line
    assert str(path) in line and "No space left on device" in line
    assert "is kept" in line and "free some disk space" in line
    assert path.read_bytes() == b"old checkpoint"
    assert leftovers(small_disk) == []
    filler.unlink()


def test_disk_full_during_a_finetune_keeps_the_last_checkpoint(
    small_disk: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from amuled_ma.learn import population as population_mod

    run_dir = small_disk / "run"
    tiny = [*tiny_cli.TINY, "--set", "finetune.save_interval=1", *tiny_cli.RULES]
    assert main(["train", "findmilk", "--variant", "base", "--run-dir", str(run_dir), *tiny]) == 0
    original = population_mod.PopulationTrainer.iterate
    calls = {"n": 0, "filler": None}

    def disk_fills_in_the_second_iteration(self):
        calls["n"] += 1
        if calls["n"] == 2:
            calls["filler"] = fill(small_disk)
        return original(self)

    monkeypatch.setattr(
        population_mod.PopulationTrainer, "iterate", disk_fills_in_the_second_iteration
    )
    finetune = ["finetune", "findmilk", "--feedback", "human", "--run-dir", str(run_dir), *tiny]
    capsys.readouterr()
    assert main(finetune) == 1
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("amuled: error:")]
    assert len(errors) == 1, err
    assert "Traceback" not in err, err
    checkpoint = run_dir / "finetune-human" / "model_last.pt"
    assert f"cannot write checkpoint {checkpoint}" in errors[0], err
    assert "free some disk space" in errors[0]
    assert "resume with: amuled finetune findmilk" in err
    # the checkpoint of iteration 1 is whole and safe to read; nothing half-written is left
    read_checkpoint(checkpoint)
    assert checkpoint_infos(checkpoint)["iteration"] == 1
    assert leftovers(run_dir) == []

    calls["filler"].unlink()
    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", original)
    assert main([*finetune, "--resume"]) == 0
    assert checkpoint_infos(checkpoint)["completed"] is True


def test_no_progress_watcher_outlives_a_training_that_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever ends the loop (here an unexpected error), the progress watcher thread stops."""
    import threading

    from amuled_ma.learn import population as population_mod

    def fails(self):
        raise RuntimeError("an unexpected failure inside an iteration")

    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", fails)
    before = {t.ident for t in threading.enumerate() if t.name == "progress"}
    try:
        code = main(["train", "findmilk", "--run-dir", str(tmp_path / "run"), *tiny_cli.TINY])
    except RuntimeError:
        code = -1
    assert code != 0
    left = [
        t for t in threading.enumerate()
        if t.name == "progress" and t.is_alive() and t.ident not in before
    ]  # fmt: skip
    assert left == []
