"""``replay``: beliefs from a recording of real LLM answers (``docs/beliefs.md``, "replay")."""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.beliefs.replies.parsing import uniform
from amuled_ma.beliefs.replies.validate import RULE, check_belief, checked_result, show_values
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, in_order
from amuled_ma.errors import ReplayMiss, ScenarioError
from amuled_ma.files.limits import read_bounded_bytes

if TYPE_CHECKING:
    from amuled_ma.clusters import ClusterRegistry

#: Miss policies of `ReplaySource`.
MISS_POLICIES = ("error", "uniform", "fallback")
#: Field of a recorded state holding the unprompted "moral agent" belief.
MORAL_AGENT_FIELD = "moral_agent"
#: Largest recording file read (bytes, 256 MiB): a larger file is refused before it is read.
MAX_RECORDING_BYTES = 256 * 1024 * 1024
#: Invalid beliefs listed by name when a recording is refused (all are counted).
SHOWN_PROBLEMS = 5


def _norm(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


def obs_key(obs: Sequence[float], decimals: int) -> tuple[float, ...]:
    """Return the lookup key of an observation: each value rounded, ``-0.0`` folded into ``0.0``."""
    return tuple(round(float(x), decimals) + 0.0 for x in obs)


class Recording:
    """One recording file, indexed by observation rounded to ``decimals``, every belief checked.

    Raises `ScenarioError`: the file is missing, not a recording, or holds an invalid belief
    (the first `SHOWN_PROBLEMS` listed, all counted).
    """

    def __init__(self, path: str | Path, *, decimals: int = 3) -> None:
        self.path = Path(path)
        try:
            raw = read_bounded_bytes(
                self.path,
                MAX_RECORDING_BYTES,
                "recording",
                error=ScenarioError,
                note="the largest shipped one is 1.4 MB",
            )
        except OSError as error:
            raise ScenarioError(f"{self.path}: cannot read recording: {error}") from error
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as error:
            deep = "nested deeper than Python's JSON reader can follow (a recording is 4 deep)"
            why = deep if isinstance(error, RecursionError) else str(error)
            raise ScenarioError(
                f"{self.path}: cannot read recording: not JSON ({why}); expected the format of "
                "the AMULED recordings (see amuled_ma.beliefs.sources.replay)"
            ) from None
        if not isinstance(data, dict):
            raise ScenarioError(
                f"{self.path}: a recording is a JSON object, found {type(data).__name__}"
            )
        for key in ("task", "clusters", "actions", "states"):
            if key not in data:
                raise ScenarioError(f"{self.path}: recording has no {key!r} field")
        for key in ("clusters", "actions"):
            if not isinstance(data[key], list) or not all(isinstance(x, str) for x in data[key]):
                raise ScenarioError(
                    f"{self.path}: {key!r} must be a list of names, found "
                    f"{show_values(data[key], 80)}"
                )
        if not isinstance(data["states"], list):
            raise ScenarioError(f"{self.path}: 'states' must be a list of states")
        self.sha256 = hashlib.sha256(raw).hexdigest()
        self.task: str = str(data["task"])
        self.model: str | None = data.get("model")
        self.clusters: list[str] = list(data["clusters"])
        self.actions: list[str] = list(data["actions"])
        self.decimals = decimals
        self.states: dict[tuple[float, ...], dict[str, Any]] = {}
        # rounded obs -> {agent: checked belief}; MORAL_AGENT_FIELD for the moral agent
        self._beliefs: dict[tuple[float, ...], dict[str, np.ndarray]] = {}
        problems: list[str] = []
        invalid = 0
        n = len(self.actions)
        for i, state in enumerate(data["states"]):
            if not isinstance(state, dict) or "obs" not in state or "beliefs" not in state:
                raise ScenarioError(f"{self.path}: states[{i}] has no 'obs' or 'beliefs'")
            try:
                state_key = obs_key(state["obs"], decimals)
            except (TypeError, ValueError, OverflowError):
                raise ScenarioError(
                    f"{self.path}: states[{i}].obs must be a list of numbers, found "
                    f"{show_values(state['obs'], 80)}"
                ) from None
            recorded = state["beliefs"]
            if recorded is not None and not isinstance(recorded, dict):
                raise ScenarioError(
                    f"{self.path}: states[{i}].beliefs must be an object {{agent: belief}} or "
                    f"null, found {show_values(recorded, 80)}"
                )
            vectors: dict[str, np.ndarray] = {}
            entries = [(f"beliefs[{a!r}]", a, v) for a, v in (recorded or {}).items()]
            entries.append((MORAL_AGENT_FIELD, MORAL_AGENT_FIELD, state.get(MORAL_AGENT_FIELD)))
            for field, agent, values in entries:
                if values is None:
                    continue  # not recorded: a miss
                belief, reason = check_belief(values, n)
                if belief is None:
                    invalid += 1
                    if len(problems) < SHOWN_PROBLEMS:
                        problems.append(
                            f"states[{i}].{field} (obs {show_values(state['obs'], 60)}): "
                            f"{show_values(values, 60)} {reason}"
                        )
                    continue
                vectors[agent] = belief
            if state_key in self.states:
                continue  # first one wins, as in the authors' cache
            self.states[state_key] = state
            self._beliefs[state_key] = vectors
        if invalid:
            raise ScenarioError(
                f"{self.path}: refusing to load the recording: {invalid} invalid belief(s) "
                f"(an invalid belief would be replayed as an answer); the first "
                f"{len(problems)}: {'; '.join(problems)}. {RULE} ({n} actions: "
                f"{', '.join(self.actions)}); correct or remove these entries (null means "
                "'not recorded'), or regenerate the recording"
            )

    @property
    def fused_only(self) -> bool:
        """True when no state holds a per-agent belief, only the authors' fused one."""
        return bool(self.states) and not any(self._beliefs.values())

    def fused(self, obs: Sequence[float]) -> np.ndarray | None:
        """The recorded fused belief (``fused_by_reference``) of a state, if recorded.

        All zeros where the authors' fusion met total conflict (``K = 1``). `ScenarioError`:
        not finite, negative, or not one value per action.
        """
        state = self.states.get(obs_key(obs, self.decimals))
        if state is None or state.get("fused_by_reference") is None:
            return None
        vector = np.asarray(state["fused_by_reference"], dtype=np.float64)
        if vector.shape != (len(self.actions),) or not np.all(np.isfinite(vector) & (vector >= 0)):
            raise ScenarioError(
                f"{self.path}: fused_by_reference of obs {show_values(state['obs'], 60)} is "
                f"{show_values(state['fused_by_reference'], 60)}; expected "
                f"{len(self.actions)} finite non-negative numbers"
            )
        return vector

    def answer(self, state: Mapping[str, Any], agent: str) -> tuple[np.ndarray, str | None] | None:
        """``(a copy of the checked belief, raw reply or None)`` of ``agent``, if recorded."""
        vector = self._beliefs[obs_key(state["obs"], self.decimals)].get(agent)
        if vector is None:
            return None
        raw = None
        for exchange in state.get("exchanges") or ():
            if isinstance(exchange, dict) and exchange.get("agent") == agent:
                raw = exchange.get("response")
        return vector.copy(), raw


class ReplaySource(BeliefSource):
    """Answers from one or more recording files (the options: ``docs/beliefs.md``, "replay").

    ``registry``: the clusters whose aliases map names (default: the shipped ones). Raises
    `ScenarioError` for a bad policy, a missing fallback, or an unreadable file.
    """

    name = "replay"
    needs_messages = False

    def __init__(
        self,
        paths: str | Path | Sequence[str | Path],
        *,
        miss_policy: str = "error",
        fallback: BeliefSource | None = None,
        decimals: int = 3,
        cluster_names: Mapping[str, str] | None = None,
        registry: ClusterRegistry | None = None,
    ) -> None:
        if miss_policy not in MISS_POLICIES:
            raise ScenarioError(
                f"replay miss_policy: expected one of {', '.join(MISS_POLICIES)}, "
                f"found {miss_policy!r}"
            )
        if miss_policy == "fallback" and fallback is None:
            raise ScenarioError("replay miss_policy 'fallback' needs a fallback source")
        if isinstance(paths, str | Path):
            paths = [paths]
        self.recordings = [Recording(p, decimals=decimals) for p in paths]
        if not self.recordings:
            raise ScenarioError("replay source needs at least one recording file")
        self.miss_policy = miss_policy
        self.fallback = fallback
        self.decimals = decimals
        self.cluster_names = dict(cluster_names or {})
        self._registry = registry
        self.hits = 0
        self.misses = 0
        self.misses_by_cluster: Counter[str] = Counter()
        self._agent_cache: dict[tuple[int, str], str | None] = {}

    def _aliases(self, cluster: str) -> tuple[tuple[str, ...], bool]:
        registry = self._registry
        if registry is None:
            from amuled_ma.clusters import default_registry

            registry = self._registry = default_registry()
        if cluster in registry:
            found = registry.get(cluster)
            return found.names, found.kind == "unprompted"
        return (cluster,), cluster == MORAL_AGENT_FIELD

    def recording_agent(self, recording: Recording, cluster: str) -> str | None:
        """Return the recording's agent name for our cluster name (``None``: not recorded)."""
        cache_key = (id(recording), cluster)
        if cache_key in self._agent_cache:
            return self._agent_cache[cache_key]
        agent: str | None = None
        if cluster in self.cluster_names:
            agent = self.cluster_names[cluster]
        else:
            names, unprompted = self._aliases(cluster)
            if unprompted:
                agent = MORAL_AGENT_FIELD
            else:
                by_norm = {_norm(c): c for c in recording.clusters}
                for name in names:
                    if name in recording.clusters:
                        agent = name
                        break
                    if _norm(name) in by_norm:
                        agent = by_norm[_norm(name)]
                        break
        self._agent_cache[cache_key] = agent
        return agent

    def lookup(self, request: BeliefRequest) -> tuple[np.ndarray, str | None] | str:
        """Return ``(belief, raw)`` for a request, or the reason it is a miss."""
        task = _norm(request.task)
        recording = next((r for r in self.recordings if _norm(r.task) == task), None)
        if recording is None:
            return f"no recording for task {request.task!r}"
        if len(request.action_names) != len(recording.actions):
            raise ScenarioError(
                f"{recording.path}: recording has {len(recording.actions)} actions "
                f"{recording.actions}, the request has {len(request.action_names)}"
            )
        agent = self.recording_agent(recording, request.cluster)
        if agent is None:
            return (
                f"cluster {request.cluster!r} is not in {recording.path.name} "
                f"(recorded: {', '.join(recording.clusters)}, {MORAL_AGENT_FIELD})"
            )
        state = recording.states.get(obs_key(request.obs, recording.decimals))
        if state is None:
            return f"state {list(request.obs)} not in {recording.path.name}"
        answer = recording.answer(state, agent)
        if answer is None:
            return f"agent {agent!r} has no belief for state {list(request.obs)}"
        return answer

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer every request from the recordings; misses follow ``miss_policy``."""
        pairs: list[tuple[int, BeliefResult]] = []
        missed: dict[int, str] = {}  # index -> why it is a miss
        for i, request in enumerate(requests):
            found = self.lookup(request)
            if isinstance(found, str):
                self.misses += 1
                self.misses_by_cluster[request.cluster] += 1
                if self.miss_policy == "error":
                    raise ReplayMiss(
                        f"replay miss: {found} (cluster {request.cluster!r}, task "
                        f"{request.task!r}); use miss_policy 'uniform' or 'fallback' to go on"
                    )
                missed[i] = found
                continue
            self.hits += 1
            belief, raw = found  # checked when the recording was loaded
            pairs.append((i, BeliefResult(belief=belief, status="ok", source=self.name, raw=raw)))
        if missed and self.miss_policy == "fallback":
            assert self.fallback is not None
            answers = self.fallback.beliefs([requests[i] for i in missed])
            for (i, reason), answer in zip(missed.items(), answers, strict=True):
                checked_result(answer, requests[i].num_actions)
                answer.extra = {**answer.extra, "replay_miss": True, "miss_reason": reason}
                pairs.append((i, answer))
        else:
            for i, reason in missed.items():
                belief = uniform(requests[i].num_actions)
                extra = {"miss_reason": reason}
                pairs.append((i, BeliefResult(belief, "replay_miss", self.name, extra=extra)))
        return in_order(pairs, len(requests), self.name)

    def identity(self) -> dict[str, Any]:
        """Return the recordings' content hashes, the rounding and the name mapping."""
        ident: dict[str, Any] = {
            "source": self.name,
            "recordings": [
                {"file": r.path.name, "sha256": r.sha256, "model": r.model} for r in self.recordings
            ],
            "decimals": self.decimals,
            "cluster_names": dict(sorted(self.cluster_names.items())),
        }
        if self.miss_policy == "fallback" and self.fallback is not None:
            ident["fallback"] = self.fallback.identity()
        return ident

    def close(self) -> None:
        """Close the fallback source, if any."""
        if self.fallback is not None:
            self.fallback.close()
