"""CleanRL policy -> our checkpoint: same actions and log-probabilities, weights only."""

import pytest
import torch
from authors_fakes import CleanRLAgent, save_agent
from job_settings import train_variant

from amuled_ma.authors.policies import (
    authors_changes,
    build_checkpoint,
    build_networks,
    cleanrl_shape,
    last_checkpoint,
    read_cleanrl,
    write_variant,
)
from amuled_ma.errors import CheckpointError
from amuled_ma.learn.checkpoints import LAST, TRAINER_KEYS, read_checkpoint
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

BASE = Variant("base")


def convert(tmp_path, agent, task, variant=BASE, iteration=7):
    source = save_agent(tmp_path / "src" / "base.cleanrl_model", agent)
    state = read_cleanrl(source)
    scenario = load_scenario(task).changed(authors_changes(cleanrl_shape(state)[1]))
    checkpoint = build_checkpoint(state, scenario.ppo, scenario.finetune,
                                  scenario_name=scenario.name, variant=variant,
                                  iteration=iteration,
                                  source={"file": "base.cleanrl_model"})  # fmt: skip
    out = tmp_path / "runs" / task / "base"
    path = write_variant(out, checkpoint, scenario.to_dict(), training={"variant": str(variant)})
    return path, scenario


@pytest.mark.parametrize(
    ("task", "obs_dim", "num_actions"), [("findmilk", 8, 4), ("driving", 11, 3)]
)
def test_converted_policy_acts_like_the_cleanrl_one(tmp_path, task, obs_dim, num_actions):
    agent = CleanRLAgent(obs_dim, num_actions, seed=5)
    path, scenario = convert(tmp_path, agent, task)
    actor = load_policy(path, scenario.ppo)
    obs = torch.rand(1000, obs_dim, generator=torch.Generator().manual_seed(1)) * 11 - 2
    with torch.no_grad():
        theirs = torch.distributions.Categorical(logits=agent.actor(obs))
        ours = action_log_probs(actor, obs)
    assert torch.equal(ours.argmax(dim=-1), theirs.logits.argmax(dim=-1))
    torch.testing.assert_close(ours, theirs.logits, rtol=0, atol=1e-5)
    # the critic too, loaded into the network the trainer builds
    state = read_checkpoint(path, need=TRAINER_KEYS)
    _actor, critic = build_networks(scenario.ppo, obs_dim, num_actions)
    critic.load_state_dict(state["critic_state_dict"])
    with torch.no_grad():
        torch.testing.assert_close(critic.mlp(obs), agent.critic(obs), rtol=0, atol=1e-5)


def test_checkpoint_is_a_completed_trainer_checkpoint(tmp_path):
    path, _scenario = convert(
        tmp_path, CleanRLAgent(8, 4), "findmilk", Variant.finetune("amuled"), 805
    )
    state = read_checkpoint(path, need=TRAINER_KEYS)
    infos = state["infos"]
    assert state["iter"] == 805 and infos["iteration"] == infos["total_iterations"] == 805
    assert infos["completed"] is True and infos["variant"] == "finetune:amuled"
    assert (infos["obs_dim"], infos["num_actions"]) == (8, 4)
    assert infos["authors"] == {"file": "base.cleanrl_model"}
    assert len(state["optimizer_state_dict"]["param_groups"][0]["params"]) == 12
    assert (path.parent / "config.json").is_file() and (path.parent / "train_cfg.json").is_file()


def test_finetune_starts_from_the_converted_base(tmp_path):
    agent = CleanRLAgent(8, 4, seed=2)
    path, scenario = convert(tmp_path, agent, "findmilk")
    scenario = scenario.replace("output", tensorboard=False)
    scenario = scenario.replace("finetune", num_envs=2, num_steps_per_env=4)
    job = train_variant(
        scenario,
        tmp_path / "ft",
        Variant.finetune("human"),
        base_dir=path.parent.parent,
        iterations=1,
    )
    assert job.outcome is not None and job.outcome.iterations == 1
    tuned = read_checkpoint(job.out_dir / LAST, need=TRAINER_KEYS)
    assert tuned["infos"]["base_checkpoint"] == str(path)


def test_unsafe_or_foreign_files_refused(tmp_path):
    marker = tmp_path / "marker"

    class Exploit:
        def __reduce__(self):
            import os

            return (os.system, (f"touch {marker}",))

    evil = tmp_path / "evil.cleanrl_model"
    torch.save({"actor.0.weight": Exploit()}, evil)
    with pytest.raises(CheckpointError, match=r"evil.cleanrl_model.*could run code"):
        read_cleanrl(evil)
    assert not marker.exists()
    other = tmp_path / "other.cleanrl_model"
    torch.save({"weight": torch.zeros(2)}, other)
    with pytest.raises(CheckpointError, match="not the authors' CleanRL Agent"):
        read_cleanrl(other)
    broken = CleanRLAgent(8, 4).state_dict()
    broken["actor.2.weight"] = torch.zeros(64, 32)
    torch.save(broken, other)
    with pytest.raises(CheckpointError, match="do not chain"):
        read_cleanrl(other)


def test_last_checkpoint_is_the_highest_iteration(tmp_path):
    for n in (5, 10, 100, 95):
        (tmp_path / f"ppo_{n}.cleanrl_model").write_bytes(b"")
    (tmp_path / "ppo_x.cleanrl_model").write_bytes(b"")
    path, n = last_checkpoint(tmp_path)
    assert (path.name, n) == ("ppo_100.cleanrl_model", 100)
