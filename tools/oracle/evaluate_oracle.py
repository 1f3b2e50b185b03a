#!/usr/bin/env python3
"""Evaluate the oracle's checkpoints (and the published ones) with OUR evaluator.

    python3 tools/oracle/evaluate_oracle.py AUTHORS_CHECKOUT OUT [--task findmilk]
        [--amuled /work/main/.venv/bin/amuled] [--iteration N] [--episodes 50]

Uses the package only through its command line (``amuled import authors``,
``amuled evaluate``); needs nothing but the standard library here.

For each seed folder ``OUT/<task>-<script>/seed<S>`` that ``run_oracle.sh`` finished, a
small checkout in the authors' layout is laid out under ``OUT/eval-<task>/checkouts/seed<S>``
(``OUT/eval-<task>-it<N>/...`` with ``--iteration N``)
(their published base as ``models/<Env>_42/base.cleanrl_model``, the oracle's AMULED
checkpoint as ``moral_llm_gpt-4o-mini/ppo_<N>``, its human checkpoint as
``moral_llm_human/ppo_<N>``), converted with ``amuled import authors --only policies``,
and the converted variant folders are gathered into ONE run folder
``OUT/eval-<task>/run`` as seed replicas (``amuled-gpt-4o-mini``,
``amuled-gpt-4o-mini.seed43``, ...; ``amuled-human``, ``amuled-human.seed43``, ...), beside
the published base (``base``); the published AMULED policy is evaluated the same way in
``OUT/eval-<task>/published`` (one run of its own: the evaluator groups seed replicas by
the name in each variant's ``config.json``, and both are named ``amuled-gpt-4o-mini``). The run's
``config.json`` gets ``scenario.evaluation.seed = 42`` (the authors' notebook: env seeds 42..91; the
imported scenario says 10,000) and then ``amuled evaluate RUN --modes sampled
--episodes 50`` writes report.md / results.json there: per variant the mean of the
per-seed means and the 95% t-interval over the seeds. A summary is printed and
written to ``OUT/eval-<task>/summary.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

ENVS = {"findmilk": "FindMilk-v4", "driving": "Driving"}
SCRIPTS = {"amuled": ("moral_llm_gpt-4o-mini", "gpt-4o-mini"), "human": ("RLHF", "human")}
METRICS = {
    "findmilk": ["steps_to_milk", "crying_pacified", "sleeping_woken", "reached_milk"],
    "driving": ["collisions", "rescues", "lane_changes"],
}


def checkpoint(folder: Path, iteration: int | None) -> tuple[Path, int] | None:
    """The ``ppo_<N>.cleanrl_model`` of ``folder`` (the last one, or ``N = iteration``)."""
    found = {int(p.stem.split("_")[1]): p for p in folder.glob("ppo_*.cleanrl_model")}
    if not found:
        return None
    n = max(found) if iteration is None else iteration
    return (found[n], n) if n in found else None


def run(cmd: list[str]) -> None:
    """Run a command under ``nice -n 19``, echoing it; stop on failure."""
    print("+", " ".join(cmd), flush=True)
    subprocess.run(["nice", "-n", "19", *cmd], check=True)


def main() -> int:
    """Convert, gather and evaluate; print and write the summary."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("authors", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--task", default="findmilk", choices=sorted(ENVS))
    ap.add_argument("--amuled", default="/work/main/.venv/bin/amuled")
    ap.add_argument("--iteration", type=int, default=None, help="checkpoint N (default: last)")
    ap.add_argument("--episodes", type=int, default=50)
    args = ap.parse_args()
    env, authors, out = ENVS[args.task], args.authors.resolve(), args.out.resolve()
    base = authors / f"models/{env}_42/base.cleanrl_model"
    published = authors / f"models/{env}_42/moral_llm_gpt-4o-mini"

    # which seeds have which checkpoints
    found: dict[int, dict[str, tuple[Path, int]]] = {}
    for script, (sub, _model) in SCRIPTS.items():
        for w in sorted((out / f"{args.task}-{script}").glob("seed*")):
            if not (w / "oracle-done").is_file():
                continue
            seed = int(w.name[4:])
            ck = checkpoint(w / f"models/{env}_{seed}/{sub}", args.iteration)
            if ck:
                found.setdefault(seed, {})[script] = ck
    if not found:
        print(f"no finished oracle seed under {out}", file=sys.stderr)
        return 1
    seeds = sorted(found)
    ev = out / (f"eval-{args.task}" + (f"-it{args.iteration}" if args.iteration else ""))
    shutil.rmtree(ev, ignore_errors=True)
    rundir = ev / "run"
    rundir.mkdir(parents=True)

    # 1. the published base and AMULED policy: one import of a checkout with just those
    pub = ev / "checkouts/published/models" / f"{env}_42"
    (pub / "moral_llm_gpt-4o-mini").mkdir(parents=True)
    shutil.copy2(base, pub / "base.cleanrl_model")
    last = checkpoint(published, args.iteration) or checkpoint(published, None)
    if last:
        shutil.copy2(last[0], pub / "moral_llm_gpt-4o-mini" / last[0].name)
    run(
        [
            args.amuled,
            "import",
            "authors",
            str(ev / "checkouts/published"),
            "--only",
            "policies",
            "--runs",
            str(ev / "imports/published"),
        ]
    )
    # (the evaluator groups seed replicas by the name in each variant's config.json, so the
    # published policy, also named amuled-gpt-4o-mini, is evaluated as a run of its own)
    pubrun = ev / "published"
    shutil.move(str(ev / "imports/published/authors" / args.task), pubrun)
    shutil.copy2(pubrun / "config.json", rundir / "config.json")
    shutil.copytree(pubrun / "base", rundir / "base")

    # 2. each oracle seed: a checkout in the authors' layout, imported, gathered as replicas
    for seed in seeds:
        ck = ev / f"checkouts/seed{seed}/models" / f"{env}_42"
        ck.mkdir(parents=True)
        shutil.copy2(base, ck / "base.cleanrl_model")
        for script, (path, n) in found[seed].items():
            sub = ck / f"moral_llm_{SCRIPTS[script][1]}"
            sub.mkdir()
            shutil.copy2(path, sub / f"ppo_{n}.cleanrl_model")
        run(
            [
                args.amuled,
                "import",
                "authors",
                str(ev / f"checkouts/seed{seed}"),
                "--only",
                "policies",
                "--runs",
                str(ev / f"imports/seed{seed}"),
            ]
        )
        imported = ev / f"imports/seed{seed}/authors" / args.task
        for script in found[seed]:
            name = f"amuled-{SCRIPTS[script][1]}"
            first = min(s for s in seeds if script in found[s])
            target = name if seed == first else f"{name}.seed{seed}"
            shutil.move(str(imported / name), rundir / target)

    # 3. the authors' evaluation seeds 42..91, then our evaluator
    for folder, run_seeds in ((rundir, seeds), (pubrun, None)):
        cfg = json.loads((folder / "config.json").read_text())
        cfg["scenario"]["evaluation"]["seed"] = 42
        if run_seeds:
            cfg["seeds"] = run_seeds
        (folder / "config.json").write_text(json.dumps(cfg, indent=2))
        run(
            [
                args.amuled,
                "evaluate",
                str(folder),
                "--modes",
                "sampled",
                "--episodes",
                str(args.episodes),
                "--no-progress",
            ]
        )

    # 4. summary
    res = json.loads((rundir / "results.json").read_text())
    pub = json.loads((pubrun / "results.json").read_text())
    lines = [
        f"# Oracle evaluation, {args.task} (sampled, {args.episodes} episodes, env seeds "
        f"42-{41 + args.episodes}, our evaluator)",
        "",
        "| variant | seeds | " + " | ".join(METRICS[args.task]) + " |",
        "|---|---|" + "---|" * len(METRICS[args.task]),
    ]
    per_seed = []
    entries = list(res["variants"].items())
    entries += [(f"published {n}", e) for n, e in pub["variants"].items() if n != "base"]
    for name, entry in entries:
        s = entry["sampled"]
        m = s["metrics"]
        cells = []
        for k in METRICS[args.task]:
            v = m.get(k)
            cells.append(f"{v['mean']:.2f} ± {v['half_width']:.2f}" if v else "-")
        lines.append(f"| {name} | {s.get('n_seeds', 1)} | " + " | ".join(cells) + " |")
        for rep, r in (s.get("replicas") or {}).items():
            per_seed.append(
                f"- {rep}: "
                + " / ".join(f"{r[k]['mean']:.2f}" for k in METRICS[args.task] if k in r)
            )
    lines += ["", "Per seed (" + " / ".join(METRICS[args.task]) + "):", *per_seed]
    for seed in seeds:
        for script in found[seed]:
            done = json.loads((out / f"{args.task}-{script}/seed{seed}/oracle-done").read_text())
            lines.append(f"- run {script} seed {seed}: {done}")
    (ev / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
