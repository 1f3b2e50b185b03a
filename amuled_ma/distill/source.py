"""`DistilledSource`: the panel asked only where a distilled reward model is unsure."""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.beliefs.replies.validate import check_belief
from amuled_ma.beliefs.store.cached import requests_sent
from amuled_ma.beliefs.store.rows import CACHEABLE
from amuled_ma.beliefs.types import (
    MODEL_STATUSES,
    UNASKED,
    BeliefRequest,
    BeliefResult,
    BeliefSource,
    ask,
)
from amuled_ma.distill.budget import BudgetLedger
from amuled_ma.distill.model import EnsembleModel, FitSettings
from amuled_ma.distill.selection import (
    choose_random,
    choose_uncertain,
    disagreement,
)
from amuled_ma.distill.state import (
    SAVE_EVERY_S,
    START_OVER,
    LedgerRest,
    StateFiles,
    checked,
)
from amuled_ma.errors import AmuledError

if TYPE_CHECKING:
    from amuled_ma.scenario import DistillConfig

#: Statuses of the model's belief for a state not asked, and in place of an asked state's
#: replay miss or abstention.
DISTILLED, DISTILLED_MISS = MODEL_STATUSES
#: Inner statuses the model answers instead with ``answer_misses``.
MISS_STATUSES = frozenset({"replay_miss", "abstained"})


@dataclass
class DistillStats:
    """Counters of a `DistilledSource`, kept across a resume (``docs/distill.md``, "Accounting")."""

    requests_forwarded: int = 0
    requests_sent: int = 0
    model_answers: int = 0
    miss_answers: int = 0
    unasked_answers: int = 0
    refits: int = 0


@dataclass
class _State:
    """One state of a batch: its key, observation and each member's request positions."""

    key: str
    obs: tuple[float, ...]
    positions: dict[str, list[int]] = field(default_factory=dict)


@dataclass
class _Example:
    """The panel's answers to one asked state (members that did not answer are absent)."""

    key: str
    obs: np.ndarray
    beliefs: dict[str, np.ndarray]
    holdout: bool


