#!/usr/bin/env python3
"""Tabulate switch_bases.py's arms and fine-tunes against the oracle's bases (Welch's t).

    PYTHONPATH=. .venv/bin/python tools/oracle/switch_table.py OUT --task findmilk \
        --oracle /work/oracle-out/eval-base-findmilk/run [--json tools/oracle/results/F.json]

Reads ``results.json`` of every ``OUT/<task>/<arm>`` (variant ``base``) and
``OUT/<task>/finetune-from-<label>`` (variant ``finetune-amuled``) and of the oracle's
evaluated bases (``evaluate_base.py``'s ``OUT/eval-base-<task>/run``, or the same folder
evaluated again). Per seed, the mean over the 50 episodes; per row, the mean over seeds with
its 95% t-interval; each arm against the oracle, and against the ``ours`` arm where it is
there, with Welch's t (``scipy.stats.ttest_ind``, ``equal_var=False``) on the per-seed
means, with the difference's 95% interval. Prints a Markdown table per mode; ``--json``
writes every per-seed mean, the summaries and the tests.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from scipy import stats

METRICS = {
    "findmilk": ["steps_to_milk", "crying_pacified", "sleeping_woken", "reached_milk"],
    "driving": ["collisions", "rescues", "lane_changes", "non_straight_steps"],
}


def per_seed(results: Path, variant: str, mode: str) -> dict[str, dict[str, float]]:
    """``{replica folder: {metric: mean over episodes}}`` of one variant in one mode."""
    entry = json.loads(results.read_text())["variants"][variant][mode]
    reps = entry.get("replicas") or {variant: entry["metrics"]}
    return {rep: {k: float(v["mean"]) for k, v in m.items()} for rep, m in reps.items()}


def summary(values: list[float]) -> tuple[float, float]:
    """Mean over seeds and the half-width of its 95% Student-t interval."""
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, math.nan
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    return mean, float(stats.t.ppf(0.975, n - 1)) * sd / math.sqrt(n)


def welch(a: list[float], b: list[float]) -> dict[str, float]:
    """Welch's t of a against b: t, df, the two-sided p, and mean(a) - mean(b) with its 95% CI."""
    test = stats.ttest_ind(a, b, equal_var=False)
    ci = test.confidence_interval(0.95)
    diff = sum(a) / len(a) - sum(b) / len(b)
    return {
        "t": float(test.statistic),
        "df": float(test.df),
        "p": float(test.pvalue),
        "diff": diff,
        "low": float(ci.low),
        "high": float(ci.high),
    }


def main() -> int:
    """Print the tables (and write the JSON) of one task."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--task", default="findmilk", choices=sorted(METRICS))
    ap.add_argument("--oracle", type=Path, required=True, help="the oracle's evaluated run")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    metrics = METRICS[args.task]
    rows: dict[str, tuple[Path, str]] = {"oracle (their ppo.py)": (args.oracle, "base")}
    for folder in sorted((args.out / args.task).iterdir()):
        if (folder / "results.json").is_file():
            variant = "finetune-amuled" if folder.name.startswith("finetune-from-") else "base"
            rows[folder.name] = (folder, variant)
    data: dict = {"task": args.task, "modes": {}}
    for mode in ("sampled", "greedy"):
        table = {}
        oracle = per_seed(args.oracle / "results.json", "base", mode)
        for name, (folder, variant) in rows.items():
            seeds = per_seed(folder / "results.json", variant, mode)
            row: dict = {"per_seed": seeds, "metrics": {}}
            for k in metrics:
                values = [s[k] for s in seeds.values() if k in s]
                if not values:
                    continue
                mean, half = summary(values)
                cell: dict = {"mean": mean, "half_width": half, "n": len(values)}
                theirs = [s[k] for s in oracle.values() if k in s]
                if variant == "base" and name != "oracle (their ppo.py)" and len(theirs) > 1:
                    cell["welch_vs_oracle"] = welch(values, theirs)
                if variant == "base" and name not in ("ours", "oracle (their ppo.py)"):
                    ours_dir = args.out / args.task / "ours"
                    if (ours_dir / "results.json").is_file():
                        mine = per_seed(ours_dir / "results.json", "base", mode)
                        cell["welch_vs_ours"] = welch(values, [m[k] for m in mine.values()])
                row["metrics"][k] = cell
            seconds = folder / "seconds.json"
            if seconds.is_file():
                row["train_seconds"] = json.loads(seconds.read_text())
            table[name] = row
        data["modes"][mode] = table
        print(f"\n{args.task}, {mode} (mean over seeds ± 95% t; Welch's t against the oracle)\n")
        print("| row | seeds | " + " | ".join(metrics) + " |")
        print("|---|---|" + "---|" * len(metrics))
        for name, row in table.items():
            cells = []
            for k in metrics:
                c = row["metrics"].get(k)
                if c is None:
                    cells.append("-")
                    continue
                text = f"{c['mean']:.2f} ± {c['half_width']:.2f}"
                w = c.get("welch_vs_oracle")
                if w is not None and math.isfinite(w["t"]):
                    text += f" (t {w['t']:.2f}, df {w['df']:.1f}, p {w['p']:.2f})"
                cells.append(text)
            print(f"| {name} | {len(row['per_seed'])} | " + " | ".join(cells) + " |")
        effects = [
            f"- {name} - ours, {k}: {c['welch_vs_ours']['diff']:+.2f} "
            f"[{c['welch_vs_ours']['low']:+.2f}, {c['welch_vs_ours']['high']:+.2f}] "
            f"(t {c['welch_vs_ours']['t']:.2f}, p {c['welch_vs_ours']['p']:.2f})"
            for name, row in table.items()
            for k, c in row["metrics"].items()
            if "welch_vs_ours" in c
        ]
        print("\n".join(effects))
        for name, row in table.items():
            for rep, m in row["per_seed"].items():
                print(f"- {name} {rep}: " + " / ".join(f"{m[k]:.2f}" for k in metrics if k in m))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
