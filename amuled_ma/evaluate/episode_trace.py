"""One evaluation episode, step by step, with what the feedback said about every state.

The viewer (:mod:`amuled_ma.evaluate.viewer`, ``amuled view``) and ``amuled explain
--state-from`` both need the same thing: replay evaluation episode ``K`` of a trained
variant (the evaluation seed ``[evaluation].seed + K``, as
:func:`~amuled_ma.evaluate.evaluator.run_episodes` seeds copy ``K``), record what the
policy did and what the base policy would have done, then ask the variant's feedback, built
as training builds it (:func:`amuled_ma.deliberation.feedback.make_feedback`), about every state.

- :func:`replay_episode` plays the episode on one task copy and records, per step, the
  observation, the prompt variables, the policy's probabilities and action, the base
  policy's, the task's events and a small picture of the state.
- :func:`open_feedback` builds a variant's feedback and puts the run's belief store behind
  it **read-only** (:class:`ReadOnlyStore`): looking at a run never writes to it.
- :func:`ask_panel` asks a :class:`~amuled_ma.deliberation.panel.MoralPanel` about states
  and keeps each agent's raw reply (the belief store's row, or the replayed recording's
  ``exchanges``) beside the numbers.
- :func:`fusion_breakdown` recomputes the fusion's intermediate quantities of one state
  with :mod:`amuled_ma.fusion` (BJS divergences, credibility, Deng entropy, information
  volume, weights, the conflict of every combination).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.beliefs.types import FUSED_STATUSES, BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation.state_key import freeze
from amuled_ma.errors import AmuledError, CheckpointError, ScenarioError

#: Action selection modes of :func:`replay_episode`.
MODES = ("greedy", "sampled")
#: Name of the final checkpoint in a variant folder (as the trainer writes it).
LAST = "model_last.pt"


# ---------------------------------------------------------------------------------------
# The run's folders


def variant_settings(variant_dir: Path) -> dict[str, Any]:
    """The ``"training"`` settings a variant folder's ``config.json`` recorded ({} if none)."""
    path = Path(variant_dir) / "config.json"
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except ValueError as error:
        raise AmuledError(
            f"{path}: not JSON ({error}); the variant's settings cannot be read: retrain it "
            "with --force"
        ) from None
    return dict(data.get("training") or {}) if isinstance(data, dict) else {}


def feedback_variant(variant_dir: Path) -> str | None:
    """The feedback a variant folder was fine-tuned on (``amuled``, ``human``...), or None.

    Read from ``config.json`` (``"training"."variant"``, ``finetune:<feedback>``); a
    folder without settings named ``finetune-<feedback>`` is read from its name.
    """
    from amuled_ma.learn.variants import Variant

    text = str(variant_settings(variant_dir).get("variant") or "")
    if text:
        try:
            return Variant.parse(text).feedback
        except ScenarioError:
            return None
    if Path(variant_dir).name.startswith("finetune-"):
        from amuled_ma.experiments.run_folder import split_replica

        name = split_replica(Path(variant_dir).name)[0].split("-", 1)[1]
        for candidate in (name, name.replace("-", ":", 1)):  # finetune-cluster-care
            try:
                return Variant.finetune(candidate).feedback
            except ScenarioError:
                continue
    return None


def variant_scenario(run_dir: Path, variant_dir: Path) -> Any:
    """The scenario a variant was trained with: its own ``config.json``, else the run's.

    Raises:
        AmuledError: Neither folder holds a ``config.json`` with a scenario.

    """
    from amuled_ma.commands._experiment import scenario_of_run

    own = Path(variant_dir) / "config.json"
    if own.is_file():
        try:
            if "scenario" in json.loads(own.read_text()):
                return scenario_of_run(Path(variant_dir))
        except ValueError:
            pass
    return scenario_of_run(Path(run_dir))


