"""``amuled study analyze``: ``analysis/report.md``, ``summary.json`` and the study's PNG figure."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from amuled_ma.evaluate.report.plotting import pyplot, save_figure
from amuled_ma.files.safe import check_own_folder, check_write_targets, write_text_atomic
from amuled_ma.study.analysis import (
    MeanInterval,
    acceptability,
    acceptability_values,
    acceptable_sets,
    agreement,
    alpha_unavailable,
    attentive,
    bootstrap_strengths,
    bradley_terry,
    choice_values,
    clarity,
    comparisons,
    few_people,
    framework_citations,
    framework_values,
    load,
    majorities,
    nominal_alpha,
    pair_answers,
    top_action,
    unreasoned_states,
    wilson,
    win_rates,
)
from amuled_ma.study.answers import read_expert_answers
from amuled_ma.study.model import ANSWERS_FILE, NO_REASON, Item, Study, read_study

#: choix's regularisation in the report (a variant that never loses keeps a finite strength).
ALPHA = 0.01


def _f(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def _num(value: float) -> float | None:
    """A number for ``summary.json``: None for nan (JSON has no nan)."""
    return None if value is None or math.isnan(value) else float(value)


def _mean(m: MeanInterval, people: str) -> dict[str, Any]:
    """A mean, its interval, its ratings and their ``people`` for ``summary.json``."""
    numbers = {"mean": _num(m.mean), "low": _num(m.low), "high": _num(m.high)}
    return {**numbers, "ratings": m.n, people: m.people}


def _row(*cells: object) -> str:
    """A Markdown table row of ``cells``."""
    return "| " + " | ".join(str(cell) for cell in cells) + " |"


def _span(row: dict[str, Any], digits: int = 3) -> str:
    """A row's interval as the report says it: ``low to high``."""
    return f"{_f(row['low'], digits)} to {_f(row['high'], digits)}"


def _view(study: Study, item: Item) -> str:
    """The ``amuled view`` command that replays the episode an item's state comes from."""
    return (
        f"amuled view {study.runs[item.run]} --variant "
        f"{study.folders[item.run][item.met_by]} --episode {item.episode}"
    )


def _rates(counts: dict[str, list[int]]) -> dict[str, dict[str, Any]]:
    out = {}
    for who, (a, n) in counts.items():
        low, high = wilson(a, n)
        out[who] = {"agree": a, "n": n, "rate": a / n, "low": _num(low), "high": _num(high)}
    return out


def _agreement_table(rates: dict[str, dict[str, Any]]) -> list[str]:
    """The Markdown lines of who agrees how often (header, separator, a row per sorted name)."""
    lines = [
        "| who | agrees | counted | rate | 95% interval (Wilson) |",
        "|---|---:|---:|---:|---|",
    ]
    return lines + [
        _row(w, a["agree"], a["n"], _f(a["rate"]), _span(a)) for w, a in sorted(rates.items())
    ]


def summarize(folder: Path, *, keep_inattentive: bool = False) -> dict[str, Any]:
    """Every figure of the report, as JSON-ready data."""
    study, answers = load(folder)
    everyone = {a.participant for a in answers}
    kept = attentive(answers, keep_inattentive=keep_inattentive)
    used = [a for a in answers if a.participant in kept]
    pairs = pair_answers(study, used)
    games = comparisons(pairs)
    by_person: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for (answer, _), game in zip(pairs, games, strict=True):
        by_person[answer.participant].append(game)
    strengths = bradley_terry(study.variants, games, ALPHA)
    low, high = bootstrap_strengths(study.variants, by_person, seed=study.seed, alpha=ALPHA)
    rated = acceptability(study.variants, pairs, seed=study.seed)
    majority = majorities(pairs)
    accepted = {
        i: {o.action for o in item.options if o.label == top}
        for i, (top, _, _) in majority.items()
        if (item := study.item(i)) is not None
    }
    disagreements: list[dict[str, Any]] = []
    for item_id, (top, n_top, n) in majority.items():
        item = study.item(item_id)
        if item is None or item.panel is None:
            continue
        fused = [item.panel.fused[o.action] for o in item.options]
        chosen = 0 if top == "A" else 1
        gap = fused[1 - chosen] - fused[chosen]
        if gap > 0:
            disagreements.append(
                {
                    "item": item_id,
                    "majority": top,
                    "votes": f"{n_top}/{n}",
                    "fused_gap": gap,
                    "view": _view(study, item),
                    "step": item.step,
                }
            )
    disagreements.sort(key=lambda d: -d["fused_gap"])
    return {
        "mode": "pairs",
        "warnings": [w for w in [few_people(len(kept))] if w],
        "participants": len(everyone),
        "kept": len(kept),
        "answers": len(used),
        "pairs_answered": len(pairs),
        "win_rates": [w.__dict__ for w in win_rates(study.variants, games)],
        "bradley_terry": [
            {"variant": v, "strength": float(s), "low": float(lo), "high": float(hi)}
            for v, s, lo, hi in zip(study.variants, strengths, low, high, strict=True)
        ],
        "rating_points": study.rating_points,
        "answers_rated": sum(1 for a, _ in pairs if a.rating_a is not None),
        "acceptability": [{"variant": v, **_mean(m, "participants")} for v, m in rated.items()],
        "krippendorff_alpha": nominal_alpha(choice_values(pairs)),
        "krippendorff_alpha_unavailable": alpha_unavailable(choice_values(pairs)),
        "agreement": _rates(agreement(study, accepted, pairs=True)),
        "disagreements": disagreements[:10],
    }


