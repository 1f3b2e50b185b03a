#!/usr/bin/env python3
"""Switch one CleanRL habit of the authors' base training at a time, on our side; fine-tune.

    PYTHONPATH=. .venv/bin/python tools/oracle/switch_bases.py OUT --task findmilk \
        --arms authors joint reshuffle ours --seeds 42 43 44 45 46
    PYTHONPATH=. .venv/bin/python tools/oracle/switch_bases.py OUT --task findmilk \
        --finetune-from oracle=/work/oracle-out/eval-base-findmilk/run --seeds 42 43 44 45 46

Arms (``[base]`` keys on ``scenarios/<task>-authors.toml``, every other key as shipped):
``ours`` rsl-rl's loop (``grad_clip = "per_network"``, one mini-batch partition per update,
the value bootstrapped at the 300-step limit), ``joint``, ``reshuffle`` and
``no-bootstrap`` each switch one of the three to the authors' ``algorithms/ppo.py``
(:315, :268-269, :230), ``authors`` all three (the shipped ``recipe = "authors"`` bases).
Each arm's seeds train as one population (``amuled_ma.experiments.jobs.run_jobs``) into
``OUT/<task>/<arm>/base`` (first seed) and ``base.seed<S>``, then ``amuled evaluate`` plays
them greedy and sampled, 50 episodes, env seeds 42-91, as ``evaluate_base.py`` plays the
oracle's; ``OUT/<task>/<arm>/seconds.json`` holds the arm's training wall time.

``--finetune-from LABEL=RUN`` fine-tunes ``finetune:amuled`` with the authors' recipe (the
shipped ``<task>-authors`` scenario) from each seed's base in RUN (``base`` for the first
seed, ``base.seed<S>``: an arm's folder, or the oracle's imported bases of
``evaluate_base.py``), all seeds as one population, into
``OUT/<task>/finetune-from-LABEL``, then evaluates them: the AMULED row of
``amuled run <task> --recipe authors --seeds N`` from those bases. ``--finetune-rollout N``
sets the fine-tunes' steps per iteration (``[finetune].num_steps_per_env``; their
``finetune_moral.py:54``: "note it is 64 for Milk").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from amuled_ma.experiments.jobs import run_jobs
from amuled_ma.experiments.pipeline import describe_job
from amuled_ma.experiments.run_folder import TrainJob, replica_folder, write_config
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

OURS = {"grad_clip": "per_network", "reshuffle_each_epoch": False, "bootstrap_time_outs": True}
ARMS: dict[str, dict[str, object]] = {
    "ours": {},
    "joint": {"grad_clip": "joint"},
    "reshuffle": {"reshuffle_each_epoch": True},
    "no-bootstrap": {"bootstrap_time_outs": False},
    "authors": {"grad_clip": "joint", "reshuffle_each_epoch": True, "bootstrap_time_outs": False},
}


def evaluate(amuled: str, run_dir: Path, scenario, seeds: list[int]) -> None:
    """Write the run's config.json (its seeds) and evaluate it greedy and sampled, 50 episodes."""
    write_config(run_dir, scenario.to_dict(), {"seeds": seeds})
    subprocess.run(
        [
            amuled,
            "evaluate",
            str(run_dir),
            "--modes",
            "greedy",
            "sampled",
            "--episodes",
            "50",
            "--no-progress",
        ],
        check=True,
    )


def train(jobs: list[TrainJob], run_dir: Path) -> None:
    """Train the jobs (populations, in this process) and record the wall time."""
    t0 = time.perf_counter()
    run_jobs(jobs, workers=1, describe=describe_job)
    seconds = round(time.perf_counter() - t0, 1)
    (run_dir / "seconds.json").write_text(json.dumps({"seconds": seconds, "jobs": len(jobs)}))
    print(f"{run_dir}: {len(jobs)} jobs in {seconds} s", flush=True)


def main() -> int:
    """Train and evaluate the arms (or the fine-tunes) named on the command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--task", default="findmilk", choices=["findmilk", "driving"])
    ap.add_argument("--arms", nargs="*", default=[], choices=sorted(ARMS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[42, 43, 44, 45, 46])
    ap.add_argument("--finetune-from", nargs="*", default=[], metavar="LABEL=RUN")
    ap.add_argument("--total-steps", type=int, default=None, help="shortened bases (a smoke run)")
    ap.add_argument("--iterations", type=int, default=None, help="shortened fine-tunes")
    ap.add_argument(
        "--finetune-rollout",
        type=int,
        default=None,
        help="fine-tune steps per iteration (finetune_moral.py:54: 'note it is 64 for Milk')",
    )
    ap.add_argument("--amuled", default=str(Path(sys.executable).parent / "amuled"))
    args = ap.parse_args()
    shipped = load_scenario(f"{args.task}-authors")
    if args.total_steps is not None:
        shipped = shipped.replace("base", total_steps=args.total_steps)
    if args.iterations is not None:
        shipped = shipped.replace("finetune", iterations=args.iterations)
    if args.finetune_rollout is not None:
        shipped = shipped.replace("finetune", num_steps_per_env=args.finetune_rollout)
    first = args.seeds[0]
    for arm in args.arms:
        scenario = shipped.replace("base", **{**OURS, **ARMS[arm]})
        run_dir = (args.out / args.task / arm).resolve()
        if (run_dir / "results.json").is_file():
            print(f"{run_dir}: evaluated before, skipped", flush=True)
            continue
        run_dir.mkdir(parents=True, exist_ok=True)
        jobs = [
            TrainJob(
                name=replica_folder("base", s, first),
                scenario=scenario,
                run_dir=run_dir,
                variant=Variant.parse("base"),
                out_dir=run_dir / replica_folder("base", s, first),
                seed=s,
                resume=True,
            )
            for s in args.seeds
        ]
        train(jobs, run_dir)
        evaluate(args.amuled, run_dir, scenario, args.seeds)
    for spec in args.finetune_from:
        label, _, path = spec.partition("=")
        bases = Path(path).resolve()
        run_dir = (args.out / args.task / f"finetune-from-{label}").resolve()
        run_dir.mkdir(parents=True, exist_ok=True)
        jobs = []
        for s in args.seeds:
            folder = replica_folder("finetune-amuled", s, first)
            jobs.append(
                TrainJob(
                    name=folder,
                    scenario=shipped,
                    run_dir=run_dir,
                    variant=Variant.parse("finetune:amuled"),
                    out_dir=run_dir / folder,
                    seed=s,
                    base_variant=replica_folder("base", s, first),
                    resume=True,
                    base_dir=bases,
                )
            )
        if not (run_dir / "results.json").is_file():
            train(jobs, run_dir)
            evaluate(args.amuled, run_dir, shipped, args.seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
