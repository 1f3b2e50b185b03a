"""Load and validate moral-cluster files ``prompts/clusters/<name>.toml`` (docs/clusters.md)."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from amuled_ma.errors import ClusterDefinitionError, ScenarioError
from amuled_ma.files.resources import prompts_dir, read_text
from amuled_ma.scenario.agents import check_agent_table
from amuled_ma.scenario.loading import parse_toml
from amuled_ma.scenario.names import identity_key, odd_character

#: Kinds of cluster files.
KINDS = ("cluster", "mixture", "unprompted")

#: The paper's credence sentence, word for word (``{credences}``: the ``label: value`` list).
CREDENCE_INSTRUCTION = (
    "Behave as an agent that assigns the following credence values: {{{credences}}}. "
    "Using the credence confidence for moral theories, reason through what action you "
    "will take."
)

#: Largest accepted ``|sum(credences) - 1|`` of a mixture: allows six-decimal values
#: (``0.333334 + 0.333333 + 0.333333``), refuses ``0.999``.
CREDENCE_SUM_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Cluster:
    """One moral-cluster agent, as loaded from its TOML file (fields: docs/clusters.md)."""

    name: str
    kind: str
    title: str
    credence_label: str
    order: int = 1000
    aliases: tuple[str, ...] = ()
    focus: str = ""
    key_principle: str = ""
    theories: tuple[Theory, ...] = ()
    credences: Mapping[str, float] | None = None
    instruction: str | None = None
    description: str = ""
    source: Mapping[str, Any] | None = None
    path: Path | None = field(default=None, compare=False)

    @property
    def names(self) -> tuple[str, ...]:
        """The cluster's name followed by its aliases."""
        return (self.name, *self.aliases)


#: The keys a cluster file may hold: the fields of `Cluster` but ``path``.
_KNOWN_FIELDS = {f.name for f in fields(Cluster)} - {"path"}

_TEXT = "a non-empty string"
_SOURCE_TABLE = (
    'a table with a \'source\' kind, e.g. [source] source = "ollama", model = "llama3.1:8b"'
)
_NonEmpty = Annotated[str, Field(pattern=r"\S", description=_TEXT)]
_Strings = Annotated[
    tuple[_NonEmpty, ...],
    Field(min_length=1, strict=False, description="a non-empty list of non-empty strings"),
]


class Theory(BaseModel):
    """One ethical theory guiding a moral cluster: a ``[[theories]]`` table."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    name: _NonEmpty
    key_concepts: _Strings
    decision_factors: _Strings


class _ClusterFile(BaseModel):
    """A cluster file's keys and types; `parse_cluster` checks what joins keys."""

    model_config = ConfigDict(strict=True, allow_inf_nan=False)

    name: _NonEmpty
    kind: Literal["cluster", "mixture", "unprompted"] = Field(
        "cluster", description="one of " + ", ".join(KINDS)
    )
    title: _NonEmpty
    order: int = Field(1000, description="an integer")
    aliases: list[Annotated[str, Field(min_length=1)]] = Field(
        default_factory=list, description="a list of strings"
    )
    instruction: _NonEmpty | None = None
    description: str = Field("", description="a string")
    credence_label: _NonEmpty | None = None
    focus: _NonEmpty | None = None
    key_principle: _NonEmpty | None = None
    theories: Annotated[list[Theory], Field(min_length=1)] | None = Field(
        None, description="one or more [[theories]] tables"
    )
    credences: (
        Annotated[dict[str, Annotated[float, Field(ge=0, le=1)]], Field(min_length=1)] | None
    ) = Field(None, description="a table name = value")
    source: dict[str, Any] | None = Field(None, description=_SOURCE_TABLE)


def _what(loc: tuple[str | int, ...]) -> str:
    """What a key at ``loc`` expects, from the models' descriptions."""
    if loc[0] == "credences" and len(loc) > 1:
        return "a finite number between 0 and 1"
    if loc[0] == "theories" and len(loc) == 2:
        return "a table"
    if loc[0] == "theories" and len(loc) > 2:
        return Theory.model_fields[str(loc[2])].description or _TEXT
    return _ClusterFile.model_fields[str(loc[0])].description or _TEXT


