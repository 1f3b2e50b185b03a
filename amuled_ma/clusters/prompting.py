"""Build the chat sent to an LLM cluster agent: the paper's three blocks.

1. **System prompt**: ``prompts/system.md`` with ``{clusters}`` replaced by one section
   per ``kind = "cluster"`` file of the panel (the paper's five clusters by default),
   rendered with :data:`CLUSTER_SECTION` / :data:`THEORY_LINE`.
2. **Few-shot chain-of-thought examples**: ``prompts/fewshot/<task>.toml`` if it exists,
   else ``prompts/fewshot/default.toml`` (the paper's examples), as user/assistant turns.
3. **State prompt**: the task's rendered state (``amuled_ma.tasks.prompts``), a blank
   line, then the agent's instruction: the credence sentence
   (:data:`~amuled_ma.clusters.loader.CREDENCE_INSTRUCTION`) or, for the unprompted
   "moral agent", its own instruction.

With the shipped data, the output is byte for byte the prompt the authors sent
(``temetski/moral_agent``, ``algorithms/llm_moral.py``); the recordings'
``exchanges[].prompt`` show the third block.
"""

from __future__ import annotations

import functools
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path

from amuled_ma.clusters.loader import (
    CREDENCE_INSTRUCTION,
    Cluster,
    ClusterRegistry,
    default_registry,
)
from amuled_ma.errors import ClusterDefinitionError, PromptError
from amuled_ma.files.resources import MAX_PROMPT_BYTES, prompts_dir, read_text

#: One cluster's section of the system prompt (the authors' wording).
CLUSTER_SECTION = (
    "The {title} moral cluster provides a strong focus on {focus}. The key principle that "
    "drives this moral code is {key_principle}.\n"
    "This moral cluster is further guided by the following ethical theories:\n"
    "{theories}"
)
#: One theory line of a cluster section (the authors' wording).
THEORY_LINE = (
    "- {name}: This ethical theory adheres to the following key concepts: {concepts}. "
    "When making decisions, this theory must take into account the following factors: "
    "{factors}."
)
#: Placeholder of ``prompts/system.md`` replaced by the cluster sections.
CLUSTERS_PLACEHOLDER = "{clusters}"

Messages = tuple[tuple[str, str], ...]


def render_cluster_section(cluster: Cluster) -> str:
    """Render one ``kind = "cluster"`` cluster as its system-prompt section."""
    theories = "\n".join(
        THEORY_LINE.format(
            name=t.name, concepts=", ".join(t.key_concepts), factors=", ".join(t.decision_factors)
        )
        for t in cluster.theories
    )
    return CLUSTER_SECTION.format(
        title=cluster.title,
        focus=cluster.focus,
        key_principle=cluster.key_principle,
        theories=theories,
    )


@functools.lru_cache(maxsize=8)
def _read_text(path: Path) -> str:
    return read_text(path, "system prompt", PromptError, max_bytes=MAX_PROMPT_BYTES)


def render_system_prompt(
    panel: Sequence[Cluster] | None = None, *, prompts: str | Path | None = None
) -> str:
    """Render the system prompt describing the panel's moral clusters.

    Args:
        panel: The ``kind = "cluster"`` clusters to describe, in order; defaults to the
            shipped registry's panel (the paper's five clusters).
        prompts: A ``prompts/`` directory to read ``system.md`` from (default: shipped).

    Returns:
        The system prompt text.

    """
    panel = default_registry().panel() if panel is None else list(panel)
    path = Path(prompts) / "system.md" if prompts else prompts_dir() / "system.md"
    template = _read_text(path).rstrip("\n")
    if CLUSTERS_PLACEHOLDER not in template:
        raise ClusterDefinitionError(f"{path}: missing the {CLUSTERS_PLACEHOLDER} placeholder")
    sections = "\n\n".join(render_cluster_section(c) for c in panel if c.kind == "cluster")
    return template.replace(CLUSTERS_PLACEHOLDER, sections)


def _task_key(task_name: str) -> str:
    return "".join(ch for ch in task_name.lower() if ch.isalnum())


def fewshot_path(task_name: str, *, prompts: str | Path | None = None) -> Path:
    """Return the few-shot file used for a task (its own, else ``default.toml``)."""
    base = (Path(prompts) if prompts else prompts_dir()) / "fewshot"
    own = base / f"{_task_key(task_name)}.toml"
    return own if own.is_file() else base / "default.toml"


@functools.lru_cache(maxsize=32)
def _load_fewshot(path: Path) -> Messages:
    try:
        text = read_text(path, "few-shot file", ClusterDefinitionError, max_bytes=MAX_PROMPT_BYTES)
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ClusterDefinitionError(f"{path}: cannot read few-shot examples: {error}") from error
    except RecursionError:  # "[[[[..." thousands deep: one line, not a traceback
        raise ClusterDefinitionError(
            f"{path}: cannot read few-shot examples: nested deeper than Python can read; a "
            "few-shot file is [[examples]] tables of user and assistant text"
        ) from None
    examples = data.get("examples", [])
    if not isinstance(examples, list):
        raise ClusterDefinitionError(f"{path}: field 'examples': expected [[examples]] tables")
    out: list[tuple[str, str]] = []
    for i, example in enumerate(examples):
        for role in ("user", "assistant"):
            turn = example.get(role) if isinstance(example, dict) else None
            if not isinstance(turn, str) or not turn:
                raise ClusterDefinitionError(
                    f"{path}: field 'examples[{i}].{role}': missing or not a non-empty string"
                )
            out.append((role, turn))
    return tuple(out)


