"""``amuled study analyze``: the study's report (``analysis/report.md``, ``summary.json``)."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

from amuled_ma.study.analysis import (
    agreement,
    attentive,
    bootstrap_strengths,
    bradley_terry,
    comparisons,
    load,
    majorities,
    pair_answers,
    reliability,
    win_rates,
)

#: choix's regularisation in the report (a variant that never loses keeps a finite strength).
ALPHA = 0.01


def _f(value: float, digits: int = 3) -> str:
    return "n/a" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def summarize(folder: Path, *, keep_inattentive: bool = False) -> dict[str, Any]:
    """Every figure of the report, as JSON-ready data."""
    study, answers = load(folder)
    everyone = {a.participant for a in answers}
    kept = everyone if keep_inattentive else attentive(study, answers)
    used = [a for a in answers if a.participant in kept]
    pairs = pair_answers(study, used)
    games = comparisons(pairs)
    by_person: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for (answer, _), game in zip(pairs, games, strict=True):
        by_person[answer.participant].append(game)
    strengths = bradley_terry(study.variants, games, ALPHA)
    low, high = bootstrap_strengths(study.variants, by_person, seed=study.seed, alpha=ALPHA)
    majority = majorities(pairs)
    agree = agreement(study, majority)
    disagreements = []
    for item_id, (top, n_top, n) in majority.items():
        item = study.item(item_id)
        if item is None or item.panel is None:
            continue
        fused = [item.panel.fused[o.action] for o in item.options]
        chosen = 0 if top == "A" else 1
        gap = fused[1 - chosen] - fused[chosen]
        if gap > 0:
            disagreements.append(
                {"item": item_id, "majority": top, "votes": f"{n_top}/{n}", "fused_gap": gap,
                 "view": f"amuled view {study.runs[item.run]} --variant "
                         f"{study.folders[item.run][item.met_by]} --episode {item.episode}",
                 "step": item.step}
            )  # fmt: skip
    disagreements.sort(key=lambda d: -d["fused_gap"])
    return {
        "participants": len(everyone),
        "kept": len(kept),
        "answers": len(used),
        "pairs_answered": len(pairs),
        "win_rates": [w.__dict__ for w in win_rates(study.variants, games)],
        "bradley_terry": [
            {"variant": v, "strength": float(s), "low": float(lo), "high": float(hi)}
            for v, s, lo, hi in zip(study.variants, strengths, low, high, strict=True)
        ],
        "krippendorff_alpha": reliability(pairs),
        "agreement": {k: {"agree": a, "n": n, "rate": a / n} for k, (a, n) in agree.items()},
        "disagreements": disagreements[:10],
    }


def write_analysis(folder: Path, *, keep_inattentive: bool = False) -> Path:
    """Write ``<study>/analysis/report.md`` and ``summary.json``; return the report's path."""
    folder = Path(folder)
    data = summarize(folder, keep_inattentive=keep_inattentive)
    out = folder / "analysis"
    out.mkdir(exist_ok=True)
    (out / "summary.json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    lines = [
        f"# Study {folder.name}: what people chose",
        "",
        f"{data['participants']} participants, {data['kept']} kept "
        f"({'all' if keep_inattentive else 'those who passed every attention check'}); "
        f"{data['pairs_answered']} answers to pairs.",
        "",
        "## Win rates (chosen / shown, Wilson 95% interval)",
        "",
        "| variant | wins | shown | rate | 95% interval |",
        "|---|---:|---:|---:|---|",
    ]
    for w in data["win_rates"]:
        lines.append(
            f"| {w['variant']} | {w['wins']} | {w['n']} | {_f(w['rate'])} | "
            f"{_f(w['low'])} to {_f(w['high'])} |"
        )
    lines += [
        "",
        "## Bradley-Terry strengths (log scale, mean 0; choix, regularisation "
        f"{ALPHA}; 95% bootstrap over participants)",
        "",
        "| variant | strength | 95% interval |",
        "|---|---:|---|",
    ]
    for b in data["bradley_terry"]:
        lines.append(
            f"| {b['variant']} | {_f(b['strength'])} | {_f(b['low'])} to {_f(b['high'])} |"
        )
    lines += [
        "",
        f"## Inter-rater reliability\n\nKrippendorff's alpha (nominal, choices A/B over the "
        f"pairs): {_f(data['krippendorff_alpha'])}.",
        "",
        "## Agreement with the participants' majority",
        "",
        "A panel member or the fused belief agrees when it believes more in the majority's "
        "option's action; a policy when it takes that action in the state.",
        "",
        "| who | agrees | counted | rate |",
        "|---|---:|---:|---:|",
    ]
    for who, a in sorted(data["agreement"].items()):
        lines.append(f"| {who} | {a['agree']} | {a['n']} | {_f(a['rate'])} |")
    lines += ["", "## Where people and the fused belief disagree most", ""]
    if not data["disagreements"]:
        lines.append("None: the fused belief sides with the majority on every item.")
    for d in data["disagreements"]:
        lines.append(
            f"- {d['item']}: majority {d['majority']} ({d['votes']}), the fused belief "
            f"prefers the other by {_f(d['fused_gap'])}; see `{d['view']}` at step {d['step']}"
        )
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
