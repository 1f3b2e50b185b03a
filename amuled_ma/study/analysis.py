"""The numbers of a study: win rates, Bradley-Terry strengths, reliability, agreement.

Each function takes plain data (the study and its answers) and returns plain numbers;
:mod:`amuled_ma.study.report` writes them down. Libraries do the statistics: ``choix``
(Bradley-Terry by iterative Luce spectral ranking, Maystre and Grossglauser 2015),
``krippendorff`` (Krippendorff's alpha); the intervals are Wilson's (win rates) and a
bootstrap over participants (strengths).
"""

from __future__ import annotations

import csv
import io
import math
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from amuled_ma.study.answers import Answer, read_answers
from amuled_ma.study.model import ANSWERS_FILE, Item, Study, StudyError, read_study

Z95 = 1.959963984540054


def wilson(wins: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a proportion ``wins / n`` (``(nan, nan)`` for ``n = 0``)."""
    if n == 0:
        return math.nan, math.nan
    p = wins / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def attentive(study: Study, answers: Sequence[Answer]) -> set[str]:
    """Participants who passed every attention check they answered."""
    failed = {a.participant for a in answers if a.correct == 0}
    return {a.participant for a in answers} - failed


def pair_answers(study: Study, answers: Sequence[Answer]) -> list[tuple[Answer, Item]]:
    """The answers to pairs (not attention checks), with their items."""
    out = []
    for answer in answers:
        item = study.item(answer.item)
        if item is not None and item.kind == "pair":
            out.append((answer, item))
    return out


def comparisons(pairs: Sequence[tuple[Answer, Item]]) -> list[tuple[str, str]]:
    """Each answer as ``(winner, loser)`` variant names."""
    out = []
    for answer, item in pairs:
        chosen = next(o for o in item.options if o.label == answer.choice)
        other = next(o for o in item.options if o.label != answer.choice)
        out.append((str(chosen.variant), str(other.variant)))
    return out


@dataclass(frozen=True)
class WinRate:
    """A variant's wins over the comparisons it was in, with Wilson's 95% interval."""

    variant: str
    wins: int
    n: int
    rate: float
    low: float
    high: float


def win_rates(variants: Sequence[str], games: Sequence[tuple[str, str]]) -> list[WinRate]:
    """Each variant's win rate: chosen / shown, over every comparison it took part in."""
    out = []
    for v in variants:
        wins = sum(1 for w, _ in games if w == v)
        n = sum(1 for w, lo in games if v in (w, lo))
        low, high = wilson(wins, n)
        out.append(WinRate(v, wins, n, wins / n if n else math.nan, low, high))
    return out


def bradley_terry(
    variants: Sequence[str], games: Sequence[tuple[str, str]], alpha: float = 0.0
) -> np.ndarray:
    """Bradley-Terry log-strengths (mean zero) by ``choix.ilsr_pairwise``.

    ``P(i beats j) = exp(s_i) / (exp(s_i) + exp(s_j))``. ``alpha`` adds choix's
    regularisation (needed when a variant never loses: its strength is infinite).
    """
    import choix

    index = {v: i for i, v in enumerate(variants)}
    data = [(index[w], index[lo]) for w, lo in games]
    if not data:
        return np.full(len(variants), math.nan)
    params = np.asarray(choix.ilsr_pairwise(len(variants), data, alpha=alpha), dtype=float)
    return params - params.mean()


def bootstrap_strengths(
    variants: Sequence[str],
    games_by_participant: dict[str, list[tuple[str, str]]],
    *,
    resamples: int = 200,
    seed: int = 0,
    alpha: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """95% percentile intervals of the strengths, resampling participants with replacement."""
    people = sorted(games_by_participant)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(resamples):
        chosen = rng.integers(len(people), size=len(people))
        games = [g for i in chosen for g in games_by_participant[people[i]]]
        if games:
            draws.append(bradley_terry(variants, games, alpha))
    if not draws:
        nan = np.full(len(variants), math.nan)
        return nan, nan
    stack = np.stack(draws)
    return np.percentile(stack, 2.5, axis=0), np.percentile(stack, 97.5, axis=0)


def reliability(pairs: Sequence[tuple[Answer, Item]]) -> float:
    """Krippendorff's alpha (nominal) of the participants' choices (A or B) over the pairs."""
    import krippendorff

    people = sorted({a.participant for a, _ in pairs})
    items = sorted({i.id for _, i in pairs})
    if len(people) < 2 or not items:
        return math.nan
    rows = {p: r for r, p in enumerate(people)}
    cols = {i: c for c, i in enumerate(items)}
    data = np.full((len(people), len(items)), np.nan)
    for answer, item in pairs:
        data[rows[answer.participant], cols[item.id]] = 0.0 if answer.choice == "A" else 1.0
    try:
        return float(krippendorff.alpha(reliability_data=data, level_of_measurement="nominal"))
    except ValueError:  # a single value in the whole data: alpha is undefined
        return math.nan


def majorities(pairs: Sequence[tuple[Answer, Item]]) -> dict[str, tuple[str, int, int]]:
    """Per item, the majority's label, its votes and all votes (ties left out)."""
    votes: dict[str, Counter[str]] = defaultdict(Counter)
    for answer, item in pairs:
        votes[item.id][answer.choice] += 1
    out = {}
    for item_id, count in votes.items():
        (top, n_top), *rest = count.most_common()
        if rest and rest[0][1] == n_top:
            continue
        out[item_id] = (top, n_top, sum(count.values()))
    return out


def _prefers(belief: Sequence[float], item: Item) -> str | None:
    a, b = (float(belief[o.action]) for o in item.options)
    if a == b:
        return None
    return "A" if a > b else "B"


def agreement(study: Study, majority: dict[str, tuple[str, int, int]]) -> dict[str, list]:
    """Agreement with the majority: ``{who: [agree, counted]}``.

    A panel member (or the fused belief) prefers the option whose action it believes more
    (a tie counts for neither); a policy agrees when its action in the state is the
    majority's option's action (a third action counts for neither).
    """
    out: dict[str, list] = {}
    for item_id, (top, _, _) in majority.items():
        item = study.item(item_id)
        if item is None:
            continue
        if item.panel is not None:
            named = list(zip(item.panel.agents, item.panel.beliefs, strict=True))
            for name, belief in [*named, ("fused", item.panel.fused)]:
                key = name if name == "fused" else f"cluster:{name}"
                pref = _prefers(belief, item)
                if pref is not None:
                    row = out.setdefault(key, [0, 0])
                    row[0] += int(pref == top)
                    row[1] += 1
        actions = {o.label: o.action for o in item.options}
        for variant, action in item.policies.items():
            if action in actions.values():
                row = out.setdefault(f"policy:{variant}", [0, 0])
                row[0] += int(action == actions[top])
                row[1] += 1
    return out


def load(folder: Path) -> tuple[Study, list[Answer]]:
    """A study and its answers.

    Raises:
        StudyError: No study, or no answers file yet.

    """
    study = read_study(folder)
    path = Path(folder) / ANSWERS_FILE
    if not path.is_file():
        raise StudyError(f"{folder}: no {ANSWERS_FILE} yet; serve the study first")
    return study, read_answers(path)


CSV_COLUMNS = (
    "participant", "item", "kind", "choice", "chosen_variant", "variant_a", "variant_b",
    "action_a", "action_b", "correct", "ms", "received", "task", "run", "episode", "step",
)  # fmt: skip


def answers_csv(folder: Path) -> str:
    """Every answer, one row each, with what was shown (for R, pandas, spreadsheets)."""
    study, answers = load(folder)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for a in answers:
        item = study.item(a.item)
        if item is None:
            continue
        oa, ob = item.options
        writer.writerow(
            [a.participant, a.item, item.kind, a.choice, a.variant or "", oa.variant or "",
             ob.variant or "", oa.action_name, ob.action_name,
             "" if a.correct is None else a.correct, f"{a.ms:.0f}", f"{a.received:.3f}",
             item.task, study.runs[item.run], item.episode, item.step]
        )  # fmt: skip
    return buffer.getvalue()
