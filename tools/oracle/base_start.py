#!/usr/bin/env python3
"""What a FindMilk base gives its fine-tune: the base's behaviour beside the fine-tune's result.

    PYTHONPATH=. .venv/bin/python tools/oracle/base_start.py \
        --pair theirs42=BASE_DIR:FINETUNE_DIR ... [--base published=BASE_DIR ...] \
        [--episodes 50] [--json tools/oracle/results/F.json]

``BASE_DIR`` and ``FINETUNE_DIR`` are job folders holding ``model_last.pt`` (a base of
``switch_bases.py`` or of ``evaluate_base.py``'s imports, a fine-tune of ``switch_bases.py
--finetune-from``). Each policy plays ``--episodes`` sampled episodes of the shipped
``findmilk-authors`` scenario (env seeds 42.., the authors' random tie-breaking) with
``amuled_ma.evaluate.rollout.rollout``; the states of every copy's first episode are kept.
Per label it reports, for the base: crying pacified, sleeping woken and steps (sampled), the
mean entropy ``H = -sum_a pi(a|s) log pi(a|s)`` of the base on its own states and on the
fine-tune's states, the mean probability of the base's most likely action on its own states;
for the fine-tune: the same three metrics and ``KL(ft || base) = sum_a ft(a|s) (log ft - log
base)`` on the fine-tune's states. Over the pairs, Spearman's rank correlation
(``scipy.stats.spearmanr``) of each base measure with the fine-tune's crying pacified.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from scipy import stats

from amuled_ma.evaluate.rollout import Observer, rollout
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.scenario import Scenario, load_scenario
from amuled_ma.tasks.base import BatchedTask

METRICS = ("crying_pacified", "sleeping_woken", "steps_to_milk")


class FirstEpisodeStates(Observer):
    """The observations each copy sees before every action of its first episode."""

    def __init__(self) -> None:
        self.states: list[torch.Tensor] = []
        self._live: torch.Tensor | None = None

    def start(self, task: BatchedTask, obs: torch.Tensor) -> None:
        """Every copy starts in its first episode."""
        self._live = torch.ones(len(obs), dtype=torch.bool)

    def before_step(
        self, task: BatchedTask, obs: torch.Tensor, logp: torch.Tensor, actions: torch.Tensor
    ) -> None:
        """Keep the states of the copies still in their first episode."""
        assert self._live is not None
        self.states.append(obs[self._live].clone())

    def after_step(
        self,
        task: BatchedTask,
        obs: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        info: Mapping[str, Any],
    ) -> None:
        """A copy whose episode ended is no longer watched."""
        assert self._live is not None
        self._live &= ~(terminated | truncated)


def play(actor: torch.nn.Module, scenario: Scenario, episodes: int) -> tuple[dict, torch.Tensor]:
    """Sampled episodes of one policy: the metrics' means and every state it saw ``[M, obs]``."""
    seen = FirstEpisodeStates()
    records = rollout(actor, scenario, episodes=episodes, mode="sampled", seed=42, observers=[seen])
    done = [r for r in records if r is not None]
    means = {k: sum(r[k] for r in done) / len(done) for k in METRICS}
    return means, torch.cat(seen.states)


def entropy(actor: torch.nn.Module, states: torch.Tensor) -> float:
    """Mean entropy of the policy over the states (nats)."""
    with torch.inference_mode():
        logp = action_log_probs(actor, states)
        return float(-(logp.exp() * logp).sum(-1).mean())


def top_probability(actor: torch.nn.Module, states: torch.Tensor) -> float:
    """Mean probability of the policy's most likely action over the states."""
    with torch.inference_mode():
        return float(action_log_probs(actor, states).exp().max(-1).values.mean())


def kl(ft: torch.nn.Module, base: torch.nn.Module, states: torch.Tensor) -> float:
    """Mean ``KL(ft || base)`` over the states."""
    with torch.inference_mode():
        lf, lb = action_log_probs(ft, states), action_log_probs(base, states)
        return float((lf.exp() * (lf - lb)).sum(-1).mean())


def describe_base(base: torch.nn.Module, scenario: Scenario, episodes: int) -> dict[str, Any]:
    """A base's sampled metrics, entropy and top probability on its own states."""
    metrics, states = play(base, scenario, episodes)
    return {
        "base": metrics,
        "base_entropy_own": entropy(base, states),
        "base_top_p_own": top_probability(base, states),
    }


def main() -> int:
    """Measure every pair and base named on the command line; print and write the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pair", nargs="*", default=[], metavar="LABEL=BASE:FINETUNE")
    ap.add_argument("--base", nargs="*", default=[], metavar="LABEL=BASE")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    scenario = load_scenario("findmilk-authors")
    rows: dict[str, dict[str, Any]] = {}
    for spec in args.base:
        label, _, path = spec.partition("=")
        base = load_policy(Path(path) / "model_last.pt", scenario)
        rows[label] = describe_base(base, scenario, args.episodes)
    for spec in args.pair:
        label, _, paths = spec.partition("=")
        base_dir, _, ft_dir = paths.partition(":")
        base = load_policy(Path(base_dir) / "model_last.pt", scenario)
        ft = load_policy(Path(ft_dir) / "model_last.pt", scenario)
        row = describe_base(base, scenario, args.episodes)
        ft_metrics, ft_states = play(ft, scenario, args.episodes)
        row.update(
            finetune=ft_metrics,
            base_entropy_on_ft=entropy(base, ft_states),
            kl_ft_base=kl(ft, base, ft_states),
        )
        rows[label] = row
    cols = ("crying", "sleeping", "H own", "top p", "H on ft", "ft crying", "ft sleeping",
            "ft steps", "KL")  # fmt: skip
    print("| label | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for label, r in rows.items():
        b, f = r["base"], r.get("finetune")
        cells = [b["crying_pacified"], b["sleeping_woken"], r["base_entropy_own"],
                 r["base_top_p_own"], r.get("base_entropy_on_ft"),
                 f and f["crying_pacified"], f and f["sleeping_woken"],
                 f and f["steps_to_milk"], r.get("kl_ft_base")]  # fmt: skip
        print(f"| {label} | " + " | ".join("-" if c is None else f"{c:.3f}" for c in cells) + " |")
    pairs = [r for r in rows.values() if "finetune" in r]
    correlations: dict[str, dict[str, float]] = {}
    if len(pairs) >= 3:
        target = [r["finetune"]["crying_pacified"] for r in pairs]
        measures = {
            "base crying pacified": [r["base"]["crying_pacified"] for r in pairs],
            "base sleeping woken": [r["base"]["sleeping_woken"] for r in pairs],
            "base entropy, own states": [r["base_entropy_own"] for r in pairs],
            "base entropy, fine-tune's states": [r["base_entropy_on_ft"] for r in pairs],
            "base top probability": [r["base_top_p_own"] for r in pairs],
        }
        for name, values in measures.items():
            rho, p = stats.spearmanr(values, target)
            correlations[name] = {"rho": float(rho), "p": float(p)}
            print(f"- {name} vs fine-tune crying pacified: Spearman rho {rho:+.2f} (p {p:.3f})")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "spearman": correlations}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