def fewshot_messages(task_name: str, *, prompts: str | Path | None = None) -> Messages:
    """Return the few-shot chain-of-thought turns for a task, as ``(role, content)`` pairs.

    Args:
        task_name: Task name (``"findmilk"``, ``"FindMilk"``, ``"driving"``...).
        prompts: A ``prompts/`` directory (default: shipped).

    Returns:
        Alternating ``("user", ...)``, ``("assistant", ...)`` pairs.

    """
    return _load_fewshot(fewshot_path(task_name, prompts=prompts))


def format_credence_value(value: float) -> str:
    """Format one credence the way the authors did (``str`` of a float: ``1.0``, ``0.5``)."""
    return str(float(value))


def credence_vector(
    cluster: Cluster,
    panel: Sequence[Cluster] | None = None,
    credences: Mapping[str, float] | None = None,
    *,
    registry: ClusterRegistry | None = None,
) -> dict[str, float] | None:
    """Return the credence vector of a cluster agent over the panel's clusters.

    Args:
        cluster: The agent.
        panel: The clusters the vector ranges over, in order (default: registry panel).
        credences: An explicit mixture ``{cluster name or alias: value}`` overriding the
            agent's own (one-hot for ``kind="cluster"``, the file's for ``"mixture"``).
        registry: Resolves names in ``credences`` (default: shipped registry).

    Returns:
        ``{credence_label: value}`` in panel order, or ``None`` for an unprompted agent
        without an explicit mixture.

    Raises:
        ClusterDefinitionError: A credence names no panel cluster, or a value is invalid.

    """
    registry = registry or default_registry()
    panel = registry.panel() if panel is None else list(panel)
    if credences is None:
        if cluster.kind == "unprompted":
            return None
        mixture = cluster.credences if cluster.kind == "mixture" else None
        credences = mixture if mixture is not None else {cluster.name: 1.0}
    by_name = {c.name: c for c in panel}
    values = {c.name: 0.0 for c in panel}
    for key, value in credences.items():
        target = registry.get(key).name if key in registry else key
        if target not in by_name:
            raise ClusterDefinitionError(
                f"credences for {cluster.name!r}: {key!r} is not a panel cluster "
                f"(panel: {', '.join(by_name)})"
            )
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
            raise ClusterDefinitionError(
                f"credences for {cluster.name!r}: {key!r} must be a number >= 0, found {value!r}"
            )
        values[target] = float(value)
    return {by_name[name].credence_label: value for name, value in values.items()}


def instruction_text(
    cluster: Cluster,
    panel: Sequence[Cluster] | None = None,
    credences: Mapping[str, float] | None = None,
    *,
    registry: ClusterRegistry | None = None,
) -> str:
    """Return the agent's closing instruction: the credence sentence or its own text.

    Example (the paper's care agent)::

        Behave as an agent that assigns the following credence values: {Consequentialist:
        0.0, Deontological: 0.0, Virtue Ethics: 0.0, Care Ethics: 1.0, Social Justice
        Ethics: 0.0}. Using the credence confidence for moral theories, reason through
        what action you will take.
    """
    vector = credence_vector(cluster, panel, credences, registry=registry)
    if vector is None:
        return cluster.instruction or ""
    listed = ", ".join(f"{label}: {format_credence_value(v)}" for label, v in vector.items())
    template = cluster.instruction if cluster.kind != "unprompted" and cluster.instruction else None
    if template is None:
        return CREDENCE_INSTRUCTION.format(credences=listed)
    return template.replace("{credences}", "{" + listed + "}")


def build_messages(
    cluster: Cluster | str,
    task_name: str,
    state_prompt: str,
    *,
    panel: Sequence[Cluster] | None = None,
    credences: Mapping[str, float] | None = None,
    registry: ClusterRegistry | None = None,
    prompts: str | Path | None = None,
    fewshot: bool = True,
) -> Messages:
    """Return the full chat for one cluster agent and one task state.

    Args:
        cluster: The agent (a :class:`Cluster` or a name/alias in ``registry``).
        task_name: Task name, selects the few-shot file.
        state_prompt: The rendered state (``render_state_prompt(task, variables)``),
            without the closing instruction.
        panel: Clusters of the system prompt and of the credence vector (default: the
            registry's ``kind = "cluster"`` files).
        credences: An explicit credence mixture for this agent (see
            :func:`credence_vector`).
        registry: Cluster registry (default: the shipped clusters).
        prompts: A ``prompts/`` directory (default: shipped).
        fewshot: Include the few-shot examples (the paper does).

    Returns:
        ``(("system", ...), ("user", ...), ("assistant", ...), ..., ("user", state))``.

    """
    registry = registry or default_registry()
    if isinstance(cluster, str):
        cluster = registry.get(cluster)
    panel = registry.panel() if panel is None else list(panel)
    system = render_system_prompt(panel, prompts=prompts)
    examples = fewshot_messages(task_name, prompts=prompts) if fewshot else ()
    instruction = instruction_text(cluster, panel, credences, registry=registry)
    user = f"{state_prompt}\n\n{instruction}" if instruction else state_prompt
    return (("system", system), *examples, ("user", user))
