"""A checkpoint that would run code when unpickled is refused, and nothing from it runs.

The poisoned file is a real pickle whose loading calls ``os.system``: the control at the
top shows that ``torch.load(..., weights_only=False)`` (what rsl-rl's ``runner.load`` and
the old loaders did) runs it.
"""

import os
import shutil

import pytest
import tiny_cli
import torch
from sparse_files import sparse

from amuled_ma.cli import main
from amuled_ma.errors import CheckpointError
from amuled_ma.learn.checkpoints import read_checkpoint

#: The tiny run, its fine-tunes 2 iterations long, on the rules panel.
TINY = [*tiny_cli.TINY, *tiny_cli.RULES, "--set", "finetune.iterations=2"]


class _Payload:
    """Unpickling this calls ``os.system(command)``."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def _poison(path, marker) -> None:
    """Write a checkpoint-shaped file whose unpickling touches ``marker``."""
    state = torch.load(path, weights_only=True) if path.exists() else {}
    state["infos"] = {"completed": True, "payload": _Payload(f"touch {marker}")}
    torch.save(state, path)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A run folder with a finished tiny base (trained once for the module)."""
    run_dir = tmp_path_factory.mktemp("safety") / "run"
    assert main(["train", "findmilk", "--run-dir", str(run_dir), *TINY]) == 0
    return run_dir


def test_control_the_poisoned_checkpoint_runs_code_when_loaded_unsafely(tmp_path):
    marker = tmp_path / "ran"
    _poison(tmp_path / "bad.pt", marker)
    torch.load(tmp_path / "bad.pt", weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("command", ["evaluate", "finetune", "train --resume"])
def test_poisoned_checkpoint_is_refused_and_nothing_runs(trained, tmp_path, capsys, command):
    run_dir = tmp_path / "run"
    shutil.copytree(trained, run_dir)
    marker = tmp_path / "ran"
    _poison(run_dir / "base" / "model_last.pt", marker)
    if command == "evaluate":
        argv = ["evaluate", str(run_dir), "--episodes", "1", "--no-progress"]
    elif command == "finetune":
        argv = ["finetune", "findmilk", "--run-dir", str(run_dir), "--feedback", "human", *TINY]
    else:
        argv = ["train", "findmilk", "--run-dir", str(run_dir), "--resume", *TINY]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert not marker.exists(), "code from the checkpoint ran"
    assert err.count("\n") == 1 and err.startswith("amuled: error: "), err
    assert "model_last.pt" in err and "posix.system" in err and "not weights-only" in err, err
    assert "Traceback" not in err


def test_read_checkpoint_names_missing_keys(tmp_path):
    path = tmp_path / "odd.pt"
    torch.save({"weights": torch.zeros(2)}, path)
    with pytest.raises(CheckpointError, match=r"odd\.pt lacks 'actor_state_dict'.*weights"):
        read_checkpoint(path)
    torch.save([1, 2, 3], path)
    with pytest.raises(CheckpointError, match="expected a dict of state dicts, found list"):
        read_checkpoint(path)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable PyTorch file"):
        read_checkpoint(path)


def test_our_checkpoints_load_weights_only_and_resume(trained, tmp_path, capsys):
    """Everything the trainer saves (curve, RNG state, settings) is plain data."""
    state = read_checkpoint(trained / "base" / "model_last.pt", need=("iter", "infos"))
    assert state["infos"]["completed"] is True
    assert isinstance(state["infos"]["torch_rng"], torch.Tensor)
    run_dir = tmp_path / "run"
    shutil.copytree(trained, run_dir)
    argv = ["finetune", "findmilk", "--run-dir", str(run_dir), "--feedback", "human", *TINY]
    assert main(argv) == 0
    argv = [*argv, "--resume", "--set", "finetune.iterations=3"]
    assert main(argv) == 0
    tuned = read_checkpoint(run_dir / "finetune-human" / "model_last.pt", need=("iter",))
    assert tuned["iter"] == 3
    capsys.readouterr()


@pytest.mark.parametrize(
    ("name", "what"), [("model_last.pt", "checkpoint"), ("x.cleanrl_model", "the CleanRL policy")]
)
def test_a_checkpoint_over_1_gib_is_refused_unread_with_one_line(tmp_path, monkeypatch, name, what):
    import time

    from amuled_ma.authors.policies import read_cleanrl
    from amuled_ma.files.torch_load import MAX_TORCH_FILE_BYTES

    assert MAX_TORCH_FILE_BYTES == 2**30
    path = tmp_path / name
    sparse(path, MAX_TORCH_FILE_BYTES + 1)

    def never(*args, **kwargs):
        raise AssertionError("torch.load was called: the file was read")

    monkeypatch.setattr(torch, "load", never)
    start = time.perf_counter()
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path) if what == "checkpoint" else read_cleanrl(path)
    assert time.perf_counter() - start < 1.0
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"cannot load {what} {path}: it is 1,073,741,825 bytes, more than ")
    assert "the 1,073,741,824 a PyTorch file may be" in message and "it is not read" in message


def test_a_checkpoint_at_the_cap_is_handed_to_torch(tmp_path, monkeypatch):
    from amuled_ma.files.torch_load import MAX_TORCH_FILE_BYTES

    path = tmp_path / "model_last.pt"
    sparse(path, MAX_TORCH_FILE_BYTES)
    called = []
    monkeypatch.setattr(torch, "load", lambda *a, **k: called.append(a) or {"iter": 1})
    with pytest.raises(CheckpointError, match="lacks 'actor_state_dict'"):
        read_checkpoint(path)
    assert called, "a file at the cap is read"


def test_evaluate_refuses_a_checkpoint_over_1_gib_with_one_line(trained, tmp_path, capsys):
    from amuled_ma.files.torch_load import MAX_TORCH_FILE_BYTES

    run_dir = tmp_path / "run"
    shutil.copytree(trained, run_dir)
    sparse(run_dir / "base" / "model_last.pt", 2 * MAX_TORCH_FILE_BYTES)
    capsys.readouterr()
    assert main(["evaluate", str(run_dir), "--episodes", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("amuled: error: "), err
    assert "model_last.pt: it is 2,147,483,648 bytes, more than the 1,073,741,824" in err
    assert "Traceback" not in err