def summarize_expert(folder: Path) -> dict[str, Any]:
    """Every figure of an expert study's report, as JSON-ready data."""
    study, _ = load(folder)
    answers = read_expert_answers(Path(folder) / ANSWERS_FILE)
    sets = acceptable_sets(answers)
    titles = dict(study.frameworks)
    clear = clarity(answers, seed=study.seed)
    unreasoned = unreasoned_states(study)
    unacceptable = []
    for item_id, (accepted, n) in sorted(sets.items()):
        item = study.item(item_id)
        if item is None or item.panel is None:
            continue
        top = top_action(item.panel.fused)
        if top is not None and top not in accepted:
            names = study.action_names.get(item.task, [])
            unacceptable.append(
                {
                    "item": item_id,
                    "fused_top": names[top],
                    "fused": item.panel.fused[top],
                    "acceptable": [names[a] for a in sorted(accepted)],
                    "experts": n,
                    "view": _view(study, item),
                    "step": item.step,
                }
            )
    experts = len({a.participant for a in answers})
    return {
        "mode": "expert",
        "warnings": [w for w in [few_people(experts, "experts")] if w],
        "experts": experts,
        "states": len(study.items),
        "states_judged": len(sets),
        "judgements": sum(len(a.judgements) for a in answers),
        "states_without_reason": len(unreasoned),
        "frameworks": [
            {
                **c.__dict__,
                "share": _num(c.share),
                "title": titles.get(c.framework, "none of these / other"),
            }
            for c in framework_citations(study, answers)
        ],
        "acceptable_sets": {
            k: {"acceptable": sorted(v[0]), "experts": v[1]} for k, v in sorted(sets.items())
        },
        "agreement": _rates(agreement(study, {k: v[0] for k, v in sets.items()})),
        "clarity": {**_mean(clear, "experts"), "points": study.clarity_points},
        "alpha_acceptable": _num(nominal_alpha(acceptability_values(answers))),
        "alpha_framework": _num(nominal_alpha(framework_values(study, answers))),
        "alpha_acceptable_unavailable": alpha_unavailable(acceptability_values(answers)),
        "alpha_framework_unavailable": alpha_unavailable(framework_values(study, answers)),
        "fused_unacceptable": unacceptable[:10],
    }


def _alpha(value: float | None, unavailable: str | None) -> str:
    """An alpha as the report says it: the number, or ``n/a (why)``."""
    return f"n/a ({unavailable})" if value is None or unavailable else _f(value)


def _warnings(data: dict[str, Any]) -> list[str]:
    """The report's warning lines (``**Warning:** ...``), each followed by a blank line."""
    return [line for w in data["warnings"] for line in (f"**Warning:** {w}.", "")]


def write_analysis(
    folder: Path,
    *,
    keep_inattentive: bool = False,
    warn: Callable[[str], None] | None = None,
) -> Path:
    """Write ``<study>/analysis/``'s report (returned), summary and figure; ``warn`` each warning.

    UnsafePathError: ``analysis`` or an output there is a link or not a folder or file.
    """
    folder = Path(folder)
    expert_mode = read_study(folder).mode == "expert"
    figure = "expert.png" if expert_mode else "strengths.png"
    out = folder / "analysis"
    check_own_folder(
        out,
        "the analysis is written only into the study's own analysis/ folder, never through "
        "a link; nothing was written; remove it, then run the command again",
    )
    out.mkdir(exist_ok=True)
    check_write_targets([out / "summary.json", out / "report.md", out / figure])
    if expert_mode:
        data = summarize_expert(folder)
    else:
        data = summarize(folder, keep_inattentive=keep_inattentive)
    for line in data["warnings"]:
        if warn is not None:
            warn(line)
    write_text_atomic(out / "summary.json", json.dumps(data, indent=2) + "\n")
    if expert_mode:
        expert_figure(data, out / figure)
        lines = _expert_report(folder, data)
    else:
        strengths_figure(data, out / figure)
        lines = _pairs_report(folder, data, keep_inattentive)
    return write_text_atomic(out / "report.md", "\n".join(lines) + "\n")


