"""A population stopped anywhere and resumed trains on as the population that never stopped.

The reference is the same population trained without a stop. A stop inside an iteration
(Ctrl-C or SIGTERM in the rollout or in the update) writes the state after the last whole
iteration; a hard stop (a killed process) keeps the last periodic checkpoint. Either
way the resumed curves, weights, Adam state and random streams are bit for bit the
uninterrupted run's: same members, same order, same float operations.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from lone_trainer import Trainer
from test_population import MEMBERS, prefers, specs, tiny

from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.errors import Terminated
from amuled_ma.learn.checkpoints import LAST, read_checkpoint
from amuled_ma.learn.population import PopulationTrainer, train_population
from amuled_ma.learn.population_groups import MemberSpec

#: Iterations, and a checkpoint every SAVE: periodic checkpoints at 2 and 4.
ITERATIONS, SAVE = 5, 2


class Killed(BaseException):
    """A stop nothing catches (the process killed): no checkpoint is written for it."""


def scenario():
    return tiny(iterations=ITERATIONS, save_interval=SAVE).replace("base", save_interval=SAVE)


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    return Trainer(tiny(), tmp_path_factory.mktemp("base") / "base").train().checkpoint


class Interrupting:
    """A member's feedback that raises ``stop`` on its ``at``-th call (inside a rollout)."""

    def __init__(self, action: int, at: int | None, stop: type[BaseException]) -> None:
        self.inner, self.at, self.stop, self.calls = prefers(action), at, stop, 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.calls += 1
        if self.calls == self.at:
            raise self.stop
        return self.inner(obs)


def finetunes(root: Path, base: Path, *, at: int | None = None, stop=KeyboardInterrupt):
    jobs = specs(root, base, scenario(), MEMBERS[:2])
    for job, (action, *_) in zip(jobs, MEMBERS, strict=False):
        job.feedback = CallableFeedback(Interrupting(action, at, stop), name=f"f{action}")
    return jobs


def bases(root: Path) -> list[MemberSpec]:
    return [
        MemberSpec(scenario(), root / f"s{seed}", seed=seed, iterations=ITERATIONS)
        for seed in (5, 6)
    ]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, base) -> dict[str, list[dict]]:
    root = tmp_path_factory.mktemp("uninterrupted")
    runs = {
        "finetune": train_population(finetunes(root / "ft", base)),
        "base": train_population(bases(root / "base")),
    }
    return {kind: [read_checkpoint(o.checkpoint) for o in out] for kind, out in runs.items()}


def resume(jobs: list[MemberSpec]) -> list[dict]:
    for job in jobs:
        job.resume = True
        job.on_iteration = None
    return [read_checkpoint(o.checkpoint) for o in train_population(jobs)]


def assert_same_run(want: list[dict], got: list[dict]) -> None:
    """Every member: the same curve (but wall time), weights, Adam state and stream."""
    for a, b in zip(want, got, strict=True):
        assert b["iter"] == a["iter"] == ITERATIONS
        rows_a = [{k: v for k, v in row.items() if k != "wall_s"} for row in a["infos"]["curve"]]
        rows_b = [{k: v for k, v in row.items() if k != "wall_s"} for row in b["infos"]["curve"]]
        assert rows_b == rows_a
        for key in ("actor_state_dict", "critic_state_dict"):
            for name, value in a[key].items():
                assert torch.equal(b[key][name], value), (key, name)
        for index, entry in a["optimizer_state_dict"]["state"].items():
            for name, value in entry.items():
                assert torch.equal(b["optimizer_state_dict"]["state"][index][name], value)
        assert torch.equal(b["infos"]["torch_rng"], a["infos"]["torch_rng"])


def iterations_written(jobs: list[MemberSpec]) -> list[int]:
    return [read_checkpoint(job.out_dir / LAST)["infos"]["iteration"] for job in jobs]


@pytest.mark.parametrize("stop", [KeyboardInterrupt, Terminated])
def test_a_stop_inside_a_rollout_resumes_exactly(tmp_path, base, uninterrupted, stop) -> None:
    # 8 steps a rollout, each member's feedback asked once a step: call 3 * 8 + 3 is
    # step 3 of iteration 4, after iteration 3 (no periodic checkpoint) was whole
    jobs = finetunes(tmp_path, base, at=3 * 8 + 3, stop=stop)
    with pytest.raises(stop):
        train_population(jobs)
    assert iterations_written(jobs) == [3, 3]
    assert_same_run(uninterrupted["finetune"], resume(finetunes(tmp_path, base)))


def test_a_stop_inside_an_update_resumes_exactly(tmp_path, base, uninterrupted) -> None:
    jobs = finetunes(tmp_path, base)
    population = PopulationTrainer(jobs)
    steps = {"n": 0}

    def interrupt(*_args) -> None:  # Adam's steps: 2 epochs x 2 mini-batches an update
        steps["n"] += 1
        if steps["n"] == 2 * 4 + 3:  # the update of iteration 3, its Adam step 3 of 4
            raise KeyboardInterrupt

    population.alg.optimizer.register_step_pre_hook(interrupt)
    with pytest.raises(KeyboardInterrupt):
        population.train()
    assert iterations_written(jobs) == [2, 2]
    assert_same_run(uninterrupted["finetune"], resume(finetunes(tmp_path, base)))


@pytest.mark.parametrize("kind", ["finetune", "base"])
def test_a_killed_population_resumes_from_its_last_checkpoint(
    tmp_path, base, uninterrupted, kind
) -> None:
    """Killed after its second periodic checkpoint (iteration 4, SAVE = 2)."""
    jobs = finetunes(tmp_path, base) if kind == "finetune" else bases(tmp_path)

    def kill(_member, iteration: int) -> None:
        if iteration == 2 * SAVE + 1:
            raise Killed

    for job in jobs:
        job.on_iteration = kill
    with pytest.raises(Killed):
        train_population(jobs)
    assert iterations_written(jobs) == [2 * SAVE, 2 * SAVE]
    again = finetunes(tmp_path, base) if kind == "finetune" else bases(tmp_path)
    assert_same_run(uninterrupted[kind], resume(again))


def test_a_kill_while_the_members_checkpoints_are_written_leaves_one_iteration(
    tmp_path, base, uninterrupted, monkeypatch
) -> None:
    """Killed inside the second member's write of checkpoint 4: both stay at checkpoint 2.

    Members at two iterations would resume as two populations of other sizes, whose float
    sums differ from this one's (the gradient of a mean over ``P x B`` rows): the set is
    written whole or not at all, so the resume is exact.
    """
    jobs = finetunes(tmp_path, base)
    writes = {"n": 0}
    save = torch.save

    def killed_in_the_fourth_write(obj, path) -> None:  # checkpoint 2: writes 1-2; 4: 3-4
        writes["n"] += 1
        save(obj, path)
        if writes["n"] == 4:
            raise Killed

    monkeypatch.setattr(torch, "save", killed_in_the_fourth_write)
    with pytest.raises(Killed):
        train_population(jobs)
    monkeypatch.setattr(torch, "save", save)
    assert iterations_written(jobs) == [SAVE, SAVE]
    assert not [p for job in jobs for p in job.out_dir.iterdir() if p.suffix == ".tmp"]
    assert_same_run(uninterrupted["finetune"], resume(finetunes(tmp_path, base)))
