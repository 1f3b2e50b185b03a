"""``rules`` and `ScriptedSource`: sources that need no LLM; a bad answer is a uniform ``error``."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from amuled_ma.beliefs.replies.parsing import uniform
from amuled_ma.beliefs.replies.validate import check_belief, show_values
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, in_order, indices_by
from amuled_ma.errors import ScenarioError

BeliefFn = Callable[[str, np.ndarray], Sequence[float]]


def resolve_callable(
    spec: str | Callable[..., Any], what: str = "rules policy"
) -> Callable[..., Any]:
    """``spec`` itself if callable, else the ``"module:attr"`` it names, through `load_plugin`.

    Raises `ScenarioError` (naming ``what``) for a malformed string, one this run does not allow
    (an installed ``amuled_ma.agents`` entry point or ``--allow-plugin``), or nothing callable.
    """
    from amuled_ma.clusters.plugins import load_plugin

    if callable(spec):
        return spec
    if not isinstance(spec, str) or ":" not in spec:
        raise ScenarioError(
            f"{what}: expected a callable or a 'module:function' string, found {spec!r}"
        )
    target = load_plugin(spec, what)
    if not callable(target):
        raise ScenarioError(f"{what}: {spec!r} is not callable")
    return target


def _result(values: object, n_actions: int, source: str) -> BeliefResult:
    """A rule's scores divided by their sum (``"ok"``), or a uniform ``"error"`` with the reason."""
    if isinstance(values, np.ndarray) and values.ndim != 1:
        values = values.reshape(-1)  # a (1, A) row of a batched rule is one answer
    belief, reason = check_belief(values, n_actions, scores=True)
    if belief is None:
        error = f"{source} gave an invalid belief: it {reason}"
        return BeliefResult.failed(
            n_actions, "error", source, error, invalid_belief=show_values(values)
        )
    return BeliefResult(belief=belief, status="ok", source=source)


def _human_belief(task: str, obs: np.ndarray) -> Any:
    from amuled_ma.tasks.human import human_belief  # lazy: the tasks package is heavy

    return human_belief(task, obs)


#: Prefix of a ``rules`` policy that names one of the task's own judges.
JUDGE_PREFIX = "judge:"


def _task_judge(judge: str) -> BeliefFn:
    """The rule ``(task, obs) -> scores`` of the task's own judge ``judge``."""

    def rule(task: str, obs: np.ndarray) -> Any:
        from amuled_ma.tasks import get_task  # lazy: the tasks package is heavy

        return get_task(task).judge_scores(judge, obs)

    return rule


class RulesSource(BeliefSource):
    """The synthetic human-feedback policies, or any rule ``(task, obs) -> scores``.

    ``policy``: ``"human"``, ``"judge:<value>"`` (the task's own judge), a callable, or a
    ``"module:function"`` allowed as `resolve_callable` says.
    """

    name = "rules"
    needs_messages = False

    def __init__(self, policy: str | BeliefFn = "human") -> None:
        self.policy_name = policy if isinstance(policy, str) else _qualname(policy)
        if policy == "human":
            self._fn: BeliefFn = _human_belief
        elif isinstance(policy, str) and policy.startswith(JUDGE_PREFIX):
            self._fn = _task_judge(policy.removeprefix(JUDGE_PREFIX))
        else:
            self._fn = resolve_callable(policy, "rules source: key policy")

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """One rule call per (task, obs length, actions), else one per request if that fails."""
        pairs: list[tuple[int, BeliefResult]] = []
        groups = indices_by(requests, lambda r: (r.task, len(r.obs), r.num_actions))
        for (task, _, n), indices in groups.items():
            if len(indices) > 1:
                try:
                    obs = np.asarray([requests[i].obs for i in indices], dtype=np.float64)
                    batch = np.asarray(self._fn(task, obs), dtype=np.float64)
                except Exception:
                    batch = None
                if batch is not None and batch.shape == (len(indices), n):
                    rows = zip(indices, batch, strict=True)
                    pairs.extend((i, _result(row, n, self.name)) for i, row in rows)
                    continue
            pairs.extend((i, self._one(requests[i])) for i in indices)
        return in_order(pairs, len(requests), self.name)

    def _one(self, request: BeliefRequest) -> BeliefResult:
        try:
            raw = self._fn(request.task, np.asarray(request.obs, dtype=np.float64))
        except Exception as error:  # a rule bug must not stop training
            return BeliefResult.failed(request.num_actions, "error", self.name, repr(error))
        return _result(raw, request.num_actions, self.name)

    def identity(self) -> dict[str, Any]:
        """Return the source kind and the policy's name."""
        return {"source": self.name, "policy": self.policy_name}


class ScriptedSource(BeliefSource):
    """Fixed or computed beliefs, per cluster (a cluster without an entry: uniform).

    ``beliefs``: ``{cluster: vector}`` (``"*"`` for any other cluster) or a callable
    ``(request) -> vector``; ``label`` names the script in `identity` (cache keys).
    """

    name = "scripted"
    needs_messages = False

    def __init__(
        self,
        beliefs: Mapping[str, Sequence[float]] | Callable[[BeliefRequest], Any] | None = None,
        *,
        label: str = "scripted",
    ) -> None:
        self._table = None if callable(beliefs) else dict(beliefs or {})
        self._fn = beliefs if callable(beliefs) else None
        self.label = label

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer each request from the table or the function."""
        out = []
        for request in requests:
            n = request.num_actions
            try:
                if self._fn is not None:
                    raw = self._fn(request)
                else:
                    assert self._table is not None
                    raw = self._table.get(request.cluster, self._table.get("*", uniform(n)))
            except Exception as error:  # a script bug must not stop training
                out.append(BeliefResult.failed(n, "error", self.name, repr(error)))
                continue
            out.append(_result(raw, n, self.name))
        return out

    def identity(self) -> dict[str, Any]:
        """Return the source kind, the label and (for a table) its content."""
        ident: dict[str, Any] = {"source": self.name, "label": self.label}
        if self._table is not None:
            ident["table"] = {k: [float(x) for x in v] for k, v in sorted(self._table.items())}
        return ident


def _qualname(fn: Callable[..., Any]) -> str:
    return f"{getattr(fn, '__module__', '?')}:{getattr(fn, '__qualname__', repr(fn))}"
