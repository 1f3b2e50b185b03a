"""Convert the authors' LLM-cache pickles into our recording JSON format (docs/authors.md).

No value is changed (float64 of the pickled scalar); what each cache value becomes: docs/authors.md.
"""

from __future__ import annotations

import json
import math
import numbers
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.authors.unpickle import load_pickle, short_repr
from amuled_ma.errors import AuthorsImportError
from amuled_ma.scenario import MORAL_AGENT  # our field (and exchange agent) for that answer

#: The authors' cluster names, in their order (the recordings' ``clusters``).
AUTHORS_CLUSTERS = ("consequentialist", "deontologist", "virtue", "care", "social justice")
#: The authors' key of the unprompted "behave as a moral agent" answer.
MORAL_KEY = "moral"
#: Keys a cache entry may hold besides the clusters and `MORAL_KEY`.
ENTRY_KEYS = ("rewards", "error", "response")
#: Our task name -> the name written in a recording's ``task``.
TASK_TITLES = {"findmilk": "FindMilk", "driving": "Driving"}
#: Folder-name prefixes of the authors' runs -> our task name.
FOLDER_TASKS = (("findmilk", "findmilk"), ("milk", "findmilk"), ("driv", "driving"))
#: Theory names in the authors' credence sentence -> their cluster name.
THEORY_CLUSTERS = {
    "consequentialist": "consequentialist",
    "deontological": "deontologist",
    "virtue ethics": "virtue",
    "care ethics": "care",
    "social justice ethics": "social justice",
}
_CREDENCES = re.compile(r"credence values:\s*\{([^{}]*)\}", re.IGNORECASE)


@dataclass
class ConvertedCache:
    """One converted cache and its counts.

    ``fused_only``: no entry holds cluster beliefs; ``errors``: states the authors flagged
    (their parser repaired an answer); ``invalid``: cluster beliefs written as ``null``;
    ``ignored_keys``: entry keys outside the authors' format.
    """

    source: Path
    task: str
    model: str
    recording: dict[str, Any]
    fused_only: bool = False
    errors: int = 0
    exchanges: int = 0
    total_conflicts: int = 0
    invalid: int = 0
    ignored_keys: list[str] = field(default_factory=list)

    @property
    def states(self) -> int:
        """Number of states."""
        return len(self.recording["states"])

    @property
    def detail(self) -> str:
        """The states and every nonzero count, for the import's report."""
        counts = (
            (self.fused_only, "fused beliefs only"),
            (self.exchanges, f"{self.exchanges} with raw replies"),
            (self.total_conflicts, f"{self.total_conflicts} all-zero (total conflict, flagged)"),
            (self.invalid, f"{self.invalid} invalid beliefs written as null"),
            (self.ignored_keys, f"keys not converted: {', '.join(self.ignored_keys)}"),
        )
        return ", ".join([f"{self.states} states", *(text for on, text in counts if on)])

    def to_json(self) -> str:
        """The recording as JSON text (standard JSON: no NaN), in the shared files' style."""
        return json.dumps(self.recording, allow_nan=False)


def model_slug(model: str) -> str:
    """File-name form of a model name: lower case, ``.`` -> ``_``, other odd characters ``-``."""
    slug = model.strip().lower().replace(".", "_")
    slug = re.sub(r"[^a-z0-9_-]+", "-", slug).strip("-")
    return slug or "model"


def task_of_folder(name: str) -> str | None:
    """Our task of an authors' run folder (``FindMilk-v4_42``, ``Driving_42``, ``Drive``)."""
    return next((task for prefix, task in FOLDER_TASKS if name.lower().startswith(prefix)), None)


def model_of_file(path: Path) -> str:
    """The model name of a cache file ``<model>_llm_cache.pickle``."""
    suffix = "_llm_cache.pickle"
    return path.name.removesuffix(suffix) if path.name.endswith(suffix) else path.stem


