"""What a moral panel says about states, each agent's raw reply kept beside the numbers."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.errors import AmuledError
from amuled_ma.evaluate.readonly_feedback import ReadOnlyStore

if TYPE_CHECKING:
    from amuled_ma.deliberation.panel import MoralPanel


class _Recorder(BeliefSource):
    """Pass requests to a source and keep every ``(request, result)`` pair."""

    def __init__(self, inner: BeliefSource) -> None:
        self.inner = inner
        self.name = getattr(inner, "name", "source")
        self.pairs: list[tuple[BeliefRequest, BeliefResult]] = []

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]  # property over an attribute
        return bool(getattr(self.inner, "needs_messages", True))

    def identity(self) -> dict[str, Any]:
        return dict(self.inner.identity())

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        results = self.inner.beliefs(requests)
        self.pairs.extend(zip(requests, results, strict=True))
        return results


@dataclass
class PanelAnswers:
    """What a panel said about ``U`` states (``K`` agents, ``A`` actions).

    ``beliefs`` ``(U, K, A)`` (uniform where not answered), ``weights``/``statuses`` ``(U, K)``,
    ``conflicts`` ``(U, K - 1)``, ``fused`` ``(U, A)``; ``raws`` None where no reply was kept;
    ``reasons`` notes on failed answers.
    """

    agents: list[str]
    rule: str
    beliefs: np.ndarray
    weights: np.ndarray
    statuses: np.ndarray
    conflicts: np.ndarray
    fused: np.ndarray
    raws: list[list[str | None]]
    reasons: list[list[str | None]]
    prompts: list[str | None] = field(default_factory=list)


def state_prompt(task_name: str, prompt_vars: Mapping[str, Any]) -> str | None:
    """The task's state prompt for these variables; None where they do not make one."""
    from amuled_ma.tasks.prompts import render_state_prompt

    try:
        return render_state_prompt(task_name, dict(prompt_vars))
    except (AmuledError, KeyError, ValueError):
        return None


def ask_panel(
    panel: MoralPanel,
    obs: np.ndarray,
    prompt_vars: Sequence[Mapping[str, Any]] | None,
    store: ReadOnlyStore | None = None,
) -> PanelAnswers:
    """Ask a moral panel about distinct states with one `fused` call, as training does.

    An agent whose answer carries no raw reply gets the one of its row in the run's ``store``.
    """
    obs = np.asarray(obs, dtype=np.float64).reshape(len(obs), -1)
    recorder = _Recorder(panel.source)
    original = panel.source
    panel.source = recorder
    try:
        out = panel.fused(obs, list(prompt_vars) if prompt_vars is not None else None)
    finally:
        panel.source = original
    agents = list(panel.clusters)
    k = len(agents)
    by_obs: dict[tuple[float, ...], list[int]] = {}
    for u, row in enumerate(obs):
        by_obs.setdefault(tuple(float(x) for x in row), []).append(u)
    raws: list[list[str | None]] = [[None] * k for _ in range(len(obs))]
    reasons: list[list[str | None]] = [[None] * k for _ in range(len(obs))]
    requests: list[list[BeliefRequest | None]] = [[None] * k for _ in range(len(obs))]
    taken: dict[tuple[tuple[float, ...], str], int] = {}
    column = {name: c for c, name in enumerate(agents)}
    for request, result in recorder.pairs:
        c = column.get(request.cluster)
        candidates = by_obs.get(tuple(request.obs))
        if c is None or not candidates:
            continue
        if panel.with_messages:
            # requests come in the order of the states: the n-th request of an agent with
            # this observation belongs to the n-th state with this observation
            n = taken.get((request.obs, request.cluster), 0)
            taken[(request.obs, request.cluster)] = n + 1
            targets = [candidates[min(n, len(candidates) - 1)]]
        else:  # a source without prompts is asked once per observation
            targets = candidates
        extra = result.extra or {}
        for u in targets:
            raws[u][c] = result.raw
            requests[u][c] = request
            reasons[u][c] = extra.get("miss_reason") or extra.get("error")
    # a missing raw reply is filled from the run's store row of any status
    wanted: dict[str, tuple[int, int]] = {}
    cells = [(u, c, r) for u, asked in enumerate(requests) for c, r in enumerate(asked)]
    for u, c, req in cells if store is not None and store.store is not None else []:
        if req is None or raws[u][c]:
            continue
        member = original
        route = getattr(original, "source_for", None)
        if callable(route):
            try:
                member = route(req.cluster)
            except AmuledError:
                continue
        keys = getattr(member, "keys", None)
        if callable(keys):
            wanted[keys([req])[0]] = (u, c)
    if wanted and store is not None:
        for key, kept in store.rows(list(wanted)).items():
            u, c = wanted[key]
            raws[u][c] = kept.raw
    prompts = [
        None if prompt_vars is None else state_prompt(panel.task_name, prompt_vars[u])
        for u in range(len(obs))
    ]
    conflicts = np.asarray(out.conflicts, dtype=np.float64).reshape(len(obs), -1)
    return PanelAnswers(
        agents=agents,
        rule=str(panel.fusion_rule),
        beliefs=np.asarray(out.beliefs, dtype=np.float64),
        weights=np.asarray(out.weights, dtype=np.float64),
        statuses=np.asarray(out.statuses).astype(str),
        conflicts=conflicts,
        fused=np.asarray(out.fused, dtype=np.float64),
        raws=raws,
        reasons=reasons,
        prompts=prompts,
    )