def _pairs_report(folder: Path, data: dict[str, Any], keep_inattentive: bool) -> list[str]:
    """The lines of a pairs study's ``report.md``."""
    lines = [
        f"# Study {folder.name}: what people chose",
        "",
        f"{data['participants']} participants, {data['kept']} kept "
        f"({'all' if keep_inattentive else 'those who passed every attention check'}); "
        f"{data['pairs_answered']} answers to pairs.",
        "",
        *_warnings(data),
        "## Win rates (chosen / shown, Wilson 95% interval)",
        "",
        "| variant | wins | shown | rate | 95% interval |",
        "|---|---:|---:|---:|---|",
    ]
    lines += [
        _row(w["variant"], w["wins"], w["n"], _f(w["rate"]), _span(w)) for w in data["win_rates"]
    ]
    lines += [
        "",
        "## Bradley-Terry strengths (log scale, mean 0; choix, regularisation "
        f"{ALPHA}; 95% bootstrap over participants)",
        "",
        "| variant | strength | 95% interval |",
        "|---|---:|---|",
    ]
    lines += [_row(b["variant"], _f(b["strength"]), _span(b)) for b in data["bradley_terry"]]
    points = data["rating_points"]
    lines += [
        "",
        f"## Acceptability (ratings 1 to {points}; mean, 95% bootstrap over participants)",
        "",
        f"Each shown decision was rated from 1 (completely unacceptable) to {points} "
        "(completely acceptable); a rating counts for the variant that took the decision. The "
        "interval is the 2.5th to 97.5th percentile of the mean over 2000 resamples of the "
        "participants (a participant's ratings stay together).",
        "",
    ]
    if not data["answers_rated"]:
        lines.append(
            "No ratings stored: the answers kept were given before the study asked for ratings."
        )
    else:
        lines += [
            "| variant | mean | 95% interval | ratings | participants |",
            "|---|---:|---|---:|---:|",
        ]
        lines += [
            _row(r["variant"], _f(r["mean"], 2), _span(r, 2), r["ratings"], r["participants"])
            for r in data["acceptability"]
        ]
    lines += [
        "",
        "![Bradley-Terry strengths and acceptability](strengths.png)",
        "",
        f"## Inter-rater reliability\n\nKrippendorff's alpha (nominal, choices A/B over the "
        f"pairs): {_alpha(data['krippendorff_alpha'], data['krippendorff_alpha_unavailable'])}.",
        "",
        "## Agreement with the participants' majority",
        "",
        "A panel member or the fused belief agrees when it believes more in the majority's "
        "option's action; a policy when it takes that action in the state.",
        "",
    ]
    lines += _agreement_table(data["agreement"])
    lines += ["", "## Where people and the fused belief disagree most", ""]
    lines += [
        f"- {d['item']}: majority {d['majority']} ({d['votes']}), the fused belief prefers "
        f"the other by {_f(d['fused_gap'])}; see `{d['view']}` at step {d['step']}"
        for d in data["disagreements"]
    ] or ["None: the fused belief sides with the majority on every item."]
    return lines


def _expert_report(folder: Path, data: dict[str, Any]) -> list[str]:
    """The lines of an expert study's ``report.md``."""
    no_reason = data["states_without_reason"]
    lines = [
        f"# Study {folder.name}: what the experts judged",
        "",
        f"{data['experts']} experts judged {data['states_judged']} of {data['states']} states "
        f"({data['judgements']} judgements of an action).",
        "",
        *_warnings(data),
        "## Frameworks the experts cite",
        "",
        "| framework | cited | share | on actions found acceptable | by action |",
        "|---|---:|---:|---:|---|",
    ]
    for c in data["frameworks"]:
        actions = ", ".join(f"{a} {k}" for a, k in c["by_action"].items()) or "-"
        lines.append(_row(c["title"], c["cited"], _f(c["share"], 2), c["acceptable"], actions))
    clear = data["clarity"]
    lines += [
        "",
        "## Agreement with the experts",
        "",
        "A state's acceptable actions are those more than half of its experts found "
        "acceptable. A panel member or the fused belief agrees when the action it believes "
        "most is one of them (a tie at the top is not counted); a policy when its action is.",
        "",
    ]
    lines += _agreement_table(data["agreement"])
    lines += [
        "",
        f"## Clarity of the panel's reasons (1 to {clear['points']})",
        "",
        f"Mean {_f(clear['mean'], 2)}, 95% interval {_span(clear, 2)} (bootstrap over "
        f"experts, 2000 resamples), from {clear['ratings']} ratings by {clear['experts']} experts.",
        "",
    ]
    if no_reason:
        lines.append(
            f"{no_reason} of {data['states']} states had no stated reason recorded ('{NO_REASON}' "
            "on the page): the panel's replies were not kept (a rules panel, or a recording of "
            "beliefs only), so clarity was not asked there."
        )
    else:
        lines.append("Every state had at least one stated reason.")
    lines += [
        "",
        "## Inter-expert reliability",
        "",
        "Krippendorff's alpha (nominal) over (state, action): acceptable or not "
        f"{_alpha(data['alpha_acceptable'], data['alpha_acceptable_unavailable'])}; the "
        f"framework cited {_alpha(data['alpha_framework'], data['alpha_framework_unavailable'])}.",
        "",
        "![Frameworks cited and agreement with the experts](expert.png)",
        "",
        "## Where the fused belief's top action is unacceptable to the experts",
        "",
    ]
    lines += [
        f"- {d['item']}: the fused belief prefers {d['fused_top']} ({_f(d['fused'])}); "
        f"the experts ({d['experts']}) accept {', '.join(d['acceptable']) or 'nothing'}; "
        f"see `{d['view']}` at step {d['step']}"
        for d in data["fused_unacceptable"]
    ] or ["None: the fused belief's top action is acceptable on every state judged."]
    return lines