def base_checkpoint_of(run_dir: Path, variant_dir: Path) -> Path | None:
    """The base policy a fine-tune started from and was anchored to, if it can be found.

    The checkpoint's recorded ``infos["base_checkpoint"]`` first (as given, else its
    folder name inside the run), then the run's ``base`` folder (a seed replica
    ``<name>.seed<k>`` looks for ``base.seed<k>`` first). None when there is none.
    """
    from amuled_ma.experiments.run_folder import split_replica
    from amuled_ma.learn.checkpoints import checkpoint_infos

    run_dir, variant_dir = Path(run_dir), Path(variant_dir)
    candidates: list[Path] = []
    try:
        infos = checkpoint_infos(variant_dir / LAST) or {}
    except AmuledError:
        infos = {}
    recorded = infos.get("base_checkpoint")
    if recorded:
        recorded_path = Path(str(recorded))
        candidates += [recorded_path, run_dir / recorded_path.parent.name / LAST]
        candidates.append(run_dir.parent / recorded_path.parent.name / LAST)
    seed = split_replica(variant_dir.name)[1]
    if seed is not None:
        candidates.append(run_dir / f"base.seed{seed}" / LAST)
    candidates += [run_dir / "base" / LAST, run_dir.parent / "base" / LAST]
    for path in candidates:
        if path.is_file() and path.resolve() != (variant_dir / LAST).resolve():
            return path
    return None


# ---------------------------------------------------------------------------------------
# The episode


@dataclass
class Episode:
    """One episode of one policy on one task copy, step by step.

    ``T`` is the number of steps taken; state ``t`` is the state step ``t`` was taken in
    (state ``T`` is the last one reached).

    Attributes:
        task: Task name.
        episode: Evaluation episode index ``K``.
        seed: The task copy's seed, ``[evaluation].seed + K``.
        mode: ``greedy`` or ``sampled``.
        action_names: The task's action names.
        obs: ``[T + 1, obs_dim]`` observations of states ``0..T``.
        prompt_vars: ``T`` dicts, the prompt variables of states ``0..T-1``.
        actions: ``[T]`` the policy's actions.
        probs: ``[T, A]`` the policy's action probabilities.
        base_actions: ``[T]`` the base policy's greedy action in the same states (None
            without a base policy).
        base_probs: ``[T, A]`` the base policy's probabilities (None without one).
        events: Per-step task events (``[T]`` each: ``collisions``, ``rescues``,
            ``crying_pacified``, ...).
        rewards: ``[T]`` the environment reward ``r_env`` of each step.
        frames: ``T + 1`` pictures of the states (task-specific, see :func:`frame_of`).
        layout: What stays fixed over the episode (FindMilk: milk and babies at the start).
        terminated: The episode ended by the task (not by the time limit).
        metrics: The task's episode metrics (``info["episode"]`` at the end).
        live_beliefs: ``[T, A]`` a non-panel feedback's belief per step (None otherwise).
        live_statuses: ``T`` tuples of ``(agent, status)`` of that feedback.

    """

    task: str
    episode: int
    seed: int
    mode: str
    action_names: tuple[str, ...]
    obs: np.ndarray
    prompt_vars: list[dict[str, Any]]
    actions: np.ndarray
    probs: np.ndarray
    base_actions: np.ndarray | None
    base_probs: np.ndarray | None
    events: dict[str, np.ndarray]
    rewards: np.ndarray
    frames: list[Any]
    layout: dict[str, Any] | None
    terminated: bool
    metrics: dict[str, float]
    live_beliefs: np.ndarray | None = None
    live_statuses: list[tuple[tuple[str, str], ...]] | None = None

    @property
    def length(self) -> int:
        """Number of steps ``T``."""
        return len(self.actions)

    def unique_states(self) -> tuple[list[int], np.ndarray]:
        """The distinct states of steps ``0..T-1`` (observation and prompt variables).

        Returns:
            ``(first, index)``: the first step of each distinct state, and for every step
            the position of its state in ``first``.

        """
        first: list[int] = []
        seen: dict[bytes, int] = {}
        index = np.empty(self.length, dtype=np.int64)
        rows = np.ascontiguousarray(self.obs[: self.length], dtype=np.float64)
        for t in range(self.length):
            key = rows[t].tobytes() + freeze(self.prompt_vars[t])
            u = seen.get(key)
            if u is None:
                u = seen[key] = len(first)
                first.append(t)
            index[t] = u
        return first, index


