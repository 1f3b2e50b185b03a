"""Panel feedback: a panel's fused beliefs, or the authors' recorded fused beliefs."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.deliberation.feedback_base import ANSWERED, Feedback, PromptVars
from amuled_ma.deliberation.summaries import describe_identity, llm_server_stats, store_stats
from amuled_ma.errors import ReplayMiss, ScenarioError

if TYPE_CHECKING:
    from amuled_ma.beliefs.sources.replay import Recording
    from amuled_ma.beliefs.types import BeliefSource
    from amuled_ma.deliberation.panel import MoralPanel


class PanelFeedback(Feedback):
    """Beliefs of a panel of moral-cluster agents, fused (`MoralPanel`)."""

    def __init__(
        self,
        name: str,
        panel: MoralPanel,
        source: BeliefSource | None = None,
        *,
        miss_zero: bool = False,
    ) -> None:
        super().__init__()
        self.name = name
        self.panel = panel
        self.source = source
        #: a state every agent missed in the recording rewards 0 (the authors' scripts)
        self.miss_zero = miss_zero
        # a source that reads no messages (replay, rules) needs no prompt variables
        self.keyed_by_prompt = bool(getattr(panel, "with_messages", True))
        from amuled_ma.distill import DistilledSource

        #: The panel's `DistilledSource`, if it has one.
        self.distilled = source if isinstance(source, DistilledSource) else None

    def _memo_generation(self) -> Any:
        """The distilled source's number of refits (None without one)."""
        return None if self.distilled is None else self.distilled.generation

    def distill_report(self) -> dict[str, Any] | None:
        """The distilled source's accounting (None when the panel answers every state)."""
        return None if self.distilled is None else self.distilled.report()

    def _compute(self, obs: np.ndarray, prompt_vars: PromptVars) -> list[tuple]:
        out = self.panel.fused(obs, prompt_vars)
        fused = np.asarray(out.fused, dtype=np.float64).reshape(len(obs), -1)
        clusters = tuple(self.panel.cluster_names)
        beliefs = getattr(out, "beliefs", None)  # (N, K, A)
        shares = None if beliefs is None else entropy_shares(beliefs)
        results = []
        for i in range(len(obs)):
            diag: dict[str, Any] = {
                "weights": dict(zip(clusters, np.asarray(out.weights[i]).tolist(), strict=True)),
                "conflict": float(out.conflict[i]),
                "statuses": tuple(out.statuses[i]),
                "agents": clusters,
            }
            if shares is not None:
                diag["entropy_share"] = {
                    name: float(shares[i, j])
                    for j, name in enumerate(clusters)
                    if diag["statuses"][j] in ANSWERED
                }
            missed = all(status == "replay_miss" for status in diag["statuses"])
            if self.miss_zero and diag["statuses"] and missed:
                results.append((np.zeros_like(fused[i]), diag))
                continue
            results.append((fused[i], diag))
        return results

    def summary(self) -> dict[str, Any]:
        """As `Feedback.summary`, plus ``store`` and ``llm_servers`` figures."""
        out = super().summary()
        servers = llm_server_stats(self.source)
        if servers:
            out["llm_servers"] = servers
        if self.source is not None:
            out["store"] = store_stats(self.source)
        return out

    def agent_source(self, agent: str) -> str:
        """The source answering ``agent``: its kind and model or recording."""
        source = self.source
        per_agent = getattr(source, "source_for", None)
        if callable(per_agent):
            source = per_agent(agent)
        return describe_identity(source.identity()) if source is not None else self.name

    def close(self) -> None:
        """Close the belief source, if it has ``close``."""
        for obj in (self.panel, self.source):
            closer = getattr(obj, "close", None)
            if callable(closer):
                closer()


def entropy_shares(beliefs: np.ndarray) -> np.ndarray:
    """Each belief's Shannon entropy / log2(A): 1 for uniform, 0 for one action."""
    p = np.clip(np.asarray(beliefs, dtype=np.float64), 0.0, None)
    logs = np.log2(p, out=np.zeros_like(p), where=p > 0)
    return -(p * logs).sum(axis=-1) / np.log2(p.shape[-1])


class FusedReplayFeedback(Feedback):
    """The AMULED feedback replayed from a recording that keeps only the fused belief.

    The authors' Driving cache of gpt-4o-mini kept only the fused belief per state, so this
    feedback is that belief, not a fusion of ours. A missing state follows ``miss_policy``
    (``zero``, ``uniform``, ``error``), counted as ``replay_miss``; a recorded all-zero belief
    (total conflict) rewards 0, counted as ``total_conflict``.
    """

    name = "amuled"
    #: the one "agent" of this feedback in the per-agent report
    agent = "fused (recorded)"

    def __init__(self, recording: Recording, miss_policy: str) -> None:
        super().__init__()
        if miss_policy not in ("zero", "uniform", "error"):
            raise ScenarioError(
                f"[feedback].miss_policy = {miss_policy!r} cannot serve the fused-only "
                f"recording {recording.path}: use zero, uniform or error"
            )
        self.recording = recording
        self.miss_policy = miss_policy

    def agent_source(self, agent: str) -> str:
        """The fused-only recording."""
        return f"replay ({self.recording.path.name}, fused beliefs only)"

    def _compute(self, obs: np.ndarray, prompt_vars: PromptVars) -> list[tuple]:
        n = len(self.recording.actions)
        results = []
        for row in obs:
            fused = self.recording.fused(row)
            status = "ok"
            if fused is None:
                if self.miss_policy == "error":
                    raise ReplayMiss(
                        f"{self.recording.path}: no fused belief for obs {row.tolist()} "
                        "([feedback].miss_policy = 'error')"
                    )
                fused = np.zeros(n) if self.miss_policy == "zero" else np.full(n, 1.0 / n)
                status = "replay_miss"
            elif not fused.any():
                status = "total_conflict"
            else:
                fused = fused / fused.sum()
            results.append((fused, {"statuses": (status,), "agents": (self.agent,)}))
        return results
