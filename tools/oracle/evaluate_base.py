#!/usr/bin/env python3
"""Evaluate the bases the authors' ppo.py trained here (run_base.sh) with OUR evaluator.

    python3 tools/oracle/evaluate_base.py AUTHORS_CHECKOUT OUT [--task findmilk]
        [--amuled /work/main/.venv/bin/amuled] [--episodes 50] [--results FILE.json]
        [--tie-break random|first]

Uses the package only through its command line (``amuled import authors --only policies``,
``amuled evaluate``). For each finished seed folder ``OUT/<task>-base/seed<S>`` a checkout
in the authors' layout (``models/<Env>_42/base.cleanrl_model``, the oracle's base) is
imported, and the imported ``base`` folders are gathered into ONE run folder
``OUT/eval-base-<task>/run`` as seed replicas (``base``, ``base.seed43``, ...); their
published base is imported and evaluated the same way in ``OUT/eval-base-<task>/published``.
Both runs' ``config.json`` get ``scenario.evaluation.seed = 42`` (the authors' notebook: env
seeds 42..91) and, on FindMilk, ``scenario.task.options.tie_break`` (default ``random``:
the authors' environment, ``environments/milk.py:106-112``; the import writes the plain
scenario, whose default is ``first``); then ``amuled evaluate RUN --modes greedy sampled
--episodes 50``. The evaluation folder is ``OUT/eval-base-<task>`` (``-ties-first`` added
with ``--tie-break first``). A summary (mean of per-seed means, 95% t-interval over
the seeds, and each seed) goes to ``OUT/eval-base-<task>/summary.md``; ``--results`` also
writes it as a small JSON file (per seed and mode, every metric's mean, and each run's
``oracle-done`` timing).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

ENVS = {"findmilk": "FindMilk-v4", "driving": "Driving"}
METRICS = {
    "findmilk": ["steps_to_milk", "crying_pacified", "sleeping_woken", "reached_milk"],
    "driving": ["collisions", "rescues", "lane_changes", "non_straight_steps"],
}
MODES = ("greedy", "sampled")


def run(cmd: list[str]) -> None:
    """Run a command under ``nice -n 19``, echoing it; stop on failure."""
    print("+", " ".join(cmd), flush=True)
    subprocess.run(["nice", "-n", "19", *cmd], check=True)


def import_base(amuled: str, base: Path, env: str, task: str, work: Path) -> Path:
    """Import one CleanRL base through a checkout of the authors' layout; its run folder."""
    ck = work / "checkout/models" / f"{env}_42"
    ck.mkdir(parents=True)
    shutil.copy2(base, ck / "base.cleanrl_model")
    imports = work / "imports"
    run([amuled, "import", "authors", str(work / "checkout"), "--only", "policies",
         "--runs", str(imports)])  # fmt: skip
    return imports / "authors" / task


def evaluate(
    amuled: str, folder: Path, seeds: list[int] | None, episodes: int, tie_break: str | None
) -> dict:
    """Set the authors' evaluation seeds (and tie-break) in config.json, evaluate, read results."""
    cfg = json.loads((folder / "config.json").read_text())
    cfg["scenario"]["evaluation"]["seed"] = 42
    if tie_break:
        cfg["scenario"]["task"].setdefault("options", {})["tie_break"] = tie_break
    if seeds:
        cfg["seeds"] = seeds
    (folder / "config.json").write_text(json.dumps(cfg, indent=2))
    run([amuled, "evaluate", str(folder), "--modes", *MODES, "--episodes", str(episodes),
         "--no-progress"])  # fmt: skip
    return json.loads((folder / "results.json").read_text())