def frame_of(task: Any) -> Any:
    """A small, JSON-ready picture of copy 0 of a task.

    FindMilk: the robot's ``[x, y]``. Driving: ``[lane, [lane, distance] of each car,
    [lane, distance] of each grandma]``. Any other task: its ``render_ansi`` text.
    """
    if task.name == "findmilk":
        x, y = (int(v) for v in task.position[0].tolist())
        return [x, y]
    if task.name == "driving":
        objects = task.objects(0)
        return [int(task.lane[0]), objects["car"], objects["grandma"]]
    return task.render_ansi(0)


def layout_of(task: Any, obs: torch.Tensor) -> dict[str, Any] | None:
    """What stays fixed over an episode of copy 0 (FindMilk: the milk and the babies)."""
    if task.name == "findmilk":
        babies = task.baby_positions(0)
        milk = [int(v) for v in obs[0, 2:4].tolist()]
        return {
            "size": int(task.grid_size),
            "milk": milk,
            "crying": [list(p) for p in babies["crying"]],
            "sleeping": [list(p) for p in babies["sleeping"]],
        }
    if task.name == "driving":
        return {"lanes": int(task.num_lanes), "distance": 8}
    return None


def replay_episode(
    actor: torch.nn.Module,
    scenario: Any,
    *,
    episode: int = 0,
    mode: str = "greedy",
    base_actor: torch.nn.Module | None = None,
    live_feedback: Any = None,
    task_factory: Callable[..., Any] | None = None,
) -> Episode:
    """Play evaluation episode ``episode`` of a policy and record every step.

    The task copy is seeded ``[evaluation].seed + episode``: the episode that copy
    ``episode`` of ``amuled evaluate`` plays (in ``greedy`` mode the same actions; in
    ``sampled`` mode the draws come from a generator seeded with the same number, so they
    differ from ``amuled evaluate``'s batched draws).

    Args:
        actor: The policy (an rsl-rl actor with our categorical head).
        scenario: The scenario (task, options, evaluation seed).
        episode: Evaluation episode index ``K >= 0``.
        mode: ``greedy`` (argmax) or ``sampled``.
        base_actor: The base policy, asked in the same states (its greedy action).
        live_feedback: A feedback that needs the live task (human, fused-only replay):
            asked about every state as the episode runs.
        task_factory: Replaces :func:`~amuled_ma.tasks.make_task`.

    Returns:
        The recorded :class:`Episode`.

    Raises:
        ScenarioError: Unknown ``mode`` or a negative ``episode``.

    """
    from amuled_ma.learn.policies import action_log_probs
    from amuled_ma.tasks import make_task

    if mode not in MODES:
        raise ScenarioError(f"mode: expected one of {', '.join(MODES)}, found {mode!r}")
    if episode < 0:
        raise ScenarioError(f"episode: expected an index >= 0, found {episode}")
    seed = int(scenario.evaluation.seed) + int(episode)
    task = (task_factory or make_task)(scenario, 1, shaping_coef=0.0, seed=seed)
    obs = torch.as_tensor(task.reset()).float()
    gen = torch.Generator().manual_seed(seed)
    layout = layout_of(task, obs)
    observations = [obs[0].numpy().copy()]
    prompt_vars: list[dict[str, Any]] = []
    frames = [frame_of(task)]
    actions: list[int] = []
    probs: list[np.ndarray] = []
    base_actions: list[int] = []
    base_probs: list[np.ndarray] = []
    events: dict[str, list[float]] = {}
    rewards: list[float] = []
    live: list[np.ndarray] = []
    live_statuses: list[tuple[tuple[str, str], ...]] = []
    metrics: dict[str, float] = {}
    terminated = False
    limit = int(getattr(task, "max_steps", 1000))
    with torch.inference_mode():
        for _ in range(limit):
            prompt_vars.append(dict(task.prompt_variables([0])[0]))
            if live_feedback is not None:
                before = Counter(live_feedback.agent_statuses)
                live.append(np.asarray(live_feedback(obs, task, [0])[0], dtype=np.float64))
                after = Counter(live_feedback.agent_statuses)
                live_statuses.append(tuple((after - before).keys()))
            logp = action_log_probs(actor, obs)
            if mode == "greedy":
                action = logp.argmax(dim=-1)
            else:
                action = torch.multinomial(logp.exp(), 1, generator=gen).squeeze(-1)
            probs.append(logp[0].exp().numpy().copy())
            actions.append(int(action[0]))
            if base_actor is not None:
                base_logp = action_log_probs(base_actor, obs)
                base_probs.append(base_logp[0].exp().numpy().copy())
                base_actions.append(int(base_logp[0].argmax()))
            obs, _, term, trunc, info = task.step(action)
            obs = torch.as_tensor(obs).float()
            final = torch.as_tensor(info.get("final_obs", obs)).float()
            observations.append(final[0].numpy().copy())
            rewards.append(float(torch.as_tensor(info["r_env"])[0]))
            for key, value in info.items():
                if key in ("final_obs", "episode", "r_env", "r_shaping") or not torch.is_tensor(
                    value
                ):
                    continue
                if value.dim() == 1 and value.numel() == 1:
                    events.setdefault(key, []).append(float(value[0]))
            done = bool(torch.as_tensor(term)[0]) or bool(torch.as_tensor(trunc)[0])
            if done:
                terminated = bool(torch.as_tensor(term)[0])
                for key, value in (info.get("episode") or {}).items():
                    tensor = torch.as_tensor(value)
                    if key != "done" and tensor.numel() == 1:
                        metrics[key] = float(tensor.reshape(-1)[0])
                # the task has reset itself: the last picture is drawn from the final obs
                frames.append(_final_frame(task, frames[-1], final[0], info))
                break
            frames.append(frame_of(task))
    n = len(actions)
    return Episode(
        task=task.name,
        episode=int(episode),
        seed=seed,
        mode=mode,
        action_names=tuple(task.action_names),
        obs=np.stack(observations),
        prompt_vars=prompt_vars,
        actions=np.asarray(actions, dtype=np.int64),
        probs=np.stack(probs) if probs else np.empty((0, task.num_actions)),
        base_actions=np.asarray(base_actions, dtype=np.int64) if base_actor else None,
        base_probs=np.stack(base_probs) if base_actor is not None and n else None,
        events={k: np.asarray(v) for k, v in events.items()},
        rewards=np.asarray(rewards),
        frames=frames,
        layout=layout,
        terminated=terminated,
        metrics=metrics,
        live_beliefs=np.stack(live) if live else None,
        live_statuses=live_statuses if live_feedback is not None else None,
    )


