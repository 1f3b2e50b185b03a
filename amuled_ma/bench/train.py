"""Training speed and quality: our figures beside the reference (the paper authors' code).

FindMilk base training (time until the greedy policy is first optimal), Driving base
training (collisions, rescues, lane changes), a 1,000-iteration replay fine-tune, and
batched ``bjs-dst`` fusion. References were measured on 2 cores, no GPU.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.bench._output import output_folder

if TYPE_CHECKING:
    from rsl_rl.models import MLPModel

    from amuled_ma.scenario import TaskConfig

#: Reference figures (the authors' code) and our targets, per measured figure.
REFERENCE: dict[str, tuple[str, str]] = {
    "findmilk_optimal_s": ("~51k steps (~16 s at 3,100 steps/s)", "< 10 s"),
    "findmilk_full_s": ("~160 s (~3,100 steps/s)", "< 30 s"),
    "final_optimal": ("100%", "100%"),
    "driving_full_s": ("~185 s", "< 40 s"),
    "driving_collisions": ("0.7", "<= 0.7"),
    "driving_grandmas": ("5.1", "-"),
    "driving_lane_changes": ("15.8", "-"),
    "finetune_s": ("~6 min (2.7-2.9 it/s)", "< 60 s"),
    "fusion_ms": ("~18 ms per state", "-"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a tenth of every budget (a smoke run, figures not comparable)",
    )
    parser.add_argument(
        "--skip",
        nargs="*",
        default=[],
        choices=("findmilk", "driving", "finetune", "fusion"),
        help="parts to leave out",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="folder for the runs (default: a temp folder)"
    )


def _eval(actor: MLPModel, task_config: TaskConfig, episodes: int) -> list[dict]:
    from amuled_ma.evaluate.evaluator import run_episodes

    records, _ = run_episodes(
        actor, task_config, episodes=episodes, mode="greedy", record_trajectory=False
    )
    return records


def bench_base(name: str, out: Path, quick: bool) -> dict[str, Any]:
    """Base training of a task: the full run and its greedy policy's 50 episodes (``final``).

    On FindMilk also ``optimal``: when the greedy policy (10 episodes after each iteration,
    their time left out) first reaches the milk in 14 steps every time.
    """
    from amuled_ma.learn.population import PopulationMember, PopulationTrainer
    from amuled_ma.learn.population_groups import MemberSpec
    from amuled_ma.scenario import load_scenario

    sc = load_scenario(name).replace("output", tensorboard=False)
    if quick:  # a tenth of its base steps
        sc = sc.replace("base", total_steps=sc.base.total_steps // 10)
    first: dict[str, Any] = {}
    eval_s = 0.0

    def check(member: PopulationMember, it: int) -> None:
        nonlocal eval_s
        if first:
            return
        t0 = time.perf_counter()
        records = _eval(member.policy(), sc.task, 10)
        eval_s += time.perf_counter() - t0
        if all(r["reached_milk"] and r["steps_to_milk"] == 14 for r in records):
            first["iteration"] = it
            first["steps"] = it * sc.base.num_envs * sc.base.num_steps_per_env
            first["wall_s"] = time.perf_counter() - start - eval_s

    watch = check if name == "findmilk" else None
    trainer = PopulationTrainer([MemberSpec(sc, out / f"{name}-base", on_iteration=watch)])
    start = time.perf_counter()
    outcome = trainer.train()[0]
    wall = time.perf_counter() - start - eval_s
    return {
        "steps": outcome.env_steps,
        "full_s": wall,
        "steps_per_s": outcome.env_steps / wall,
        "optimal": first,
        "final": _eval(trainer.member_policy(0), sc.task, 50),
        "checkpoint": outcome.checkpoint,
    }


def bench_finetune(out: Path, base_ckpt: Path | None, quick: bool) -> dict[str, Any]:
    """Time a fine-tune of the paper's length with replayed AMULED feedback."""
    from amuled_ma.experiments.pipeline import PipelineRequest, train_alone
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.learn.population import PopulationTrainer
    from amuled_ma.learn.population_groups import MemberSpec
    from amuled_ma.records.variants import Variant
    from amuled_ma.scenario import load_scenario

    sc = load_scenario("findmilk").replace("output", tensorboard=False)
    if not sc.recording_path().exists():
        return {"skipped": f"recording not found at {sc.recording_path()}"}
    run = out / "finetune-run"
    (run / "base").mkdir(parents=True, exist_ok=True)
    if base_ckpt is None or not Path(base_ckpt).is_file():
        PopulationTrainer(
            [MemberSpec(sc.replace("base", total_steps=100_000), run / "base")]
        ).train()
    else:
        (run / "base" / LAST).write_bytes(Path(base_ckpt).read_bytes())
    iterations = sc.finetune.iterations // (10 if quick else 1)
    t0 = time.perf_counter()
    request = PipelineRequest(sc, run, force=True, progress=False)
    job = train_alone(request, Variant.finetune("amuled"), iterations=iterations)
    wall = time.perf_counter() - t0
    assert job.outcome is not None
    return {
        "iterations": iterations,
        "transitions_per_iteration": sc.finetune.num_envs * sc.finetune.num_steps_per_env,
        "wall_s": wall,
        "it_per_s": iterations / wall,
        "miss_rate": (job.outcome.feedback or {}).get("miss_rate"),
        "unique_states": (job.outcome.feedback or {}).get("unique_states"),
    }


