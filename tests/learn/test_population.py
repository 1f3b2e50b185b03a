"""A population trains each member as the lone Trainer trains it, from the same seeds.

The reference of every comparison is the existing lone path (``Trainer`` and rsl-rl's PPO
through ``AnchoredPPO``) run on each member's job alone; members differ in seed, feedback,
KL weight and recipe. Equality is within float rounding (batched matmuls sum in another
order than ``nn.Linear``); random streams, actions, rewards and task states are equal.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from lone_trainer import Trainer

from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.errors import MemberFailed
from amuled_ma.learn.checkpoints import LAST, TRAINER_KEYS, read_checkpoint
from amuled_ma.learn.population import PopulationTrainer, train_population
from amuled_ma.learn.population_groups import MemberSpec
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import scenario_from_dict

#: Float tolerance: the members' float32 networks after a few Adam steps.
ATOL = 1e-5


def tiny(task: str = "findmilk", **finetune) -> object:
    return scenario_from_dict(
        {
            "task": {"name": task, "seed": 3},
            "ppo": {"hidden_dims": [8, 8], "num_mini_batches": 2, "num_learning_epochs": 2},
            "base": {"total_steps": 2 * 4 * 16, "num_envs": 4, "num_steps_per_env": 16},
            "finetune": {
                "iterations": 3,
                "num_envs": 2,
                "num_steps_per_env": 8,
                "num_learning_epochs": 2,
                "save_interval": 2,
                **finetune,
            },
            "output": {"tensorboard": False},
        }
    )


def prefers(action: int, names: int = 4):
    def belief(obs: np.ndarray) -> np.ndarray:
        out = np.full((len(obs), names), 0.1)
        out[:, action] = 1.0 - 0.1 * (names - 1)
        return out

    return belief


#: (feedback's preferred action, lambda_KL, recipe, seed) of each member
MEMBERS = [(0, 2.5, "equation", 10), (1, 0.5, "authors", 11), (2, 1.0, "equation", 12)]


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("base")
    return Trainer(tiny(), folder / "base").train().checkpoint


def specs(root: Path, base: Path, scenario=None, members=MEMBERS) -> list[MemberSpec]:
    scenario = scenario or tiny()
    out = []
    for action, lam, recipe, seed in members:
        job = scenario.replace("finetune", lambda_kl=lam, recipe=recipe)
        out.append(
            MemberSpec(
                job,
                root / f"m{seed}",
                variant=Variant.finetune(f"f{action}"),
                feedback=CallableFeedback(prefers(action), name=f"f{action}"),
                base_checkpoint=base,
                seed=seed,
            )
        )
    return out


LONE_KEYS = (
    "variant", "feedback", "base_checkpoint", "resume", "seed", "iterations", "resume_hint",
    "task_factory",
)  # fmt: skip


def lone_kwargs(spec: MemberSpec) -> dict:
    """The job as keyword arguments of the lone loop (``lone_trainer.Trainer``)."""
    return {key: getattr(spec, key) for key in LONE_KEYS}


def lone(spec: MemberSpec):
    return Trainer(spec.scenario, spec.out_dir, **lone_kwargs(spec)).train()


def assert_rows_close(alone: list[dict], together: list[dict]) -> None:
    assert len(alone) == len(together)
    for a, b in zip(alone, together, strict=True):
        assert set(a) == set(b)
        for key, value in a.items():
            if key == "wall_s":
                continue
            if isinstance(value, float) and math.isfinite(value):
                assert b[key] == pytest.approx(value, abs=ATOL), key
            else:
                assert b[key] == value, key


def assert_states_close(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for key in a:
        torch.testing.assert_close(b[key], a[key], atol=ATOL, rtol=0)


@pytest.mark.parametrize("options", [{}, {"tie_break": "random"}])
def test_members_train_as_they_train_alone(tmp_path, base, options) -> None:
    # random ties: every copy draws from its own stream each step (findmilk-authors)
    scenario = tiny().replace("task", options=options)
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base, scenario)]
    together = train_population(specs(tmp_path / "pop", base, scenario))
    for a, b in zip(alone, together, strict=True):
        assert b.iterations == a.iterations == 3 and b.env_steps == a.env_steps
        assert_rows_close(a.curve, b.curve)
        assert b.feedback == a.feedback  # the same states asked, the same answers counted
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        assert set(sb) == set(sa) == set(TRAINER_KEYS)
        assert sb["iter"] == sa["iter"] == 3
        assert_states_close(sa["actor_state_dict"], sb["actor_state_dict"])
        assert_states_close(sa["critic_state_dict"], sb["critic_state_dict"])
        oa, ob = sa["optimizer_state_dict"], sb["optimizer_state_dict"]
        assert ob["param_groups"] == oa["param_groups"]
        for index, entry in oa["state"].items():
            assert_states_close(entry, ob["state"][index])
        ia, ib = sa["infos"], sb["infos"]
        assert set(ib) == set(ia)
        # each member drew the same random numbers as its lone run, in the same order
        assert torch.equal(ib["torch_rng"], ia["torch_rng"])
        for key in ("variant", "scenario", "iteration", "total_iterations", "completed"):
            assert ib[key] == ia[key]
        assert ib["train_cfg"] == ia["train_cfg"]
        assert_env_states_equal(ia["env_state"], ib["env_state"])
        assert (b.out_dir / "curve.json").is_file() and (b.out_dir / "feedback.json").is_file()
        cfg = (a.out_dir / "train_cfg.json").read_text()
        assert (b.out_dir / "train_cfg.json").read_text() == cfg


def assert_env_states_equal(a, b) -> None:
    if isinstance(a, dict):
        assert set(a) == set(b)
        for key in a:
            assert_env_states_equal(a[key], b[key])
    elif torch.is_tensor(a):
        assert torch.equal(a, b)
    else:
        assert a == b


def test_first_update_matches_alone_loss_by_loss(tmp_path, base) -> None:
    """Losses of the first iteration and rsl-rl's own figure, their mean over members."""
    jobs = specs(tmp_path / "pop", base)
    for job in jobs:
        job.iterations = 1
    population = PopulationTrainer(jobs)
    population.train()
    together = population.alg.member_losses
    rsl_rl = population.alg.last_losses  # rsl-rl's update: the mean over all P x B rows
    for key in ("value", "surrogate", "entropy"):
        mean = sum(member[key] for member in together) / len(together)
        assert mean == pytest.approx(rsl_rl[key], abs=1e-6)
    for job, member in zip(jobs, together, strict=True):
        trainer = Trainer(job.scenario, tmp_path / "lone" / job.out_dir.name, **lone_kwargs(job))
        trainer.train()
        for key, value in trainer.alg.last_losses.items():
            assert member[key] == pytest.approx(value, abs=1e-6), key