class DistilledSource(BeliefSource):
    """The panel's source behind a budget and a distilled model.

    The settings are ``[feedback.distill]``'s (`DistillConfig`, checked there); ``fusion_rule``
    fuses the held-out agreement; ``state_dir`` None keeps nothing on disk, and without
    ``resume`` its state files are removed. `AmuledError`: a budget out of range, or
    ``resume`` with state files written with other settings or damaged.
    """

    name = "distilled"

    def __init__(
        self,
        source: BeliefSource,
        *,
        budget: float | int = 0.1,
        selection: str = "uncertainty",
        ensemble: int = 5,
        hidden: int = 64,
        refit_every: int = 32,
        holdout: float = 0.2,
        answer_misses: bool = False,
        seed: int = 0,
        fusion_rule: str = "bjs-dst",
        state_dir: str | Path | None = None,
        resume: bool = False,
        fit_steps: int = 400,
    ) -> None:
        self.source = source
        self.ledger = BudgetLedger(budget)
        self.budget = self.ledger.budget
        self.selection = selection
        self.refit_every = int(refit_every)
        self.holdout = float(holdout)
        self.answer_misses = bool(answer_misses)
        self.seed = int(seed)
        self.fusion_rule = fusion_rule
        self.fit = FitSettings(ensemble=int(ensemble), hidden=int(hidden), steps=int(fit_steps))
        self.stats = DistillStats()
        self.members: list[str] = []
        self.actions: tuple[str, ...] | None = None
        self.task: str | None = None
        self.obs_dim: int | None = None
        self.model: EnsembleModel | None = None
        #: Number of fits so far (the feedback's memo refreshes the model's answers on a change).
        self.generation = 0
        self.agreement: dict[str, Any] = {}
        self._asked_obs: dict[str, tuple[float, ...]] = {}
        self._examples: dict[str, _Example] = {}
        # the panel's answers to the states asked in this process (one forward each)
        self._answers: dict[str, dict[str, BeliefResult]] = {}
        self._fit_examples = 0
        self._rng = np.random.Generator(np.random.PCG64(self.seed))
        self._files = StateFiles(state_dir) if state_dir is not None else None
        self._changed = False
        if self._files is not None:
            if resume and self._files.ledger.is_file():
                self._load()
            else:  # a fine-tune that starts over
                for path in (self._files.ledger, self._files.examples):
                    path.unlink(missing_ok=True)

    @classmethod
    def from_config(
        cls,
        source: BeliefSource,
        config: DistillConfig,
        *,
        seed: int,
        fusion_rule: str,
        state_dir: str | Path | None = None,
        resume: bool = False,
    ) -> DistilledSource:
        """Build from a ``[feedback.distill]`` section (its ``seed``, if set, wins)."""
        return cls(
            source,
            **config.model_dump(exclude={"enabled", "model", "seed"}),
            seed=seed if config.seed is None else config.seed,
            fusion_rule=fusion_rule,
            state_dir=state_dir,
            resume=resume,
        )

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]
        """Whether the panel's source reads the chat (the state key then includes it)."""
        return bool(getattr(self.source, "needs_messages", True))

    def identity(self) -> dict[str, Any]:
        """The panel's source's identity (the store keys are the inner source's)."""
        return self.source.identity()

    def source_for(self, agent: str) -> Any:
        """The source answering ``agent``'s asked states (for messages)."""
        per_agent = getattr(self.source, "source_for", None)
        return per_agent(agent) if callable(per_agent) else self.source

    def close(self) -> None:
        """Write the state file and close the panel's source."""
        try:
            self._save(force=True)
        finally:
            self.source.close()

    def settings(self) -> dict[str, Any]:
        """What decides this source's answers besides the panel (kept in the state file)."""
        return {
            "model": "mlp",
            "budget": self.budget,
            "selection": self.selection,
            "ensemble": self.fit.ensemble,
            "hidden": self.fit.hidden,
            "refit_every": self.refit_every,
            "holdout": self.holdout,
            "answer_misses": self.answer_misses,
            "seed": self.seed,
            "fusion_rule": self.fusion_rule,
        }

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Forward asked states to the panel's source, answer the others by the model.

        `RuntimeError`: the panel's source answered another number of results; `AmuledError`:
        the requests change task, actions or observation length.
        """
        if not requests:
            return []
        states = self._group(requests)
        ledger = self.ledger
        if ledger.visit(s.key for s in states):
            self._changed = True
        known = [s for s in states if ledger.is_asked(s.key)]
        candidates = [s for s in states if not ledger.is_asked(s.key)]
        remembered = [s for s in known if s.key in self._answers]
        known = [s for s in known if s.key not in self._answers]
        chosen = self._choose(candidates, ledger.allowed())
        if chosen:
            ledger.ask(s.key for s in chosen)
            for s in chosen:
                self._asked_obs[s.key] = s.obs
            self._save(force=True)  # spend the budget before asking
        results: list[BeliefResult | None] = [None] * len(requests)
        forward = known + chosen
        if forward:
            self._forward(forward, requests, results)
        self._recall(remembered, results)
        forward += remembered
        since = sum(1 for e in self._examples.values() if e.beliefs) - self._fit_examples
        if since > 0 and since >= min(self.refit_every, max(1, self._fit_examples)):
            self._refit()  # after 1, 2, 4, ... answered asked states, then every refit_every
        rest = [s for s in candidates if not ledger.is_asked(s.key)]
        self._answer(rest, results)
        if self.answer_misses:
            self._answer(forward, results, misses=True)
        self._save()
        return results  # type: ignore[return-value]

    def report(self) -> dict[str, Any]:
        """The accounting, JSON-ready: settings, state counts, counters, held-out agreement.

        ``holdout_tv`` (per member) and ``holdout_tv_fused`` are the mean total-variation distance
        between the model's and the panel's beliefs on the held-out states at the last fit.
        """
        ledger = self.ledger
        visited, asked = ledger.visited_count, ledger.asked_count
        return {
            **self.settings(),
            "visited_states": visited,
            "asked_states": asked,
            "asked_share": asked / visited if visited else 0.0,
            "cap": ledger.cap(),
            "model_states": visited - asked,
            **asdict(self.stats),
            "members": list(self.members),
            "holdout_states": self.agreement.get("states", 0),
            "holdout_tv": dict(self.agreement.get("tv", {})),
            "holdout_tv_fused": self.agreement.get("tv_fused"),
        }

    def _group(self, requests: Sequence[BeliefRequest]) -> list[_State]:
        """The batch's distinct states, in order of first request."""
        first = requests[0]
        if self.actions is None:
            self.actions = tuple(first.action_names)
            self.task, self.obs_dim = first.task, len(first.obs)
        occurrences: dict[tuple[bytes, str], int] = {}
        groups: dict[tuple[bytes, int], dict[str, list[int]]] = {}
        obs_of: dict[bytes, tuple[float, ...]] = {}
        for i, request in enumerate(requests):
            if (
                tuple(request.action_names) != self.actions
                or request.task != self.task
                or len(request.obs) != self.obs_dim
            ):
                raise AmuledError(
                    f"distilled feedback: a request for task {request.task!r} with actions "
                    f"{request.action_names} and {len(request.obs)} observations, after "
                    f"{self.task!r} with {self.actions} and {self.obs_dim}; one distilled "
                    "source serves one task"
                )
            raw = np.asarray(request.obs, dtype=np.float64).tobytes()
            obs_of.setdefault(raw, tuple(float(x) for x in request.obs))
            slot = occurrences.get((raw, request.cluster), 0)
            occurrences[(raw, request.cluster)] = slot + 1
            groups.setdefault((raw, slot), {}).setdefault(request.cluster, []).append(i)
        states: dict[str, _State] = {}
        for (raw, _slot), positions in groups.items():
            key = self._key(raw, positions, requests)
            state = states.get(key)
            if state is None:
                states[key] = _State(key, obs_of[raw], positions)
            else:  # the same state twice in one batch: answered alike
                for member, idx in positions.items():
                    state.positions.setdefault(member, []).extend(idx)
            for member in positions:
                if member not in self.members:
                    self.members.append(member)
                    self._changed = True
        return list(states.values())

    def _key(
        self, raw: bytes, positions: Mapping[str, list[int]], requests: Sequence[BeliefRequest]
    ) -> str:
        """A state's key: its observation and every member's chat (128-bit BLAKE2b)."""
        digest = hashlib.blake2b(digest_size=16)
        digest.update(raw)
        for member in sorted(positions):
            digest.update(b"\x1d" + member.encode("utf-8"))
            for role, content in requests[positions[member][0]].messages:
                digest.update(b"\x1e" + role.encode("utf-8") + b"\x1f" + content.encode("utf-8"))
        return digest.hexdigest()

    def _choose(self, candidates: list[_State], count: int) -> list[_State]:
        if count <= 0 or not candidates:
            return []
        if count >= len(candidates):
            return list(candidates)
        if self.selection == "random":
            picks = choose_random(len(candidates), count, self._rng)
            self._changed = True
        else:
            obs = np.asarray([s.obs for s in candidates], dtype=np.float64)
            spread = None
            if self.model is not None and self.model.fitted:
                spread = disagreement(self.model.predict_ensemble(obs), self.model.trained)
            asked = np.asarray(list(self._asked_obs.values()), dtype=np.float64)
            picks = choose_uncertain(obs, count, asked.reshape(-1, obs.shape[1]), spread)
        return [candidates[i] for i in picks]

    def _forward(
        self, forward: list[_State], requests: Sequence[BeliefRequest], results: list
    ) -> None:
        """Ask the panel's source about the asked states; keep their answers to learn from."""
        idx = [i for s in forward for positions in s.positions.values() for i in positions]
        before = requests_sent(self.source)
        answers = ask(self.source, [requests[i] for i in idx])
        after = requests_sent(self.source)
        self.stats.requests_forwarded += len(idx)
        self.stats.requests_sent += len(idx) if before is None or after is None else after - before
        self._changed = True
        for i, answer in zip(idx, answers, strict=True):
            results[i] = answer
        order = {key: n for n, key in enumerate(self.ledger.asked)}
        records: list[dict[str, Any]] = []
        a = len(self.actions or ())
        for s in forward:
            kept = {member: results[positions[0]] for member, positions in s.positions.items()}
            self._answers[s.key] = kept  # for the rest of this process: asked once per process
            answered: dict[str, np.ndarray] = {}
            for member, result in kept.items():
                if result.status in CACHEABLE:
                    belief, _ = check_belief(result.belief, a)
                    if belief is not None:
                        answered[member] = belief
            old = self._examples.get(s.key)
            if old is not None and set(answered) <= set(old.beliefs):
                continue
            beliefs = {**(old.beliefs if old else {}), **answered}
            example = _Example(
                s.key, np.asarray(s.obs, dtype=np.float64), beliefs, self._is_holdout(order[s.key])
            )
            self._examples[s.key] = example
            records.append({
                "key": s.key,
                "obs": list(s.obs),
                "beliefs": {m: b.tolist() for m, b in beliefs.items()},
            })  # fmt: skip
        if records and self._files is not None:
            self._files.append(records)
        if any(self._examples[r["key"]].holdout for r in records) and self.model is not None:
            self._measure([e for e in self._ordered_examples() if e.holdout and e.beliefs])

    def _recall(self, states: list[_State], results: list) -> None:
        """Copies of the panel's answers (failures included) to states asked in this process."""
        for s in states:
            kept = self._answers[s.key]
            for member, positions in s.positions.items():
                result = kept.get(member)
                if result is None:  # a member not asked with the state before: ask it now
                    raise AmuledError(
                        f"distilled feedback: state {s.key} was asked without {member!r}; one "
                        "distilled source serves one panel"
                    )
                for i in positions:
                    results[i] = result.copy()

    def _is_holdout(self, index: int) -> bool:
        """Whether the ``index``-th asked state (from 0) is held out (a ``holdout`` share)."""
        share = Fraction(self.holdout)
        return math.floor((index + 1) * share) > math.floor(index * share)

    def _ordered_examples(self) -> list[_Example]:
        return [self._examples[k] for k in self.ledger.asked if k in self._examples]

    def _arrays(self, examples: list[_Example]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k, a = len(self.members), len(self.actions or ())
        obs = np.asarray([e.obs for e in examples], dtype=np.float64).reshape(-1, self.obs_dim or 0)
        beliefs = np.full((len(examples), k, a), 1.0 / max(a, 1))
        mask = np.zeros((len(examples), k), dtype=bool)
        column = {m: j for j, m in enumerate(self.members)}
        for n, example in enumerate(examples):
            for member, belief in example.beliefs.items():
                beliefs[n, column[member]] = belief
                mask[n, column[member]] = True
        return obs, beliefs, mask

    def _refit(self, *, generation: int | None = None) -> None:
        """Fit a new model on the asked states that are not held out."""
        examples = [e for e in self._ordered_examples() if e.beliefs]
        self._fit_examples = len(examples)
        train = [e for e in examples if not e.holdout]
        if not train or self.actions is None:
            return
        new = self.generation + 1 if generation is None else generation
        model = EnsembleModel(self.members, len(self.actions), self.fit)
        # the fit's seed: a 63-bit integer drawn from (run seed, generation)
        words = np.random.SeedSequence([self.seed % 2**64, new]).generate_state(2)
        model.fit(*self._arrays(train), seed=(int(words[0]) << 31 ^ int(words[1])) % 2**63)
        self.model = model
        self.generation = new
        self.stats.refits = max(self.stats.refits, new)
        self._changed = True
        self._measure([e for e in examples if e.holdout])

    def _measure(self, held: list[_Example]) -> None:
        """Agreement of the model with the panel on the held-out asked states."""
        model = self.model
        if model is None or not held:
            self.agreement = {"states": len(held), "tv": {}, "tv_fused": None}
            return
        obs, real, mask = self._arrays(held)
        pred = model.predict(obs)
        use = mask & model.trained[None, :]
        tv = 0.5 * np.abs(pred - real).sum(-1)  # (N, K)
        per_member = {
            m: float(tv[use[:, j], j].mean()) for j, m in enumerate(self.members) if use[:, j].any()
        }
        from amuled_ma.fusion import fuse

        fused_tv = []
        patterns, inverse = np.unique(use, axis=0, return_inverse=True)
        for p, pattern in enumerate(patterns):
            if not pattern.any():
                continue
            rows = np.flatnonzero(inverse.reshape(-1) == p)
            cols = np.flatnonzero(pattern)
            a = np.asarray(fuse(real[rows][:, cols], self.fusion_rule), dtype=np.float64)
            b = np.asarray(fuse(pred[rows][:, cols], self.fusion_rule), dtype=np.float64)
            fused_tv += (0.5 * np.abs(a - b).sum(-1)).tolist()
        self.agreement = {
            "states": len(held),
            "tv": per_member,
            "tv_fused": float(np.mean(fused_tv)) if fused_tv else None,
        }

    def _answer(self, states: list[_State], results: list, *, misses: bool = False) -> None:
        """The model's beliefs for states not asked, or (``misses``) for asked states' misses.

        ``unasked`` where the model has no answer for a member; with ``misses`` only the replay
        misses and abstentions of the asked ``states`` are replaced (``distilled_miss``).
        """
        model = self.model if self.model is not None and self.model.fitted else None
        column = {m: j for j, m in enumerate(model.members)} if model else {}
        todo: list[tuple[int, str, list[int], int | None]] = []
        for n, s in enumerate(states):
            for member, positions in s.positions.items():
                j = column.get(member)
                known = model is not None and j is not None and bool(model.trained[j])
                if not misses or (known and results[positions[0]].status in MISS_STATUSES):
                    todo.append((n, member, positions, j if known else None))
        if not todo:
            return
        a = len(self.actions or ())
        pred = model.predict(np.asarray([s.obs for s in states])) if model else np.zeros(0)
        for n, member, positions, j in todo:
            if j is None:
                error = (
                    f"not asked, and no asked state has {member!r}'s answer yet for the "
                    "distilled model to learn from"
                )
                result = BeliefResult.failed(a, UNASKED, self.name, error)
                self.stats.unasked_answers += 1
            else:
                belief, _ = check_belief(pred[n, j], a)
                assert belief is not None  # a softmax is a valid belief
                inner = results[positions[0]]
                extra = {"generation": self.generation}
                if misses:
                    extra["inner_status"] = inner.status
                    self.stats.miss_answers += 1
                else:
                    self.stats.model_answers += 1
                result = BeliefResult(
                    belief,
                    DISTILLED_MISS if misses else DISTILLED,
                    self.name,
                    raw=inner.raw if misses else None,
                    extra=extra,
                )
            for m, i in enumerate(positions):
                results[i] = result if m == 0 else result.copy()
        self._changed = True

    def _save(self, *, force: bool = False) -> None:
        files = self._files
        recent = files is not None and time.monotonic() - files.saved_at < SAVE_EVERY_S
        if files is None or (not force and (not self._changed or recent)):
            return
        files.save({
            "settings": self.settings(),
            "ledger": self.ledger.to_dict(),
            "asked_obs": {k: list(v) for k, v in self._asked_obs.items()},
            "members": list(self.members),
            "task": self.task,
            "actions": list(self.actions) if self.actions is not None else None,
            "obs_dim": self.obs_dim,
            "generation": self.generation,
            "counters": asdict(self.stats),
            "rng": self._rng.bit_generator.state,  # PCG64 gives plain ints
        })  # fmt: skip
        self._changed = False

    def _load(self) -> None:
        """Continue from the state files: the budget spent, the pairs, the model refitted."""
        files = self._files
        assert files is not None
        data = files.load()
        where = str(files.ledger)
        saved = data.get("settings") or {}
        now = self.settings()
        diffs = [f"{k}: {saved.get(k)!r} -> {v!r}" for k, v in now.items() if saved.get(k) != v]
        if diffs:
            raise AmuledError(
                f"{where} was written with other [feedback.distill] settings (saved -> now: "
                f"{'; '.join(diffs)}); {START_OVER}"
            )
        rest = checked(LedgerRest, dict(data), where)
        self.ledger = BudgetLedger.from_dict(rest.ledger.model_dump(), where, budget=self.budget)
        asked = self.ledger.asked_count
        generation = data.get("generation", 0)
        if type(generation) is not int or not 0 <= generation <= asked:
            raise AmuledError(
                f"{where}: generation is {generation!r}, expected an integer in [0, {asked}] "
                f"(at most one fit per asked state); {START_OVER}"
            )
        self.stats = DistillStats(**rest.counters.model_dump())
        if self.stats.refits > asked:
            raise AmuledError(
                f"{where}: counters.refits ({self.stats.refits}) exceeds the {asked} states "
                f"asked; the file was edited or damaged; {START_OVER}"
            )
        self._asked_obs = {k: tuple(v) for k, v in rest.asked_obs.items()}
        self.members = list(rest.members)
        self.task = rest.task
        self.actions = tuple(rest.actions) if rest.actions is not None else None
        self.obs_dim = rest.obs_dim
        if rest.rng is not None:
            self._rng.bit_generator.state = rest.rng.model_dump()
        if set(self._asked_obs) != set(self.ledger.asked):
            raise AmuledError(
                f"{where}: asked_obs and ledger.asked name different states; {START_OVER}"
            )
        order = {key: n for n, key in enumerate(self.ledger.asked)}
        a = len(self.actions or ())
        for line, record in files.read_examples():
            key = record.key
            if key not in order:  # written only after the ledger charged it: edited
                raise AmuledError(
                    f"{line}: answers of state {key[:16]}, which {where} never "
                    f"asked (one of the files was edited); {START_OVER}"
                )
            if len(record.obs) != self.obs_dim:
                raise AmuledError(
                    f"{line}: obs has {len(record.obs)} values, but {where} says obs_dim "
                    f"{self.obs_dim} (one of the files was edited); {START_OVER}"
                )
            beliefs = {}
            for member, values in record.beliefs.items():
                belief, why = check_belief(values, a)
                if member not in self.members or belief is None:
                    what = (
                        f"{member!r}'s belief {why}"
                        if belief is None
                        else (f"a belief of {member!r}, not a member of {where}")
                    )
                    raise AmuledError(f"{line}: {what} (one of the files was edited); {START_OVER}")
                beliefs[member] = belief
            obs = np.asarray(record.obs, dtype=np.float64)
            self._examples[key] = _Example(key, obs, beliefs, self._is_holdout(order[key]))
        if generation > 0:
            self._refit(generation=generation)