def _field(loc: tuple[str | int, ...]) -> str:
    """``("theories", 0, "name")`` as ``theories[0].name``."""
    text = str(loc[0])
    for part in loc[1:]:
        text += f"[{part}]" if isinstance(part, int) else f".{part}"
    return text


def _refuse_odd_characters(path: Path, field_name: str, value: str) -> None:
    """Refuse a name holding a character that prints as nothing (`odd_character`)."""
    odd = odd_character(value)
    if odd is not None:
        raise _fail(
            path,
            field_name,
            f"expected a name of visible characters, found {value!r} holding {odd}, which "
            "prints as nothing or changes how another character looks; remove it",
        )


def _fail(path: Path, field_name: str, problem: str) -> ClusterDefinitionError:
    return ClusterDefinitionError(f"{path}: field {field_name!r}: {problem}")


def _check_credences(credences: Mapping[str, float], path: Path) -> None:
    """Refuse a cluster named twice (up to case and spacing) or credences not summing to 1."""
    seen: dict[str, str] = {}
    for key in credences:
        previous = seen.setdefault(identity_key(key), key)
        if previous != key:
            raise _fail(
                path,
                f"credences.{key}",
                f"expected each cluster once, found both {previous!r} and {key!r} (keys are "
                "compared ignoring case, '_', '-' and spaces); keep one of them",
            )
    total = math.fsum(credences.values())
    if abs(total - 1.0) > CREDENCE_SUM_TOLERANCE:
        fix = f"divide each value by {total:.12g}" if total > 0 else "give one a value above 0"
        raise _fail(
            path,
            "credences",
            f"expected values summing to 1 (within {CREDENCE_SUM_TOLERANCE:g}), found a sum of "
            f"{total:.12g}; fix the values so they add up to 1 ({fix})",
        )


def _source_table(table: dict[str, Any] | None, path: Path) -> dict[str, Any] | None:
    """The optional ``[source]`` table, checked like a scenario's ``[feedback.agents.<name>]``."""
    if table is None:
        return None
    if not isinstance(table.get("source"), str):
        raise _fail(path, "source", f"expected {_SOURCE_TABLE}; found {table!r}")
    try:
        check_agent_table(f"{path}: [source]", table, default_source="ollama", default_model="*")
    except ScenarioError as error:
        raise ClusterDefinitionError(str(error)) from None
    return dict(table)


#: The keys each kind needs besides ``name`` and ``title``.
_REQUIRED = {
    "cluster": ("credence_label", "focus", "key_principle", "theories"),
    "mixture": ("credences",),
    "unprompted": ("instruction",),
}


