"""The numbers of a study: win rates, Bradley-Terry, acceptability, agreement, citations.

Ratings are resampled by participant: one participant's ratings are not independent. An expert
state's acceptable set holds the actions more than half of its experts found acceptable.
"""

from __future__ import annotations

import csv
import io
import math
import unicodedata
from collections import Counter, defaultdict
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from amuled_ma.study.answers import Answer, ExpertAnswer, read_answers, read_expert_answers
from amuled_ma.study.model import ANSWERS_FILE, Item, Study, StudyError, read_study

#: Below this many participants the report warns: a percentile bootstrap over so few people
#: undercovers (Davison and Hinkley 1997, section 5.3).
MIN_PARTICIPANTS = 10


def wilson(wins: int, n: int) -> tuple[float, float]:
    """Wilson's 95% score interval of a proportion ``wins / n`` (``(nan, nan)`` for ``n = 0``)."""
    if n == 0:
        return math.nan, math.nan
    interval = binomtest(wins, n).proportion_ci(method="wilson")
    return float(interval.low), float(interval.high)


def attentive(answers: Sequence[Answer], *, keep_inattentive: bool = False) -> set[str]:
    """Participants who passed every attention check they answered (or all who answered)."""
    failed = set() if keep_inattentive else {a.participant for a in answers if a.correct == 0}
    return {a.participant for a in answers} - failed


def pair_answers(study: Study, answers: Sequence[Answer]) -> list[tuple[Answer, Item]]:
    """The answers to pairs (not attention checks), with their items."""
    items = ((answer, study.item(answer.item)) for answer in answers)
    return [(answer, item) for answer, item in items if item is not None and item.kind == "pair"]


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
    """Bradley-Terry log-strengths (mean 0) by ``choix.ilsr_pairwise``, regularised by ``alpha``."""
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


def few_people(people: int, who: str = "participants") -> str | None:
    """The warning when ``people`` is under `MIN_PARTICIPANTS`, None otherwise."""
    if people >= MIN_PARTICIPANTS:
        return None
    return (
        f"only {people} {who}: the 95% intervals (bootstrap over {who}) are unreliable "
        f"below {MIN_PARTICIPANTS} and one person moves every estimate; gather more answers "
        "before drawing conclusions"
    )


def alpha_unavailable(values: dict[tuple[str, str], float]) -> str | None:
    """Why Krippendorff's alpha of ``{(rater, unit): value}`` is undefined, None when it is not."""
    raters = {r for r, _ in values}
    if len(raters) < 2:
        return f"fewer than 2 raters ({len(raters)})"
    count = Counter(u for _, u in values)
    if max(count.values()) < 2:
        return "no item was answered by 2 or more raters"
    if len(set(values.values())) < 2:
        return "no variation: every answer has the same value"
    return None


def nominal_alpha(values: dict[tuple[str, str], float]) -> float:
    """Krippendorff's alpha (nominal) of ``{(rater, unit): value}``; nan where undefined."""
    import krippendorff

    raters = sorted({r for r, _ in values})
    units = sorted({u for _, u in values})
    if alpha_unavailable(values) is not None:
        return math.nan
    rows = {p: r for r, p in enumerate(raters)}
    cols = {i: c for c, i in enumerate(units)}
    data = np.full((len(raters), len(units)), np.nan)
    for (rater, unit), value in values.items():
        data[rows[rater], cols[unit]] = value
    try:
        return float(krippendorff.alpha(reliability_data=data, level_of_measurement="nominal"))
    except ValueError:  # a single value in the whole data: alpha is undefined
        return math.nan


def choice_values(pairs: Sequence[tuple[Answer, Item]]) -> dict[tuple[str, str], float]:
    """``{(participant, item): 0 for A, 1 for B}``: the data of the choices' alpha."""
    return {(a.participant, i.id): 0.0 if a.choice == "A" else 1.0 for a, i in pairs}


@dataclass(frozen=True)
class MeanInterval:
    """A mean of ``n`` ratings by ``people`` and 95% bootstrap interval (nan below 2 people)."""

    mean: float
    low: float
    high: float
    n: int
    people: int


