"""The chat sent to an LLM cluster agent: the authors' prompt byte for byte (docs/clusters.md)."""

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
    """Render ``prompts/system.md`` (shipped by default) with a section per cluster of ``panel``."""
    panel = default_registry().panel() if panel is None else list(panel)
    path = Path(prompts) / "system.md" if prompts else prompts_dir() / "system.md"
    template = _read_text(path).rstrip("\n")
    if CLUSTERS_PLACEHOLDER not in template:
        raise ClusterDefinitionError(f"{path}: missing the {CLUSTERS_PLACEHOLDER} placeholder")
    sections = "\n\n".join(render_cluster_section(c) for c in panel if c.kind == "cluster")
    return template.replace(CLUSTERS_PLACEHOLDER, sections)


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
    """Return the task's few-shot turns (its own file, else ``default.toml``), user first."""
    base = (Path(prompts) if prompts else prompts_dir()) / "fewshot"
    own = base / f"{''.join(ch for ch in task_name.lower() if ch.isalnum())}.toml"
    return _load_fewshot(own if own.is_file() else base / "default.toml")


def credence_vector(
    cluster: Cluster,
    panel: Sequence[Cluster] | None = None,
    credences: Mapping[str, float] | None = None,
    *,
    registry: ClusterRegistry | None = None,
) -> dict[str, float] | None:
    """Return the agent's ``{credence_label: value}`` over the panel, in panel order.

    ``credences`` (``{name or alias: value}``) overrides the agent's own; None: unprompted.

    Raises:
        ClusterDefinitionError: A credence names no panel cluster, or a value is not >= 0.
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
    """Return the agent's closing instruction: the credence sentence or its own text."""
    vector = credence_vector(cluster, panel, credences, registry=registry)
    if vector is None:
        return cluster.instruction or ""
    # each value as the authors wrote it: ``str`` of a float (``1.0``, ``0.5``)
    listed = ", ".join(f"{label}: {float(v)}" for label, v in vector.items())
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
    """Return ``(("system", ...), few-shot turns..., ("user", state + instruction))``.

    ``state_prompt`` lacks the closing instruction; ``panel``, ``credences``: `credence_vector`.
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