def test_population_checkpoints_resume_alone_and_together(tmp_path, base) -> None:
    """A member's checkpoint is a lone job's: a lone resume continues it, and back."""
    scenario = tiny(iterations=4)
    members = MEMBERS[:2]
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base, scenario, members)]

    def stop_at_2(member, iteration: int) -> None:
        if iteration == 2 and member.index == 1:
            raise KeyboardInterrupt

    jobs = specs(tmp_path / "pop", base, scenario, members)
    for job in jobs:
        job.on_iteration = stop_at_2
    with pytest.raises(KeyboardInterrupt):
        train_population(jobs)
    for job in jobs:
        infos = read_checkpoint(job.out_dir / LAST)["infos"]
        assert infos["iteration"] == 2 and not infos["completed"]
    # member 0 resumes alone, member 1 in a population of one
    first, second = specs(tmp_path / "pop", base, scenario, members)
    first.resume = second.resume = True
    resumed = [lone(first), train_population([second])[0]]
    for a, b in zip(alone, resumed, strict=True):
        assert b.iterations == 4
        assert_rows_close(a.curve, b.curve)
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        assert_states_close(sa["actor_state_dict"], sb["actor_state_dict"])
        assert torch.equal(sa["infos"]["torch_rng"], sb["infos"]["torch_rng"])


def test_base_training_population_matches_alone(tmp_path) -> None:
    scenario = tiny(task="driving")
    jobs = [
        MemberSpec(scenario, tmp_path / "pop" / f"s{seed}", seed=seed, iterations=2)
        for seed in (5, 6)
    ]
    together = train_population(jobs)
    for job, b in zip(jobs, together, strict=True):
        job.out_dir = tmp_path / "lone" / job.out_dir.name
        a = lone(job)
        assert_rows_close(a.curve, b.curve)
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        assert_states_close(sa["actor_state_dict"], sb["actor_state_dict"])
        assert_states_close(sa["critic_state_dict"], sb["critic_state_dict"])