def bench_fusion() -> dict[str, Any]:
    """Cost of fusing five beliefs per state with bjs-dst, per state, batched and alone."""
    import numpy as np

    from amuled_ma.fusion import fuse

    rng = np.random.default_rng(0)
    beliefs = rng.dirichlet(np.ones(4), size=(1024, 5))
    fuse(beliefs[:8], "bjs-dst")
    t0 = time.perf_counter()
    for _ in range(5):
        fuse(beliefs, "bjs-dst", return_diagnostics=True)
    batched = (time.perf_counter() - t0) / (5 * len(beliefs))
    t0 = time.perf_counter()
    for i in range(200):
        fuse(beliefs[i], "bjs-dst")
    single = (time.perf_counter() - t0) / 200
    return {"batched_ms": batched * 1e3, "single_ms": single * 1e3}


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print our figures beside the reference."""
    import torch

    torch.set_num_threads(1)
    with output_folder(args.out, "amuled-bench-") as out:
        rows = _measure(args, out)
    widths = [
        max(len(r[i]) for r in [("figure", "ours", "reference", "target"), *rows]) for i in range(4)
    ]
    line = "  ".join(f"{{:<{w}}}" for w in widths)
    print()
    print(line.format("figure", "ours", "reference (authors' code)", "target"))
    print(line.format(*("-" * w for w in widths)))
    for row in rows:
        print(line.format(*row))
    print(f"\n(torch threads: {torch.get_num_threads()}; quick: {args.quick})")
    return 0


def _measure(args: argparse.Namespace, out: Path) -> list[tuple[str, str, str, str]]:
    """Run the selected parts into ``out``; one table row per figure."""
    from amuled_ma.evaluate.evaluator import summarize
    from amuled_ma.evaluate.report import format_stat  # here: it imports torch

    rows: list[tuple[str, str, str, str]] = []

    def add(figure: str, ours: str, reference: str) -> None:
        rows.append((figure, ours, *REFERENCE[reference]))

    fm: dict[str, Any] = {}
    if "findmilk" not in args.skip:
        print("FindMilk base training ...", flush=True)
        fm = bench_base("findmilk", out, args.quick)
        optimal = [r["steps_to_milk"] == 14 for r in fm["final"]]
        opt = fm["optimal"]
        first = f"{opt['steps']:,} steps, {opt['wall_s']:.1f} s" if opt else "not reached"
        add("FindMilk greedy first optimal (14 steps, 100%)", first, "findmilk_optimal_s")
        add(
            f"FindMilk base run ({fm['steps']:,} steps)",
            f"{fm['full_s']:.1f} s ({fm['steps_per_s']:,.0f} steps/s)",
            "findmilk_full_s",
        )
        add(
            "FindMilk final greedy optimal",
            f"{100 * sum(optimal) / len(optimal):.0f}%",
            "final_optimal",
        )
    if "driving" not in args.skip:
        print("Driving base training ...", flush=True)
        dr = bench_base("driving", out, args.quick)
        metrics = summarize(dr["final"])
        add(f"Driving base run ({dr['steps']:,} steps)", f"{dr['full_s']:.1f} s", "driving_full_s")
        for key, ref in (
            ("collisions", "driving_collisions"),
            ("rescues", "driving_grandmas"),
            ("lane_changes", "driving_lane_changes"),
        ):
            if key in metrics:
                add(f"Driving greedy {key} / episode", format_stat(metrics[key]), ref)
    if "finetune" not in args.skip:
        print("Fine-tuning with replayed AMULED feedback ...", flush=True)
        ft = bench_finetune(out, fm.get("checkpoint"), args.quick)
        if "skipped" in ft:
            add("Fine-tune, 1,000 it x 128 steps", ft["skipped"], "finetune_s")
        else:
            add(
                f"Fine-tune, {ft['iterations']:,} it x "
                f"{ft['transitions_per_iteration']} steps (replay)",
                f"{ft['wall_s']:.1f} s ({ft['it_per_s']:.1f} it/s, miss rate "
                f"{100 * (ft['miss_rate'] or 0):.2f}%)",
                "finetune_s",
            )
    if "fusion" not in args.skip:
        fu = bench_fusion()
        add(
            "bjs-dst fusion of 5 beliefs, per state",
            f"{fu['batched_ms']:.4f} ms batched, {fu['single_ms']:.3f} ms alone",
            "fusion_ms",
        )
    return rows