def _task_spec(task: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(action names, observation names)`` of one of our tasks."""
    from amuled_ma.tasks import get_task

    cls = get_task(task)
    return tuple(cls.action_names), tuple(cls.obs_names)


def _number(value: object) -> float | None:
    """``float(value)`` for a real number (numpy scalars included, no bools), else None."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        return None
    return float(value)


def _vector(value: object, n: int) -> list[float] | None:
    """A 1-D numeric array or list of ``n`` numbers as floats, else None."""
    if isinstance(value, np.ndarray) and (value.ndim != 1 or value.dtype.kind not in "fiu"):
        return None
    if not isinstance(value, np.ndarray | list | tuple) or len(value) != n:
        return None
    floats = [x for x in map(_number, value) if x is not None]
    return floats if len(floats) == n else None


def _fused(rewards: object, n: int) -> list[float] | None:
    """The fused belief ``{frozenset({'0'}): p0, ...}`` as a list over actions, else None."""
    if not isinstance(rewards, Mapping) or len(rewards) != n:
        return None
    out: list[float | None] = [None] * n
    for key, value in rewards.items():
        if not (isinstance(key, frozenset) and len(key) == 1):
            return None
        (label,) = key
        if not (isinstance(label, str) and label.isdigit() and int(label) < n):
            return None
        out[int(label)] = _number(value)
    if any(x is None or not math.isfinite(x) for x in out):
        return None
    return out  # type: ignore[return-value]


def exchange_agent(prompt: str, position: int) -> str:
    """The agent a raw reply belongs to: the theory at credence 1.0 in its prompt.

    A prompt without a credence sentence is the moral agent's; otherwise the authors' call
    order (the five clusters, then the moral agent) by ``position``.
    """
    match = _CREDENCES.search(prompt)
    if match is None:
        if "credence" not in prompt.lower():
            return MORAL_AGENT
    else:
        ones: list[str] = []
        for part in match.group(1).split(","):
            theory, _, value = part.partition(":")
            try:
                weight = float(value)
            except ValueError:
                ones = []
                break
            if weight == 1.0:
                ones.append(theory.strip().lower())
        if len(ones) == 1 and ones[0] in THEORY_CLUSTERS:
            return THEORY_CLUSTERS[ones[0]]
    order = (*AUTHORS_CLUSTERS, MORAL_AGENT)
    return order[position] if position < len(order) else f"reply_{position}"


def convert_cache(
    path: str | Path, *, task: str | None = None, model: str | None = None
) -> ConvertedCache:
    """Read one authors' LLM cache (safely) and convert it to a recording.

    ``task`` None: the folder's, else by observation length; ``model`` None: the file name's.

    Raises:
        UnsafePickleError: The pickle names a global outside the allow-list.
        AuthorsImportError: Not the authors' cache format (naming file, state and what was
            found), or its task cannot be told.
    """
    path = Path(path)
    cache = load_pickle(path)
    if not isinstance(cache, dict) or len(cache) == 0:
        # never the value's truth: an array of several values has none (numpy raises)
        found = "an empty dict" if isinstance(cache, dict) else type(cache).__name__
        if isinstance(cache, np.ndarray):
            found += f" of shape {cache.shape} and dtype {cache.dtype}"
        raise AuthorsImportError(
            f"{path}: expected the authors' LLM cache (a dict observation -> answers), found "
            f"{found}"
        )
    first = next(iter(cache))
    dims = {len(k) for k in cache if isinstance(k, tuple)}
    if not isinstance(first, tuple) or len(dims) != 1:
        raise AuthorsImportError(
            f"{path}: cache keys must be observation tuples of one length, found "
            f"{type(first).__name__} keys of lengths {sorted(dims)}"
        )
    by_dim = {len(_task_spec(t)[1]): t for t in TASK_TITLES}
    (dim,) = dims
    folder_task = task or task_of_folder(path.parent.name)
    task = folder_task or by_dim.get(dim)
    if task not in TASK_TITLES:
        raise AuthorsImportError(
            f"{path}: cannot tell the task (folder {path.parent.name!r}, observations of "
            f"{dim} values); expected FindMilk (8) or Driving (11)"
        )
    actions, layout = _task_spec(task)
    if dim != len(layout):
        raise AuthorsImportError(
            f"{path}: observations of {dim} values, but {TASK_TITLES[task]} has {len(layout)} "
            f"({', '.join(layout)}); is the file in the right folder?"
        )
    model = model or model_of_file(path)
    n = len(actions)
    out = ConvertedCache(source=path, task=task, model=model, recording={})
    states: list[dict[str, Any]] = []
    ignored: set[str] = set()
    any_cluster = False
    for i, (key, entry) in enumerate(cache.items()):
        where = f"{path}: state {i}"
        obs = [_number(x) for x in key] if isinstance(key, tuple) else [None]
        if any(x is None or not math.isfinite(x) for x in obs):
            raise AuthorsImportError(f"{where}: the key must be a tuple of finite numbers")
        where = f"{path}: state {i} (obs {obs})"
        if not isinstance(entry, dict):
            raise AuthorsImportError(f"{where}: expected a dict of answers, found {type(entry)}")
        fused = _fused(entry.get("rewards"), n)
        if fused is None:
            raise AuthorsImportError(
                f"{where}: 'rewards' must map frozenset({{'0'}}) .. frozenset({{'{n - 1}'}}) to "
                f"finite numbers ({n} actions: {', '.join(actions)})"
            )
        beliefs: dict[str, list[float]] = {}
        for agent in (*AUTHORS_CLUSTERS, MORAL_KEY):
            if agent not in entry:
                continue
            vector = _vector(entry[agent], n)
            if vector is None:
                raise AuthorsImportError(
                    f"{where}: {agent!r} must be {n} numbers (one per action), found "
                    f"{short_repr(entry[agent])}"
                )
            beliefs[agent] = vector
        ignored.update(
            str(k) for k in entry if k not in (*AUTHORS_CLUSTERS, MORAL_KEY, *ENTRY_KEYS)
        )
        moral = beliefs.pop(MORAL_KEY, None)
        any_cluster = any_cluster or bool(beliefs)
        invalid: dict[str, str] = {}
        state: dict[str, Any] = {
            "obs": obs,
            "beliefs": {a: _checked(v, n, invalid, a) for a, v in beliefs.items()} or None,
            MORAL_AGENT: _checked(moral, n, invalid, MORAL_AGENT) if moral else None,
            "fused_by_reference": fused,
            "error": bool(entry.get("error", False)),
        }
        out.errors += state["error"]
        if not any(fused):
            state["total_conflict"] = True
            out.total_conflicts += 1
        if invalid:
            state["invalid_beliefs"] = invalid
            out.invalid += len(invalid)
        replies = entry.get("response")
        if replies is not None:
            if not isinstance(replies, dict) or not all(
                isinstance(q, str) and isinstance(r, str) for q, r in replies.items()
            ):
                raise AuthorsImportError(
                    f"{where}: 'response' must map prompts to reply texts, found "
                    f"{short_repr(replies)}"
                )
            state["exchanges"] = [
                {"agent": exchange_agent(q, j), "prompt": q, "response": r}
                for j, (q, r) in enumerate(replies.items())
            ]
            out.exchanges += 1
        states.append(state)
    out.fused_only = not any_cluster
    out.ignored_keys = sorted(ignored)
    out.recording = {
        "task": TASK_TITLES[task],
        "model": model,
        "clusters": list(AUTHORS_CLUSTERS),
        "actions": list(actions),
        "obs_layout": list(layout),
        "states": states,
    }
    return out


def _checked(
    vector: list[float], n: int, invalid: dict[str, str], agent: str
) -> list[float] | None:
    """``vector`` if it is a probability vector over ``n`` actions; else None, noting why."""
    from amuled_ma.beliefs.replies.validate import check_belief

    belief, reason = check_belief(vector, n)
    if belief is None:
        invalid[agent] = f"{vector} {reason}"
        return None
    return vector