def _interval_bars(ax: Any, names: Sequence[str], rows: Sequence[Mapping[str, Any]],
                   key: str) -> None:  # fmt: skip
    """Points with horizontal 95% intervals, one row per name (top to bottom)."""
    ys = list(range(len(names)))[::-1]
    for y, row in zip(ys, rows, strict=True):
        value, low, high = row[key], row["low"], row["high"]
        if value is None or not math.isfinite(value):
            ax.text(0.02, y, "no data", va="center", transform=ax.get_yaxis_transform())
            continue
        if low is not None and math.isfinite(low) and math.isfinite(high):
            ax.plot([low, high], [y, y], color="#555", lw=2, solid_capstyle="butt")
        ax.plot([value], [y], "o", color="#1d3557", ms=7)
        ax.annotate(f"{value:.2f}", (value, y), textcoords="offset points", xytext=(0, 7),
                    ha="center", fontsize=8)  # fmt: skip
    ax.set_yticks(ys, list(names))
    ax.set_ylim(-0.7, len(names) - 0.3)
    ax.grid(axis="x", color="#ddd")


def strengths_figure(summary: Mapping[str, Any], path: Path) -> Path:
    """``strengths.png``: Bradley-Terry strengths and mean acceptability, with intervals."""
    plt = pyplot()
    bt = summary["bradley_terry"]
    acc = summary.get("acceptability") or []
    panels = 2 if acc else 1
    names = [row["variant"] for row in bt]
    fig, axes = plt.subplots(1, panels, figsize=(4.4 * panels + 0.6, 0.55 * len(names) + 1.8),
                             squeeze=False)  # fmt: skip
    ax = axes[0][0]
    _interval_bars(ax, names, bt, "strength")
    ax.axvline(0.0, color="#999", lw=1, ls="--")
    ax.set_xlabel("Bradley-Terry strength (log scale, mean 0)")
    ax.set_title("Chosen as the more acceptable", fontsize=10)
    if acc:
        ax = axes[0][1]
        _interval_bars(ax, [row["variant"] for row in acc], acc, "mean")
        points = int(summary.get("rating_points") or 7)
        ax.set_xlim(0.5, points + 0.5)
        ax.set_xticks(range(1, points + 1))
        ax.set_xlabel(f"mean rating (1: completely unacceptable,\n{points}: completely "
                      "acceptable)")  # fmt: skip
        ax.set_title("Rated acceptability", fontsize=10)
    fig.suptitle("Variants as people judged them (95% bootstrap intervals over participants)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    return save_figure(fig, path)


def expert_figure(summary: Mapping[str, Any], path: Path) -> Path:
    """``expert.png``: frameworks cited, and agreement with the experts' acceptable sets."""
    plt = pyplot()
    cites = summary["frameworks"]
    agree = summary["agreement"]
    who = sorted(agree)
    height = max(len(cites), len(who)) * 0.45 + 1.8
    fig, (left, right) = plt.subplots(1, 2, figsize=(10.5, height))
    names = [c["framework"] for c in cites][::-1]
    yes = [c["acceptable"] for c in cites][::-1]
    no = [c["cited"] - c["acceptable"] for c in cites][::-1]
    left.barh(names, yes, color="#2a9d8f", label="action found acceptable")
    left.barh(names, no, left=yes, color="#e76f51", label="found unacceptable")
    left.set_xlabel("judgements citing the framework")
    left.set_title("Frameworks the experts cite", fontsize=10)
    left.legend(fontsize=8, loc="lower right")
    rows = [agree[w] for w in who]
    _interval_bars(right, who, rows, "rate")
    right.set_xlim(-0.02, 1.02)
    right.set_xlabel("share of states where its top action\nis acceptable to the experts")
    right.set_title("Agreement with the experts (Wilson 95%)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