def load_cluster(path: str | Path) -> Cluster:
    """Load and validate one ``<name>.toml`` cluster file; its stem must equal ``name``.

    Raises ClusterDefinitionError: the file is unreadable, not TOML, or a field is missing,
        unknown, or of the wrong type.
    """
    path = Path(path)
    text = read_text(path, "cluster file", ClusterDefinitionError, max_bytes=MAX_CLUSTER_BYTES)
    data = parse_toml(text, path, "cluster file", ClusterDefinitionError, MAX_CLUSTER_CHARS)
    unknown = set(data) - _KNOWN_FIELDS
    if unknown:
        raise _fail(
            path, sorted(unknown)[0], f"unknown field (known: {', '.join(sorted(_KNOWN_FIELDS))})"
        )
    try:
        file = _ClusterFile.model_validate(data)
    except ValidationError as error:
        first = error.errors()[0]
        loc = first["loc"]
        if first["type"] == "extra_forbidden":
            raise _fail(path, _field(loc), "unknown field") from None
        if first["type"] == "missing":
            raise _fail(path, _field(loc), f"missing (expected {_what(loc)})") from None
        problem = f"expected {_what(loc)}, found {first['input']!r}"
        raise _fail(path, _field(loc), problem) from None
    for key, value in (("name", file.name), *(("aliases", a) for a in file.aliases)):
        _refuse_odd_characters(path, key, value)
    if file.name != path.stem:
        raise _fail(path, "name", f"must equal the file name {path.stem!r}, found {file.name!r}")
    for key in _REQUIRED[file.kind]:
        if getattr(file, key) is None:
            raise _fail(path, key, f"missing (expected {_what((key,))}; kind = {file.kind!r})")
    if file.kind != "mixture" and file.credences is not None:
        raise _fail(path, "credences", "only allowed with kind = 'mixture'")
    if file.kind != "unprompted" and file.instruction and "{credences}" not in file.instruction:
        raise _fail(path, "instruction", f"a {file.kind}'s instruction must contain {{credences}}")
    values = file.model_dump(include={"name", "kind", "title", "order", "description"})
    values.update(aliases=tuple(file.aliases), instruction=file.instruction, path=path)
    values.update(credence_label=file.title, source=_source_table(file.source, path))
    if file.kind == "cluster" and file.credence_label and file.theories:
        _refuse_odd_characters(path, "credence_label", file.credence_label)
        values.update(
            credence_label=file.credence_label, focus=file.focus, key_principle=file.key_principle
        )
        values["theories"] = tuple(file.theories)
    elif file.kind == "mixture" and file.credences is not None:
        _check_credences(file.credences, path)
        values["credences"] = dict(file.credences)
    return Cluster(**values)


#: Most characters a cluster file may hold (a shipped one holds about 2,000).
MAX_CLUSTER_CHARS = 200_000
#: Largest cluster file read [bytes]: 4 bytes per character (UTF-8's most).
MAX_CLUSTER_BYTES = 4 * MAX_CLUSTER_CHARS


def default_clusters_dir() -> Path:
    """Return the shipped ``prompts/clusters`` directory."""
    return prompts_dir() / "clusters"


class Override(NamedTuple):
    """A cluster replaced by a file of the same name in a later directory."""

    name: str
    old_path: Path | None
    new_path: Path | None