def test_options_of_the_authors_update_are_per_member(tmp_path, base) -> None:
    """Joint gradient clipping and a new partition per epoch, per member."""
    from amuled_ma.scenario.sections import FinetuneConfig

    if "grad_clip" not in FinetuneConfig.model_fields:
        pytest.skip("this tree has no [finetune].grad_clip")
    scenario = tiny().replace(
        "finetune", grad_clip="joint", reshuffle_each_epoch=True, bootstrap_time_outs=False
    )
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base, scenario, MEMBERS[:2])]
    together = train_population(specs(tmp_path / "pop", base, scenario, MEMBERS[:2]))
    for a, b in zip(alone, together, strict=True):
        assert_rows_close(a.curve, b.curve)
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        assert_states_close(sa["actor_state_dict"], sb["actor_state_dict"])


def test_jobs_of_another_shape_do_not_train_together(tmp_path, base) -> None:
    jobs = specs(tmp_path, base, members=MEMBERS[:2])
    jobs[1].scenario = jobs[1].scenario.replace("finetune", num_envs=4)
    with pytest.raises(ValueError, match="cannot train with"):
        PopulationTrainer(jobs)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_population_on_cuda_trains_as_alone_on_the_cpu(tmp_path, base) -> None:
    """The same code on a GPU: its members draw the same numbers (CPU streams)."""
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base)]
    together = train_population(specs(tmp_path / "pop", base), device="cuda")
    for a, b in zip(alone, together, strict=True):
        for ra, rb in zip(a.curve, b.curve, strict=True):
            for key in ("losses/value", "losses/surrogate", "feedback/feedback_reward"):
                assert rb[key] == pytest.approx(ra[key], abs=1e-4), key
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        for key, value in sa["actor_state_dict"].items():
            torch.testing.assert_close(sb["actor_state_dict"][key], value, atol=1e-4, rtol=0)
        assert torch.equal(sb["infos"]["torch_rng"], sa["infos"]["torch_rng"])


class NanAfter:
    """A member's feedback that answers NaN after iteration ``after`` (a bad input)."""

    def __init__(self, inner, after: int) -> None:
        self.inner, self.after, self.done = inner, after, 0

    def on_iteration(self, _member, iteration: int) -> None:
        self.done = iteration

    def __call__(self, obs, task):
        out = np.asarray(self.inner(obs, task), dtype=np.float64)
        return out if self.done < self.after else np.full_like(out, np.nan)

    def __getattr__(self, name: str):
        return getattr(self.inner, name)


def test_a_member_whose_feedback_fails_stops_alone(tmp_path, base, capsys) -> None:
    """Member 1's feedback gives NaN in iteration 3: it stops, the others end as alone."""
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base)]
    jobs = specs(tmp_path / "pop", base)
    jobs[1].feedback = NanAfter(jobs[1].feedback, after=2)
    jobs[1].on_iteration = jobs[1].feedback.on_iteration
    results = train_population(jobs)
    failed = results[1]
    assert isinstance(failed, MemberFailed)
    assert str(jobs[1].out_dir) in str(failed) and "not a finite number" in str(failed)
    assert "in iteration 3/3" in str(failed) and "checkpoint of iteration 2" in str(failed)
    # its checkpoint is its state before the iteration that failed
    kept = read_checkpoint(jobs[1].out_dir / LAST)
    assert kept["infos"]["iteration"] == 2 and not kept["infos"]["completed"]
    assert all(torch.isfinite(v).all() for v in kept["actor_state_dict"].values())
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "member" in ln]
    assert len(lines) == 1 and str(jobs[1].out_dir) in lines[0]
    for k in (0, 2):  # the others: as alone, through the stop and the restart without it
        a, b = alone[k], results[k]
        assert b.iterations == 3
        assert_rows_close(a.curve, b.curve)
        sa, sb = read_checkpoint(a.checkpoint), read_checkpoint(b.checkpoint)
        assert_states_close(sa["actor_state_dict"], sb["actor_state_dict"])
        assert_states_close(sa["critic_state_dict"], sb["critic_state_dict"])
        assert torch.equal(sa["infos"]["torch_rng"], sb["infos"]["torch_rng"])