def _final_frame(task: Any, previous: Any, final_obs: torch.Tensor, info: Mapping) -> Any:
    """The picture of the last state, after the task reset the copy.

    FindMilk: the robot's position is in the final observation. Driving: the lane is in
    the final observation's one-hot; the objects are those of the previous picture moved
    one step closer (the road's rules), without the ones that reached the agent.
    """
    if task.name == "findmilk":
        return [int(final_obs[0]), int(final_obs[1])]
    if task.name == "driving":
        lane = int(torch.argmax(final_obs[6:]))
        cars = [[ln, d - 1] for ln, d in previous[1] if d - 1 > 0]
        grandmas = [[ln, d - 3] for ln, d in previous[2] if d - 3 > 0]
        return [lane, cars, grandmas]
    return previous


# ---------------------------------------------------------------------------------------
# Feedback, read-only


class ReadOnlyStore:
    """The run's belief store behind a feedback, opened read-only.

    Stands in for the :class:`~amuled_ma.beliefs.store.BeliefStore` of a
    :class:`~amuled_ma.beliefs.cached.CachedSource`: lookups read the run's file (SQLite
    ``mode=ro``), answers to states the run never asked are not written (counted in
    :attr:`not_written`), so looking at a run never changes it.

    Args:
        path: The store file; a missing file reads as empty.

    """

    def __init__(self, path: str | Path | None) -> None:
        from amuled_ma.beliefs.store import BeliefStore

        self.path = Path(path) if path else None
        self.store = (
            BeliefStore(self.path, read_only=True)
            if self.path is not None and self.path.is_file()
            else None
        )
        #: Answers not written to the run's store.
        self.not_written = 0

    def lookup(self, keys: Sequence[str]) -> dict[str, BeliefResult]:
        """Cached answers (``ok``/``repaired`` rows) of ``keys`` in the run's store."""
        return self.store.lookup(keys) if self.store is not None else {}

    def rows(self, keys: Sequence[str]) -> dict[str, Any]:
        """Every row of ``keys``, answers or not (an abstention's raw reply is kept)."""
        if self.store is None:
            return {}
        return self.store.get_many(keys, cacheable_only=False)

    def put_many(self, items: Any) -> int:
        """Write nothing: count the answers a writable store would have kept."""
        self.not_written += len(list(items))
        return 0

    def close(self) -> None:
        """Close the read-only connection."""
        if self.store is not None:
            self.store.close()


