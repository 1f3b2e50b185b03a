"""The moral panel: one belief per (env copy, cluster), fused per env copy.

What one call does (one batch of new states, invalid beliefs never fused): docs/deliberation.md.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from amuled_ma.beliefs.replies.validate import check_belief, check_beliefs, show_values
from amuled_ma.beliefs.types import FUSED_STATUSES, BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation.state_key import freeze

if TYPE_CHECKING:  # torch and the cluster files are loaded by what hands them in
    import torch


#: Marker substituted by the state prompt in a cluster's pre-built chat.
_SENTINEL = "\x00AMULED_STATE_PROMPT\x00"

Messages = tuple[tuple[str, str], ...]


@dataclass
class PanelOutput:
    """The panel's answer for ``N`` env copies, ``K`` clusters, ``A`` actions.

    ``fused`` ``(N, A)``, ``beliefs`` ``(N, K, A)``, ``weights`` and ``statuses`` ``(N, K)``,
    ``conflict`` ``(N,)`` (Dempster's ``K`` of the first combination, 0 if none), ``conflicts``
    ``(N, K - 1)``, ``unique``: distinct states in the batch.
    """

    fused: np.ndarray
    beliefs: np.ndarray
    weights: np.ndarray
    conflict: np.ndarray
    conflicts: np.ndarray
    statuses: np.ndarray
    unique: int = 0

    def reward(self, actions: npt.ArrayLike | torch.Tensor) -> np.ndarray:
        """``fused[i, actions[i]]`` as ``(N,)`` float64: the shaping reward of the actions taken."""
        a = np.asarray(actions, dtype=np.int64).reshape(-1)
        return self.fused[np.arange(len(a)), a]


@dataclass
class PanelStats:
    """Counters of a `MoralPanel` since creation.

    ``requests`` are sent to the source (K per new state); ``fallbacks`` are beliefs that were
    not answers; ``invalid`` were not probability vectors (made uniform ``"error"``, the first
    few reasons kept); ``no_answer`` counts states fused to the uniform fallback.
    """

    calls: int = 0
    copies: int = 0
    unique: int = 0
    requests: int = 0
    fallbacks: int = 0
    by_status: dict[str, int] = field(default_factory=dict)
    invalid: int = 0
    invalid_reasons: list[str] = field(default_factory=list)
    no_answer: int = 0


#: How many invalid-belief reasons `PanelStats` keeps.
_KEEP_REASONS = 10


class MoralPanel:
    """Ask every moral cluster about every env copy's state and fuse the answers.

    ``clusters`` are in fusion order; ``with_messages`` defaults to the source's
    ``needs_messages``. ``prior``: a weight per cluster for a rule that takes one
    (``bjs-dst``); a state fuses the prior of the clusters that answered. None: the rule's own.
    """

    def __init__(
        self,
        task_name: str,
        clusters: Sequence[Any],
        source: BeliefSource,
        fusion_rule: str = "bjs-dst",
        *,
        action_names: Sequence[str] | None = None,
        with_messages: bool | None = None,
        render_state_prompt: Callable[[str, Mapping[str, Any]], str] | None = None,
        build_messages: Callable[[Any, str, str], Messages] | None = None,
        prior: Sequence[float] | None = None,
    ) -> None:
        if not clusters:
            raise ValueError("a moral panel needs at least one cluster")
        self.task_name = task_name
        self._cluster_specs = list(clusters)
        self.cluster_names = tuple(c if isinstance(c, str) else str(c.name) for c in clusters)
        #: Cluster names, in fusion order (the columns of ``weights``).
        self.clusters = list(self.cluster_names)
        if len(set(self.cluster_names)) != len(self.cluster_names):
            raise ValueError(f"duplicate cluster in panel: {self.cluster_names}")
        self.source = source
        self.fusion_rule = fusion_rule
        if action_names is None:
            from amuled_ma.tasks import get_task

            action_names = getattr(get_task(task_name), "action_names", None)
            if action_names is None:
                raise ValueError(
                    f"task {task_name!r} has no class attribute action_names; pass them"
                )
        self.action_names = tuple(action_names)
        needs = bool(getattr(source, "needs_messages", True))
        self.with_messages = needs if with_messages is None else with_messages
        self._render = render_state_prompt
        self._build = build_messages
        self._templates: list[Messages] | None = None
        self.stats = PanelStats()
        from amuled_ma.fusion import fuse

        self._fuse = fuse
        #: The clusters' prior weights (``(K,)``), or None.
        self.prior = None if prior is None else np.asarray(prior, dtype=np.float64)
        if self.prior is not None and self.prior.shape != (len(self.clusters),):
            raise ValueError(
                f"prior has {self.prior.size} weights for {len(self.clusters)} clusters"
            )
        # Fail at construction, not in the training loop, on an unknown rule or a bad prior.
        uniform = np.full((1, len(self.clusters), len(self.action_names)), 1.0 / self.num_actions)
        fuse(uniform, fusion_rule, prior=self.prior, return_diagnostics=True)

    @property
    def num_clusters(self) -> int:
        """Number of clusters ``K``."""
        return len(self.clusters)

    @property
    def num_actions(self) -> int:
        """Number of actions ``A``."""
        return len(self.action_names)

    def state_prompt(self, variables: Mapping[str, Any]) -> str:
        """Render one state prompt with the configured renderer."""
        if self._render is None:
            from amuled_ma.tasks.prompts import render_state_prompt

            self._render = render_state_prompt
        return self._render(self.task_name, variables)

    def messages(self, cluster_index: int, state_prompt: str) -> Messages:
        """Build the chat of one cluster for one state prompt.

        Each cluster's chat is built once with a placeholder state that each prompt replaces; a
        self-check at first use falls back to the builder if that would change a single byte.
        """
        if self._build is None:
            from amuled_ma.clusters import build_messages

            self._build = build_messages
        if self._templates is None:
            self._templates = self._make_templates()
        if not self._templates:
            spec = self._cluster_specs[cluster_index]
            return tuple(self._build(spec, self.task_name, state_prompt))
        template = self._templates[cluster_index]
        role, content = template[-1]
        return (*template[:-1], (role, content.replace(_SENTINEL, state_prompt, 1)))

    def _make_templates(self) -> list[Messages]:
        assert self._build is not None
        probe = "Probe state: x=1, y=2 {braces} \\ 'quotes'."
        templates = []
        for cluster in self._cluster_specs:
            template = tuple(self._build(cluster, self.task_name, _SENTINEL))
            direct = tuple(self._build(cluster, self.task_name, probe))
            ok = (
                template
                and sum(content.count(_SENTINEL) for _, content in template) == 1
                and _SENTINEL in template[-1][1]
            )
            if not ok:
                return []
            role, content = template[-1]
            if (*template[:-1], (role, content.replace(_SENTINEL, probe, 1))) != direct:
                return []
            templates.append(template)
        return templates

    def fused(
        self,
        obs_batch: npt.ArrayLike | torch.Tensor,
        prompt_vars: Sequence[Mapping[str, Any]] | None = None,
    ) -> PanelOutput:
        """Ask every cluster about every env copy and fuse per copy.

        Raises ``ValueError`` when ``obs_batch`` is not 2-D or messages need ``prompt_vars``
        (one per copy) that are missing.
        """
        obs = np.asarray(obs_batch.detach().cpu() if hasattr(obs_batch, "detach") else obs_batch)
        if obs.ndim != 2:
            raise ValueError(f"obs_batch must be (N, obs_dim), got shape {obs.shape}")
        n, k, a = obs.shape[0], self.num_clusters, self.num_actions
        if self.with_messages and (prompt_vars is None or len(prompt_vars) != n):
            got = "None" if prompt_vars is None else f"{len(prompt_vars)} dicts"
            raise ValueError(f"prompt_vars must hold {n} dicts (one per env copy), got {got}")

        # 1. distinct states of this batch
        rows = np.ascontiguousarray(obs, dtype=np.float64)
        keys = [rows[i].tobytes() for i in range(n)]
        if prompt_vars is not None and self.with_messages:
            keys = [
                key + freeze(variables) for key, variables in zip(keys, prompt_vars, strict=True)
            ]
        first: dict[bytes, int] = {}  # a representative env copy of each distinct state
        for i, key in enumerate(keys):
            first.setdefault(key, i)
        first_index = list(first.values())
        ordinal = {key: u for u, key in enumerate(first)}
        inverse = np.array([ordinal[key] for key in keys], dtype=np.int64)
        u_count = len(first_index)

        # 2. one batch of requests, one per (distinct state, cluster)
        beliefs = np.empty((u_count, k, a))
        statuses = np.empty((u_count, k), dtype=object)
        fused = np.empty((u_count, a))
        weights = np.empty((u_count, k))
        conflicts = np.zeros((u_count, max(k - 1, 0)))
        if u_count:
            requests: list[BeliefRequest] = []
            for i in first_index:
                obs_t = tuple(float(x) for x in rows[i])
                state = ""
                if self.with_messages:
                    assert prompt_vars is not None
                    state = self.state_prompt(prompt_vars[i])
                requests += [
                    BeliefRequest(
                        self.task_name,
                        name,
                        obs_t,
                        self.action_names,
                        self.messages(c, state) if self.with_messages else (),
                    )
                    for c, name in enumerate(self.cluster_names)
                ]
            results = self.source.beliefs(requests)
            if len(results) != len(requests):
                raise RuntimeError(
                    f"belief source {getattr(self.source, 'name', '?')!r} answered "
                    f"{len(results)} results for {len(requests)} requests"
                )
            beliefs, statuses = self._collect(results, u_count)
            fused, weights, conflicts = self._fuse_answers(beliefs, statuses)

        st = self.stats
        st.calls += 1
        st.copies += n
        st.unique += u_count

        conflict = conflicts[:, 0] if k > 1 else np.zeros(u_count)
        return PanelOutput(
            fused=fused[inverse],
            beliefs=beliefs[inverse],
            weights=weights[inverse],
            conflict=conflict[inverse],
            conflicts=conflicts[inverse],
            statuses=statuses[inverse].astype(str),
            unique=u_count,
        )

    def _fuse_answers(
        self, beliefs: np.ndarray, statuses: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fuse each state's answers; an agent that did not answer abstains (weight 0).

        An absent agent is never fed as a uniform belief, which BJS weighting would favour. A state
        no agent answered gets the uniform belief, counted in `PanelStats.no_answer`. Conflicts of
        the answering agents come first, zeros after.
        """
        u_count, k, a = beliefs.shape
        answered = np.isin(statuses.astype(str), list(FUSED_STATUSES))
        fused = np.full((u_count, a), 1.0 / a)
        weights = np.zeros((u_count, k))
        conflicts = np.zeros((u_count, max(k - 1, 0)))
        patterns, inverse = np.unique(answered, axis=0, return_inverse=True)
        for p, pattern in enumerate(patterns):
            rows = np.flatnonzero(inverse.reshape(-1) == p)
            cols = np.flatnonzero(pattern)
            if len(cols) == 0:
                self.stats.no_answer += len(rows)
                continue
            subset = beliefs[rows] if len(cols) == k else beliefs[rows][:, cols]
            prior = None
            if self.prior is not None:
                prior = self.prior[cols]
                if not prior.sum() > 0:  # only clusters with no weight answered: the
                    prior = None  # rule's own weights among them (a prior of all zeros)
            diag = self._fuse(subset, self.fusion_rule, prior=prior, return_diagnostics=True)
            fused[rows] = diag.fused
            weights[np.ix_(rows, cols)] = diag.weights
            if len(cols) > 1 and diag.conflicts.shape[-1] == len(cols) - 1:
                conflicts[rows, : len(cols) - 1] = diag.conflicts
        return fused, weights, conflicts

    def _collect(self, results: Sequence[BeliefResult], count: int) -> tuple[np.ndarray, Any]:
        """Stack results into ``(count, K, A)`` beliefs; an invalid one becomes uniform error."""
        k, a = self.num_clusters, self.num_actions
        m = count * k
        out = np.full((m, a), np.nan)
        statuses = np.empty(m, dtype=object)
        odd: dict[int, str] = {}  # results that are not a float vector of length A at all
        for j, result in enumerate(results):
            b = result.belief
            if isinstance(b, np.ndarray) and b.shape == (a,) and b.dtype.kind in "iuf":
                out[j] = b
            else:
                belief, reason = check_belief(b, a)
                if belief is None:
                    odd[j] = f"{show_values(b)} {reason}"
                else:
                    out[j] = belief
            statuses[j] = result.status
        # one vectorised check of the package's rule (amuled_ma.beliefs.replies.validate)
        out, reasons = check_beliefs(out)
        bad = [j for j, reason in enumerate(reasons) if reason is not None]
        st = self.stats
        if bad:
            out[bad] = 1.0 / a
            statuses[bad] = "error"
            st.invalid += len(bad)
            for j in bad[: max(0, _KEEP_REASONS - len(st.invalid_reasons))]:
                found = odd.get(j) or f"{show_values(results[j].belief)} {reasons[j]}"
                st.invalid_reasons.append(f"{self.cluster_names[j % k]}: {found}")
        st.requests += len(results)
        for status, n in Counter(statuses.tolist()).items():
            st.by_status[status] = st.by_status.get(status, 0) + n
            if status not in FUSED_STATUSES:
                st.fallbacks += n
        return out.reshape(count, k, a), statuses.reshape(count, k)