def test_a_member_whose_gradient_is_nan_does_not_reach_the_others(tmp_path, base) -> None:
    """rsl-rl clips all members' gradients with one norm: a NaN member is kept out of it."""
    clean = specs(tmp_path / "clean", base)
    for job in clean:
        job.iterations = 1
    reference = PopulationTrainer(clean)
    reference.train()
    jobs = specs(tmp_path / "pop", base)
    for job in jobs:
        job.iterations = 1
    poisoned = PopulationTrainer(jobs)
    with torch.no_grad():  # member 1's critic answers NaN: its returns, advantages, losses
        last = list(poisoned.alg.critic.parameters())[-1]
        last[1] = float("nan")
    with pytest.raises(MemberFailed, match="gradient was not a finite number") as stop:
        poisoned.train()
    assert stop.value.member == 1 and str(jobs[1].out_dir) in str(stop.value)
    # nothing of its NaN update is written: its checkpoint is its start, the base's actor
    kept = read_checkpoint(jobs[1].out_dir / LAST)
    assert kept["infos"]["iteration"] == 0
    assert_states_close(read_checkpoint(base)["actor_state_dict"], kept["actor_state_dict"])
    for k in (0, 2):
        got = read_checkpoint(jobs[k].out_dir / LAST)["actor_state_dict"]
        want = reference.member_checkpoint(k, completed=False)["actor_state_dict"]
        assert all(torch.isfinite(v).all() for v in got.values())
        assert_states_close(want, got)


def test_a_job_alone_whose_weights_turn_nan_stops_with_its_start_kept(tmp_path, base) -> None:
    """A population of one (the lone classes): a NaN update is caught after the iteration."""
    [job] = specs(tmp_path, base, members=MEMBERS[:1])
    job.iterations = 1
    alone = PopulationTrainer([job])
    with torch.no_grad():
        list(alone.alg.critic.parameters())[-1].fill_(float("nan"))
    with pytest.raises(MemberFailed, match="gradient was not a finite number"):
        alone.train()
    kept = read_checkpoint(job.out_dir / LAST)
    assert kept["infos"]["iteration"] == 0
    assert_states_close(read_checkpoint(base)["actor_state_dict"], kept["actor_state_dict"])


def test_five_seeds_alone_and_together_agree_within_seed_noise(tmp_path, base) -> None:
    """The suite's small form of the 5-seed agreement (docs/learning.md, full runs).

    Five seeds of one fine-tune trained alone and the same five as one population: per
    curve metric (the last iterations' mean of each seed), Welch's t from scipy finds no
    difference beyond the seeds' own spread.
    """
    from scipy import stats

    scenario = tiny(iterations=12)
    members = [(1, 2.5, "authors", seed) for seed in range(20, 25)]
    alone = [lone(spec) for spec in specs(tmp_path / "lone", base, scenario, members)]
    together = train_population(specs(tmp_path / "pop", base, scenario, members))
    for key in ("feedback/feedback_reward", "losses/value", "losses/entropy"):
        a = [np.mean([row[key] for row in run.curve[-4:]]) for run in alone]
        b = [np.mean([row[key] for row in run.curve[-4:]]) for run in together]
        assert np.std(a) > 0, key  # the seeds really differ: the test can tell
        result = stats.ttest_ind(a, b, equal_var=False)
        assert result.pvalue > 0.05, (key, a, b, result)


@pytest.mark.parametrize("kind", ["base", "finetune"])
def test_a_population_of_one_is_the_lone_run_bit_for_bit(tmp_path, base, kind) -> None:
    """One job alone (``amuled train`` / ``finetune``) trains as the lone ``Trainer`` did."""
    if kind == "base":
        job = MemberSpec(tiny(), tmp_path / "pop" / "b", seed=4, iterations=3)
    else:
        job = specs(tmp_path / "pop", base, members=MEMBERS[1:2])[0]
    [together] = train_population([job])
    job.out_dir = tmp_path / "lone" / job.out_dir.name
    alone = lone(job)
    strip = [{k: v for k, v in row.items() if k != "wall_s"} for row in alone.curve]
    assert [{k: v for k, v in row.items() if k != "wall_s"} for row in together.curve] == strip
    sa, sb = read_checkpoint(alone.checkpoint), read_checkpoint(together.checkpoint)
    for key in ("actor_state_dict", "critic_state_dict"):
        for name, value in sa[key].items():
            assert torch.equal(sb[key][name], value), (key, name)
    assert torch.equal(sb["infos"]["torch_rng"], sa["infos"]["torch_rng"])
    assert_env_states_equal(sa["infos"]["env_state"], sb["infos"]["env_state"])