def cached_sources(source: Any) -> Iterator[Any]:
    """Every :class:`~amuled_ma.beliefs.cached.CachedSource` in a (routed) source."""
    from amuled_ma.beliefs.cached import CachedSource

    if isinstance(source, CachedSource):
        yield source
        return
    for member, _agents in getattr(source, "members", ()) or ():
        yield from cached_sources(member)


def store_path_of(scenario: Any, run_dir: Path | None) -> Path | None:
    """The belief store file of a scenario's feedback in a run (None without a run)."""
    if run_dir is None:
        return None
    path = Path(scenario.feedback.store)
    return path if path.is_absolute() else Path(run_dir) / path


def open_feedback(
    feedback_name: str, scenario: Any, run_dir: Path | None
) -> tuple[Any, ReadOnlyStore]:
    """Build a variant's feedback as training does, with the run's store read-only.

    :func:`~amuled_ma.deliberation.feedback.make_feedback` builds it (same agents, fusion rule,
    sources and store keys) in a scratch folder; every belief store behind it is then
    replaced by one :class:`ReadOnlyStore` over the run's file, which is never opened for
    writing (an Ollama source still asks its server about states the run never asked).

    Args:
        feedback_name: ``amuled``, ``human``, ``cluster:care``, ...
        scenario: The variant's scenario.
        run_dir: The run folder holding the store (None: a scratch folder, no store).

    Returns:
        ``(feedback, store)``.

    """
    import tempfile

    from amuled_ma.deliberation.feedback import make_feedback
    from amuled_ma.learn.variants import parse_feedback

    store = ReadOnlyStore(store_path_of(scenario, run_dir))
    if run_dir is not None and parse_feedback(feedback_name)[0] == "human":
        # the demonstrator's counts are cached in the run folder; no belief store
        return make_feedback(feedback_name, scenario, Path(run_dir)), store
    # built in a scratch folder: make_feedback opens its store for writing, and even
    # opening the run's store so (then closing it) could rewrite the file
    with tempfile.TemporaryDirectory(prefix="amuled-view-") as scratch:
        try:
            feedback = make_feedback(feedback_name, scenario, Path(scratch))
        except BaseException:
            store.close()
            raise
        _swap_stores(feedback, store)
    return feedback, store


def _swap_stores(feedback: Any, store: ReadOnlyStore) -> None:
    source = getattr(getattr(feedback, "panel", None), "source", None)
    if source is None:
        return
    closed: set[int] = set()
    for cached in cached_sources(source):
        old = cached.store
        if id(old) not in closed and hasattr(old, "close"):
            old.close()
            closed.add(id(old))
        cached.store = store