def bootstrap_mean(
    by_person: dict[str, list[float]], *, resamples: int = 2000, seed: int = 0
) -> MeanInterval:
    """The mean of everyone's ratings and its 95% percentile bootstrap interval over people."""
    people = sorted(p for p, values in by_person.items() if values)
    sums = np.array([float(np.sum(by_person[p])) for p in people])
    counts = np.array([len(by_person[p]) for p in people], dtype=float)
    n = int(counts.sum())
    if not people:
        return MeanInterval(math.nan, math.nan, math.nan, 0, 0)
    mean = float(sums.sum() / counts.sum())
    if len(people) < 2:
        return MeanInterval(mean, math.nan, math.nan, n, 1)
    draws = np.random.default_rng(seed).integers(len(people), size=(resamples, len(people)))
    means = sums[draws].sum(axis=1) / counts[draws].sum(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return MeanInterval(mean, float(low), float(high), n, len(people))


def acceptability(
    variants: Sequence[str], pairs: Sequence[tuple[Answer, Item]], *, seed: int = 0
) -> dict[str, MeanInterval]:
    """Each variant's mean acceptability rating (options it took), `bootstrap_mean`'s interval."""
    ratings: dict[str, dict[str, list[float]]] = {v: defaultdict(list) for v in variants}
    for answer, item in pairs:
        for option in item.options:
            rating = answer.rating_a if option.label == "A" else answer.rating_b
            if rating is not None and option.variant in ratings:
                ratings[option.variant][answer.participant].append(float(rating))
    return {v: bootstrap_mean(ratings[v], seed=seed) for v in variants}


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


def top_action(belief: Sequence[float], among: Sequence[int] | None = None) -> int | None:
    """The action believed most (of ``among``, default all); None when several share the top."""
    actions = np.arange(len(belief)) if among is None else np.asarray(among)
    values = np.asarray(belief, dtype=float)[actions]
    best = np.flatnonzero(values == values.max())
    return int(actions[best[0]]) if len(best) == 1 else None


def agreement(
    study: Study, accepted: Mapping[str, Collection[int]], *, pairs: bool = False
) -> dict[str, list[int]]:
    """Agreement with people's ``accepted`` actions per item: ``{who: [agree, counted]}``.

    ``cluster:<name>`` and ``fused`` agree when their top action is accepted (a tie at the top is
    not counted), ``policy:<variant>`` when its action is; with ``pairs`` only the item's two
    options compete (a policy taking neither is not counted).
    """
    out: dict[str, list[int]] = {}
    for item_id, good in accepted.items():
        item = study.item(item_id)
        if item is None:
            continue
        shown = [o.action for o in item.options] if pairs else None
        judged: list[tuple[str, int | None]] = []
        if item.panel is not None:
            named = zip(item.panel.agents, item.panel.beliefs, strict=True)
            judged += [(f"cluster:{a}", top_action(b, shown)) for a, b in named]
            judged.append(("fused", top_action(item.panel.fused, shown)))
        policies = item.policies.items()
        judged += [(f"policy:{v}", a) for v, a in policies if shown is None or a in shown]
        for who, action in judged:
            if action is not None:
                row = out.setdefault(who, [0, 0])
                row[0] += int(action in good)
                row[1] += 1
    return out


def load(folder: Path) -> tuple[Study, list[Answer]]:
    """A study and its answers; StudyError without a study or an answers file."""
    study = read_study(folder)
    path = Path(folder) / ANSWERS_FILE
    if not path.is_file():
        raise StudyError(f"{folder}: no {ANSWERS_FILE} yet; serve the study first")
    return study, read_answers(path)


CSV_COLUMNS = (
    "participant", "item", "kind", "choice", "chosen_variant", "variant_a", "variant_b",
    "action_a", "action_b", "correct", "ms", "received", "task", "run", "episode", "step",
    "rating_a", "rating_b",
)  # fmt: skip
#: An expert study's CSV: one row per expert, state and action.
EXPERT_CSV_COLUMNS = (
    "participant", "item", "action", "action_name", "acceptable", "framework", "clarity",
    "ms", "received", "task", "run", "episode", "step",
)  # fmt: skip


#: What a spreadsheet reads as a formula at the start of a cell (OWASP, CSV injection).
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def safe_cell(value: object) -> object:
    r"""A CSV cell a spreadsheet shows as text, never runs (OWASP's CSV-injection rule).

    `FORMULA_STARTS` get a leading ``'``; control characters are written ``\xNN``; None is "".
    """
    if value is None:
        return ""
    if not isinstance(value, str):
        return value
    text = "'" + value if value.startswith(FORMULA_STARTS) else value
    return "".join(f"\\x{ord(c):02x}" if unicodedata.category(c) == "Cc" else c for c in text)


def answers_csv(folder: Path) -> str:
    """Every answer as CSV rows via `safe_cell` (one per answer, or per expert, state, action)."""
    study, answers = load(folder)
    rows: list[Sequence[object]] = []
    if study.mode == "expert":
        rows.append(EXPERT_CSV_COLUMNS)
        for e in read_expert_answers(Path(folder) / ANSWERS_FILE):
            item = study.item(e.item)
            if item is None:
                continue
            names = study.action_names.get(item.task, [])
            rows += [
                [e.participant, e.item, j.action, names[j.action] if j.action < len(names)
                 else "", int(j.acceptable), j.framework, e.clarity, f"{e.ms:.0f}",
                 f"{e.received:.3f}", item.task, study.runs[item.run], item.episode, item.step]
                for j in e.judgements
            ]  # fmt: skip
    else:
        rows.append(CSV_COLUMNS)
        for a in answers:
            item = study.item(a.item)
            if item is None or item.kind == "expert" or not item.options:
                continue
            oa, ob = item.options
            rows.append(
                [a.participant, a.item, item.kind, a.choice, a.variant or "", oa.variant or "",
                 ob.variant or "", oa.action_name, ob.action_name, a.correct,
                 f"{a.ms:.0f}", f"{a.received:.3f}", item.task, study.runs[item.run],
                 item.episode, item.step, a.rating_a, a.rating_b]
            )  # fmt: skip
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerows([safe_cell(c) for c in r] for r in rows)
    return buffer.getvalue()


@dataclass(frozen=True)
class Citation:
    """How often one framework was cited (``share`` of all judgements, ``by_action`` per action)."""

    framework: str
    cited: int
    share: float
    acceptable: int
    by_action: dict[str, int] = field(default_factory=dict)


def framework_citations(study: Study, answers: Sequence[ExpertAnswer]) -> list[Citation]:
    """Each of the study's frameworks (``none`` last), with how often it was cited."""
    total = sum(len(a.judgements) for a in answers)
    cited: Counter[str] = Counter()
    acceptable: Counter[str] = Counter()
    by_action: dict[str, Counter[str]] = defaultdict(Counter)
    for answer in answers:
        item = study.item(answer.item)
        task = item.task if item is not None else ""
        names = study.action_names.get(task, [])
        for j in answer.judgements:
            cited[j.framework] += 1
            acceptable[j.framework] += int(j.acceptable)
            name = names[j.action] if j.action < len(names) else str(j.action)
            by_action[j.framework][name if len(study.action_names) <= 1 else f"{task}:{name}"] += 1
    return [
        Citation(
            name,
            cited[name],
            cited[name] / total if total else float("nan"),
            acceptable[name],
            dict(sorted(by_action[name].items())),
        )
        for name in study.framework_names()
    ]


def acceptable_sets(answers: Sequence[ExpertAnswer]) -> dict[str, tuple[frozenset[int], int]]:
    """Per state, the experts' acceptable set and how many experts judged the state."""
    yes: dict[str, Counter[int]] = defaultdict(Counter)
    experts: Counter[str] = Counter()
    for answer in answers:
        experts[answer.item] += 1
        for j in answer.judgements:
            yes[answer.item][j.action] += int(j.acceptable)
    return {
        item: (frozenset(a for a, k in yes[item].items() if 2 * k > n), n)
        for item, n in experts.items()
    }


def clarity(answers: Sequence[ExpertAnswer], *, seed: int = 0) -> MeanInterval:
    """The mean clarity of the panel's reasons, with its bootstrap interval over experts."""
    by_expert: dict[str, list[float]] = defaultdict(list)
    for answer in answers:
        if answer.clarity is not None:
            by_expert[answer.participant].append(float(answer.clarity))
    return bootstrap_mean(by_expert, seed=seed)


def acceptability_values(answers: Sequence[ExpertAnswer]) -> dict[tuple[str, str], float]:
    """``{(expert, "state/action"): 1 acceptable, 0 not}``: the data of its alpha."""
    return {(a.participant, f"{a.item}/{j.action}"): float(j.acceptable)
            for a in answers for j in a.judgements}  # fmt: skip


def framework_values(study: Study, answers: Sequence[ExpertAnswer]) -> dict[tuple[str, str], float]:
    """``{(expert, "state/action"): the framework's index}``: the data of its alpha."""
    index = {name: float(i) for i, name in enumerate(study.framework_names())}
    return {(a.participant, f"{a.item}/{j.action}"): index[j.framework]
            for a in answers for j in a.judgements if j.framework in index}  # fmt: skip


def unreasoned_states(study: Study) -> list[str]:
    """The states whose panel stated no reason (no panel, or no reply kept)."""
    return [
        item.id
        for item in study.items
        if item.kind == "expert" and (item.panel is None or not item.panel.has_reasons())
    ]
