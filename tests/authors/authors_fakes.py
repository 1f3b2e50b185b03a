"""Small artefacts in the AMULED authors' formats, built here (see /tmp spec section 5, 6).

- LLM caches: ``dict[tuple of numpy scalars (the flattened obs)] -> {cluster: float64 array,
  'moral': array, 'rewards': {frozenset({'0'}): np.float64, ...}, ['error': True,
  'response': {prompt: raw reply}]}``; the fused-only Drive cache holds ``{'rewards': ...}``.
- CleanRL policies: ``torch.save(Agent().state_dict())`` of CleanRL's ``Agent`` (separate
  ``critic`` and ``actor`` ``nn.Sequential``: Linear, Tanh, Linear, Tanh, Linear).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

CLUSTERS = ("consequentialist", "deontologist", "virtue", "care", "social justice")
THEORIES = ("Consequentialist", "Deontological", "Virtue Ethics", "Care Ethics",
            "Social Justice Ethics")  # fmt: skip


def credence_prompt(state_text: str, cluster: str | None) -> str:
    """A prompt as the authors built it (their llm_moral.py): credences one-hot, or none."""
    if cluster is None:
        return f"{state_text}\n\nBehave as moral agent. Using moral theories, reason through it."
    values = ", ".join(
        f"{t}: {1.0 if c == cluster else 0.0}" for t, c in zip(THEORIES, CLUSTERS, strict=True)
    )
    return (
        f"{state_text}\n\nBehave as an agent that assigns the following credence values: "
        f"{{{values}}}. Using the credence confidence for moral theories, reason through it."
    )


def belief(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random float64 probability vector with a zero entry (as the LLMs often answer)."""
    p = rng.random(n)
    p[rng.integers(n)] = 0.0
    return p / p.sum()


def findmilk_cache(seed: int = 0, states: int = 5) -> dict:
    """A FindMilk cache: float32 8-tuples, 4 actions; state 1 flagged with raw replies."""
    rng = np.random.default_rng(seed)
    cache: dict = {}
    for i in range(states):
        key = tuple(np.float32(v) for v in (i, 1, 7, 7, 2, 2, 1, 1))
        entry: dict = {c: belief(rng, 4) for c in CLUSTERS}
        entry["moral"] = belief(rng, 4)
        fused = belief(rng, 4)
        entry["rewards"] = {frozenset({str(a)}): np.float64(fused[a]) for a in range(4)}
        if i == 1:
            entry["error"] = True
            # replies in another order than the call order: the agent comes from the prompt
            order = ["care", None, "consequentialist", "virtue", "social justice", "deontologist"]
            entry["response"] = {
                credence_prompt(f"state {i}", c): f'reply of {c or "moral"}: {{"0": 0.5}}'
                for c in order
            }
        cache[key] = entry
    return cache


def driving_fused_only_cache(seed: int = 1) -> dict:
    """A fused-only Driving cache (float64 11-tuples, 3 actions); state 2 is all zero."""
    rng = np.random.default_rng(seed)
    cache: dict = {}
    for i in range(4):
        key = tuple(np.float64(v) for v in (i, -1, -1, -1, -1, -1, 0, 0, 1, 0, 0))
        if i == 2:  # total conflict: the authors' fusion returned Python 0.0 for every action
            rewards = {frozenset({str(a)}): 0.0 for a in range(3)}
        else:
            fused = belief(rng, 3)
            rewards = {frozenset({str(a)}): np.float64(fused[a]) for a in range(3)}
        cache[key] = {"rewards": rewards}
    return cache


def driving_cache(seed: int = 2, states: int = 3) -> dict:
    """A Driving cache with cluster beliefs (float64 11-tuples, 3 actions)."""
    rng = np.random.default_rng(seed)
    cache: dict = {}
    for i in range(states):
        key = tuple(np.float64(v) for v in (i + 1, -1, 3, -1, -2, -2, 0, 0, 0, 0, 1))
        entry: dict = {c: belief(rng, 3) for c in CLUSTERS}
        entry["moral"] = belief(rng, 3)
        fused = belief(rng, 3)
        entry["rewards"] = {frozenset({str(a)}): np.float64(fused[a]) for a in range(3)}
        cache[key] = entry
    return cache


def write_pickle(path: Path, obj: object) -> Path:
    """Pickle ``obj`` as the authors did (protocol 4)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(obj, protocol=4))
    return path


class CleanRLAgent(nn.Module):
    """CleanRL's ppo.py ``Agent``: separate critic and actor, 64-64 tanh MLPs."""

    def __init__(self, obs_dim: int, num_actions: int, seed: int = 0) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(seed)

        def layer(n_in: int, n_out: int) -> nn.Linear:
            linear = nn.Linear(n_in, n_out)
            with torch.no_grad():  # random weights and biases (a trained net, not an init)
                linear.weight.copy_(torch.randn(n_out, n_in, generator=gen) * 0.5)
                linear.bias.copy_(torch.randn(n_out, generator=gen) * 0.5)
            return linear

        self.critic = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1)
        )
        self.actor = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, num_actions)
        )


def save_agent(path: Path, agent: CleanRLAgent) -> Path:
    """``torch.save(agent.state_dict(), path)`` as the authors did."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(agent.state_dict(), path)
    return path


def fake_checkout(root: Path) -> dict:
    """A folder laid out like a checkout of temetski/moral_agent; returns what it holds."""
    caches = {
        "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle": findmilk_cache(),
        "models/Driving_42/llama-3.1-8B_llm_cache.pickle": driving_cache(),
        "PickleCacheAndBaseModels/Drive/gpt-4o-mini_llm_cache.pickle": driving_fused_only_cache(),
    }
    for rel, cache in caches.items():
        write_pickle(root / rel, cache)
    agents = {
        "models/FindMilk-v4_42/base.cleanrl_model": CleanRLAgent(8, 4, seed=1),
        "models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_5.cleanrl_model": CleanRLAgent(8, 4, 2),
        "models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_10.cleanrl_model": CleanRLAgent(8, 4, 3),
        "models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_100.cleanrl_model": CleanRLAgent(8, 4, 4),
    }
    for rel, agent in agents.items():
        save_agent(root / rel, agent)
    return {"caches": caches, "agents": agents}