# ---------------------------------------------------------------------------------------
# The panel's answers, with the raw replies


class _Recorder(BeliefSource):
    """Pass requests to a source and keep every ``(request, result)`` pair."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.name = getattr(inner, "name", "source")
        self.pairs: list[tuple[BeliefRequest, BeliefResult]] = []

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]
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

    Attributes:
        agents: The agents, in fusion order.
        rule: The fusion rule.
        beliefs: ``(U, K, A)`` each agent's belief (uniform where it did not answer).
        weights: ``(U, K)`` fusion weights (0 for an agent that abstained).
        statuses: ``(U, K)`` statuses (``ok``, ``abstained``, ``replay_miss``...).
        conflicts: ``(U, K - 1)`` Dempster's conflict at each combination.
        fused: ``(U, A)`` the fused belief.
        raws: ``U`` lists of ``K`` raw replies (None where neither the store nor the
            recording kept one).
        reasons: ``U`` lists of ``K`` notes on a failed answer (miss reason, error).
        prompts: ``U`` rendered state prompts.

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


def ask_panel(
    panel: Any,
    obs: np.ndarray,
    prompt_vars: Sequence[Mapping[str, Any]] | None,
    store: ReadOnlyStore | None = None,
) -> PanelAnswers:
    """Ask a moral panel about distinct states and keep each agent's raw reply.

    One :meth:`~amuled_ma.deliberation.panel.MoralPanel.fused` call, as training makes it;
    the source's answers carry the raw replies (a stored row's ``raw``, a replayed
    recording's ``exchanges``). An agent whose answer has none (an abstention answered
    again as a miss, say) gets the raw reply of its row in the run's store, if any.

    Args:
        panel: The moral panel.
        obs: ``(U, obs_dim)`` distinct states.
        prompt_vars: Their prompt variables (None when the source reads no prompts).
        store: The run's store, read-only, for the raw replies of non-answers.

    Returns:
        The :class:`PanelAnswers`.

    """
    from amuled_ma.tasks.prompts import render_state_prompt

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
    if store is not None and store.store is not None:
        _raws_from_store(original, store, requests, raws)
    prompts: list[str | None] = []
    for u in range(len(obs)):
        text = None
        if prompt_vars is not None:
            try:
                text = render_state_prompt(panel.task_name, dict(prompt_vars[u]))
            except (AmuledError, KeyError, ValueError):
                text = None
        prompts.append(text)
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


def _raws_from_store(
    source: Any,
    store: ReadOnlyStore,
    requests: list[list[BeliefRequest | None]],
    raws: list[list[str | None]],
) -> None:
    """Fill missing raw replies from the run's store rows of any status."""
    wanted: dict[str, tuple[int, int]] = {}
    for u, row in enumerate(requests):
        for c, request in enumerate(row):
            if request is None or raws[u][c]:
                continue
            member = source
            route = getattr(source, "source_for", None)
            if callable(route):
                try:
                    member = route(request.cluster)
                except AmuledError:
                    continue
            keys = getattr(member, "keys", None)
            if callable(keys):
                wanted[keys([request])[0]] = (u, c)
    if wanted:
        for key, row in store.rows(list(wanted)).items():
            u, c = wanted[key]
            raws[u][c] = row.raw


def describe_feedback(feedback: Any) -> str:
    """Where a feedback's beliefs come from, in words (for headers)."""
    from amuled_ma.deliberation.feedback import describe_identity

    source = getattr(feedback, "source", None)
    if source is not None:
        try:
            members = getattr(source, "members", None)
            if members:
                parts = []
                for member, agents in members:
                    who = ", ".join(agents) if agents else "the others"
                    parts.append(f"{who}: {describe_identity(member.identity())}")
                return "; ".join(parts)
            return describe_identity(source.identity())
        except (AmuledError, OSError, AttributeError):
            return str(getattr(source, "name", "source"))
    recording = getattr(feedback, "recording", None)
    if recording is not None:
        return f"replay ({Path(recording.path).name}, fused beliefs only)"
    return str(getattr(feedback, "name", "feedback"))


