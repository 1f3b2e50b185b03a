"""The numbers of an expert study: frameworks cited, the panel against the experts, clarity.

A state's acceptable set holds the actions more than half of its experts found acceptable.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

from amuled_ma.study.analysis import MeanInterval, bootstrap_mean
from amuled_ma.study.answers import ExpertAnswer
from amuled_ma.study.model import Study


@dataclass(frozen=True)
class Citation:
    """How often one framework was cited (``share`` of all judgements, ``by_action`` per action)."""

    framework: str
    cited: int
    share: float
    acceptable: int
    by_action: dict[str, int] = field(default_factory=dict)


def _action_name(study: Study, task: str, action: int) -> str:
    names = study.action_names.get(task, [])
    name = names[action] if action < len(names) else str(action)
    return name if len(study.action_names) <= 1 else f"{task}:{name}"


def framework_citations(study: Study, answers: Sequence[ExpertAnswer]) -> list[Citation]:
    """Each of the study's frameworks (``none`` last), with how often it was cited."""
    total = sum(len(a.judgements) for a in answers)
    cited: Counter[str] = Counter()
    acceptable: Counter[str] = Counter()
    by_action: dict[str, Counter[str]] = defaultdict(Counter)
    for answer in answers:
        item = study.item(answer.item)
        task = item.task if item is not None else ""
        for j in answer.judgements:
            cited[j.framework] += 1
            acceptable[j.framework] += int(j.acceptable)
            by_action[j.framework][_action_name(study, task, j.action)] += 1
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