def main() -> int:
    """Import, gather and evaluate the oracle's bases and the published one; summarise."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("authors", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--task", default="findmilk", choices=sorted(ENVS))
    ap.add_argument("--amuled", default="/work/main/.venv/bin/amuled")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--results", type=Path, default=None, help="also write a JSON summary")
    ap.add_argument("--tie-break", default="random", choices=["random", "first"])
    args = ap.parse_args()
    env, authors, out = ENVS[args.task], args.authors.resolve(), args.out.resolve()
    metrics = METRICS[args.task]

    found: dict[int, Path] = {}
    for w in sorted((out / f"{args.task}-base").glob("seed*")):
        seed = int(w.name[4:])
        model = w / f"models/{env}_{seed}/base.cleanrl_model"
        if (w / "oracle-done").is_file() and model.is_file():
            found[seed] = model
    if not found:
        print(f"no finished oracle base under {out}/{args.task}-base", file=sys.stderr)
        return 1
    seeds = sorted(found)
    tie_break = args.tie_break if args.task == "findmilk" else None
    ev = out / (f"eval-base-{args.task}" + ("-ties-first" if tie_break == "first" else ""))
    shutil.rmtree(ev, ignore_errors=True)
    rundir = ev / "run"

    # the published base: a run of its own
    pub_imported = import_base(
        args.amuled, authors / f"models/{env}_42/base.cleanrl_model", env, args.task,
        ev / "work/published",
    )  # fmt: skip
    pubrun = ev / "published"
    pubrun.mkdir(parents=True)
    shutil.copy2(pub_imported / "config.json", pubrun / "config.json")
    shutil.copytree(pub_imported / "base", pubrun / "base")
    rundir.mkdir(parents=True)
    shutil.copy2(pub_imported / "config.json", rundir / "config.json")

    # each oracle seed's base, gathered as replicas of one variant
    for seed in seeds:
        imported = import_base(args.amuled, found[seed], env, args.task, ev / f"work/seed{seed}")
        target = "base" if seed == seeds[0] else f"base.seed{seed}"
        shutil.move(str(imported / "base"), rundir / target)

    res = evaluate(args.amuled, rundir, seeds, args.episodes, tie_break)
    pub = evaluate(args.amuled, pubrun, None, args.episodes, tie_break)

    summary: dict = {
        "task": args.task,
        "evaluation": f"our evaluator, {args.episodes} episodes, env seeds 42-{41 + args.episodes}",
        "scenario_task_options": json.loads((rundir / "config.json").read_text())["scenario"][
            "task"
        ].get("options", {}),
        "oracle_bases": {},
        "published_base": {},
        "training": {},
    }
    lines = [
        f"# The authors' ppo.py bases, {args.task} (our evaluator, {args.episodes} episodes, "
        f"env seeds 42-{41 + args.episodes})",
        "",
        "| policy | mode | seeds | " + " | ".join(metrics) + " |",
        "|---|---|---|" + "---|" * len(metrics),
    ]
    runs = (("oracle bases", res, "oracle_bases"), ("published base", pub, "published_base"))
    for label, results, key in runs:
        entry = results["variants"]["base"]
        for mode in MODES:
            s = entry[mode]
            m = s["metrics"]
            cells = [
                f"{m[k]['mean']:.2f} ± {m[k]['half_width']:.2f}" if k in m else "-" for k in metrics
            ]
            lines.append(
                f"| {label} | {mode} | {s.get('n_seeds', 1)} | " + " | ".join(cells) + " |"
            )
            reps = s.get("replicas") or {"base": m}
            summary[key][mode] = {
                "mean": {k: round(m[k]["mean"], 4) for k in metrics if k in m},
                "half_width": {k: round(m[k]["half_width"], 4) for k in metrics if k in m},
                "per_seed": {
                    rep: {k: round(r[k]["mean"], 4) for k in metrics if k in r}
                    for rep, r in reps.items()
                },
            }
    lines.append("")
    for mode in MODES:
        for rep, r in summary["oracle_bases"][mode]["per_seed"].items():
            lines.append(f"- {mode} {rep}: " + " / ".join(f"{r[k]:.2f}" for k in metrics if k in r))
    for seed in seeds:
        done = json.loads((out / f"{args.task}-base/seed{seed}/oracle-done").read_text())
        summary["training"][str(seed)] = done
        lines.append(f"- training seed {seed}: {done}")
    (ev / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    if args.results:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