# ---------------------------------------------------------------------------------------
# The fusion of one state, explained


@dataclass
class FusionBreakdown:
    """The fusion of one state, with its intermediate quantities (``k`` answering agents).

    Attributes:
        rule: The fusion rule.
        agents: The agents that answered (fused), in order.
        left_out: The agents that did not answer (weight 0), with their statuses.
        beliefs: ``(k, A)`` their beliefs.
        bjs: ``(k, k)`` pairwise BJS divergences.
        bjs_mean: ``(k,)`` average divergence of each agent from the others.
        credibility: ``(k,)`` Xiao's ``Crd_i``.
        entropy: ``(k,)`` Deng entropy in bits.
        volume: ``(k,)`` information volume ``exp(E_d)``, normalised to sum 1.
        weights: ``(k,)`` final weights.
        wae: ``(A,)`` weighted average evidence (``bjs-dst``; None otherwise).
        conflicts: ``(k - 1,)`` Dempster's conflict at each combination.
        fused: ``(A,)`` the fused belief.

    """

    rule: str
    agents: list[str]
    left_out: list[tuple[str, str]]
    beliefs: np.ndarray
    bjs: np.ndarray
    bjs_mean: np.ndarray
    credibility: np.ndarray
    entropy: np.ndarray
    volume: np.ndarray
    weights: np.ndarray
    wae: np.ndarray | None
    conflicts: np.ndarray
    fused: np.ndarray


def fusion_breakdown(
    agents: Sequence[str], beliefs: np.ndarray, statuses: Sequence[str], rule: str
) -> FusionBreakdown | None:
    """Recompute one state's fusion over the agents that answered, with diagnostics.

    As the panel fuses (:meth:`~amuled_ma.deliberation.panel.MoralPanel.fused`): an agent
    without an answer abstains (left out, weight 0). None when no agent answered.
    """
    from amuled_ma.fusion import bjs_divergence, fuse

    beliefs = np.asarray(beliefs, dtype=np.float64)
    answered = [i for i, s in enumerate(statuses) if str(s) in FUSED_STATUSES]
    left_out = [(agents[i], str(statuses[i])) for i in range(len(agents)) if i not in answered]
    if not answered:
        return None
    sub = beliefs[answered]
    k = len(answered)
    diag = fuse(sub[None], rule, return_diagnostics=True)
    pairwise = bjs_divergence(sub[:, None, :], sub[None, :, :])
    bjs_mean = pairwise.sum(axis=1) / max(k - 1, 1)
    entropy = np.asarray(diag.entropy, dtype=np.float64)[0]
    volume = np.exp(entropy - entropy.max())
    volume = volume / volume.sum()
    conflicts = np.asarray(diag.conflicts, dtype=np.float64).reshape(-1)
    return FusionBreakdown(
        rule=rule,
        agents=[agents[i] for i in answered],
        left_out=left_out,
        beliefs=sub,
        bjs=pairwise,
        bjs_mean=bjs_mean,
        credibility=np.asarray(diag.credibility, dtype=np.float64)[0],
        entropy=entropy,
        volume=volume,
        weights=np.asarray(diag.weights, dtype=np.float64)[0],
        wae=None if diag.wae is None else np.asarray(diag.wae, dtype=np.float64)[0],
        conflicts=conflicts,
        fused=np.asarray(diag.fused, dtype=np.float64)[0],
    )


def load_actor(checkpoint: Path, scenario: Any) -> torch.nn.Module:
    """Load a policy for replay (:func:`~amuled_ma.learn.policies.load_policy`).

    Raises:
        CheckpointError: The checkpoint is missing or does not fit the scenario.

    """
    from amuled_ma.learn.policies import load_policy

    if not Path(checkpoint).is_file():
        raise CheckpointError(
            f"no policy at {checkpoint}; train the variant first ('amuled run' or "
            "'amuled finetune') or name another with --variant"
        )
    return load_policy(Path(checkpoint), scenario)