class ClusterRegistry:
    """All known cluster agents: the shipped ones plus any extra directories.

    A later directory's file replaces an earlier one of the same name (``overridden``).

    Raises:
        ClusterDefinitionError: Names or credence labels collide, or a mixture's credences
            name no cluster or one twice.
    """

    def __init__(self, clusters: Iterable[Cluster]) -> None:
        self.overridden: list[Override] = []
        by_identity: dict[str, Cluster] = {}
        for cluster in clusters:
            identity = identity_key(cluster.name)
            old = by_identity.get(identity)
            if (
                old is not None
                and not _same_file(old.path, cluster.path)
                and _spelling(old.name) != _spelling(cluster.name)
            ):
                raise _fail(
                    _where(cluster),
                    "name",
                    f"expected a name that does not only look like another cluster's, found "
                    f"{cluster.name!r} ({_codepoints(cluster.name)}), which reads as "
                    f"{old.name!r} of {old.path} once width, invisible characters and "
                    "look-alike letters are set aside; rename it (or name the file exactly "
                    f"{old.name!r} to override that cluster)",
                )
            if old is not None and not _same_file(old.path, cluster.path):
                if _same_folder(old.path, cluster.path):
                    raise _fail(
                        _where(cluster),
                        "name",
                        f"expected cluster names unique within one directory (compared "
                        f"ignoring case, '_', '-' and spaces), found {cluster.name!r} here and "
                        f"{old.name!r} in {old.path}; rename or remove one of the two files",
                    )
                self.overridden.append(Override(cluster.name, old.path, cluster.path))
            by_identity[identity] = cluster
        self._clusters: dict[str, Cluster] = {c.name: c for c in by_identity.values()}
        labels: dict[str, Cluster] = {}
        for cluster in self.panel():
            other = labels.setdefault(identity_key(cluster.credence_label), cluster)
            if other is not cluster:
                raise _fail(
                    _where(cluster),
                    "credence_label",
                    f"expected a label no other cluster uses (compared ignoring case and "
                    f"spacing), found {cluster.credence_label!r}, already the label "
                    f"{other.credence_label!r} of {other.name!r} in {_where(other)}; choose "
                    "another credence_label",
                )
        self._aliases: dict[str, str] = {}
        for cluster in self._clusters.values():
            for alias in cluster.aliases:
                self._aliases.setdefault(identity_key(alias), cluster.name)
        for cluster in self._clusters.values():
            self._aliases[identity_key(cluster.name)] = cluster.name
        for cluster in self._clusters.values():
            if cluster.kind == "mixture":
                self._check_mixture(cluster)

    def _check_mixture(self, cluster: Cluster) -> None:
        first_key: dict[str, str] = {}
        for key in cluster.credences or {}:
            target = self._resolve(key)
            if target is None or self._clusters[target].kind != "cluster":
                raise _fail(
                    _where(cluster),
                    f"credences.{key}",
                    "not the name of a kind = 'cluster' file (known: "
                    + ", ".join(c.name for c in self.panel())
                    + ")",
                )
            first = first_key.setdefault(target, key)
            if first != key:
                raise _fail(
                    _where(cluster),
                    f"credences.{key}",
                    f"expected each cluster once, found both {first!r} and {key!r}, which "
                    f"both name the cluster {target!r}; keep one of them",
                )

    @classmethod
    def load(
        cls, extra_dirs: Sequence[str | Path] = (), *, include_default: bool = True
    ) -> ClusterRegistry:
        """Load the shipped clusters and every ``*.toml`` of ``extra_dirs`` (later ones win).

        Raises ClusterDefinitionError: a directory is missing, a file is bad, or names collide.
        """
        dirs = [default_clusters_dir()] if include_default else []
        dirs += [Path(d) for d in extra_dirs]
        clusters = []
        for directory in dirs:
            if not directory.is_dir():
                raise ClusterDefinitionError(f"{directory}: cluster directory not found")
            clusters += [load_cluster(p) for p in sorted(directory.glob("*.toml"))]
        return cls(clusters)

    def _resolve(self, name: str) -> str | None:
        return self._aliases.get(identity_key(name))

    def get(self, name: str) -> Cluster:
        """Return the cluster called ``name`` or aliased so; ``ClusterDefinitionError`` if none."""
        resolved = self._resolve(name)
        if resolved is None:
            raise ClusterDefinitionError(
                f"unknown moral cluster {name!r}; known: {', '.join(self.names())}"
            )
        return self._clusters[resolved]

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self._resolve(name) is not None

    def all(self) -> list[Cluster]:
        """Every cluster, sorted by ``(order, name)``."""
        return sorted(self._clusters.values(), key=lambda c: (c.order, c.name))

    def names(self) -> list[str]:
        """Names of every cluster, sorted by ``(order, name)``."""
        return [c.name for c in self.all()]

    def panel(self) -> list[Cluster]:
        """Return the ``kind = "cluster"`` files: the system prompt's clusters and credence axes."""
        return [c for c in self.all() if c.kind == "cluster"]


def _spelling(name: str) -> str:
    """A name as written, up to case, ``_``, ``-`` and spaces (not look-alikes)."""
    return " ".join(name.lower().replace("_", " ").replace("-", " ").split())


def _codepoints(name: str) -> str:
    """The characters of a name beyond printable ASCII, as ``U+0430``."""
    odd = [f"U+{ord(c):04X}" for c in name if not (c.isascii() and c.isprintable())]
    return "characters " + ", ".join(dict.fromkeys(odd)) if odd else "plain ASCII"


def _where(cluster: Cluster) -> Path:
    return cluster.path or Path(cluster.name)


def _same_file(a: Path | None, b: Path | None) -> bool:
    return a is not None and b is not None and a.resolve() == b.resolve()


def _same_folder(a: Path | None, b: Path | None) -> bool:
    return a is not None and b is not None and a.parent.resolve() == b.parent.resolve()


@functools.cache
def default_registry() -> ClusterRegistry:
    """Return the registry of shipped clusters (loaded once)."""
    return ClusterRegistry.load()
