"""Load and validate moral-cluster files ``prompts/clusters/<name>.toml`` (docs/clusters.md).

Every error names the file and the field.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

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
class Theory:
    """One ethical theory guiding a moral cluster."""

    name: str
    key_concepts: tuple[str, ...]
    decision_factors: tuple[str, ...]


@dataclass(frozen=True)
class Cluster:
    """One moral-cluster agent, as loaded from its TOML file (fields: docs/clusters.md).

    ``focus``, ``key_principle`` and ``theories`` are for ``kind="cluster"``; ``credences``
    for ``"mixture"``; ``source`` is the agent's default ``[source]`` table (None: the
    scenario's ``[feedback].source``).
    """

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


def _string(data: Mapping[str, Any], key: str, path: Path, *, required: bool) -> str:
    if key not in data:
        if required:
            raise _fail(path, key, "missing (expected a non-empty string)")
        return ""
    value = data[key]
    if not isinstance(value, str) or (required and not value.strip()):
        raise _fail(path, key, f"expected a non-empty string, found {value!r}")
    return value


def _string_list(value: object, path: Path, key: str) -> tuple[str, ...]:
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(v, str) and v.strip() for v in value)
    ):
        raise _fail(path, key, f"expected a non-empty list of non-empty strings, found {value!r}")
    return tuple(value)


def _theories(data: Mapping[str, Any], path: Path) -> tuple[Theory, ...]:
    if "theories" not in data:
        raise _fail(path, "theories", "missing (expected one or more [[theories]] tables)")
    raw = data["theories"]
    if not isinstance(raw, list) or not raw:
        raise _fail(path, "theories", f"expected one or more [[theories]] tables, found {raw!r}")
    theories = []
    for i, item in enumerate(raw):
        where = f"theories[{i}]"
        if not isinstance(item, dict):
            raise _fail(path, where, f"expected a table, found {item!r}")
        for key in ("name", "key_concepts", "decision_factors"):
            if key not in item:
                raise _fail(path, f"{where}.{key}", "missing")
        unknown = set(item) - {"name", "key_concepts", "decision_factors"}
        if unknown:
            raise _fail(path, f"{where}.{sorted(unknown)[0]}", "unknown field")
        name = item["name"]
        if not isinstance(name, str) or not name.strip():
            raise _fail(path, f"{where}.name", f"expected a non-empty string, found {name!r}")
        theories.append(
            Theory(
                name=name,
                key_concepts=_string_list(item["key_concepts"], path, f"{where}.key_concepts"),
                decision_factors=_string_list(
                    item["decision_factors"], path, f"{where}.decision_factors"
                ),
            )
        )
    return tuple(theories)


def _credences(data: Mapping[str, Any], path: Path) -> dict[str, float]:
    raw = data.get("credences")
    if not isinstance(raw, dict) or not raw:
        raise _fail(
            path, "credences", f"missing or empty (expected a table name = value), found {raw!r}"
        )
    out: dict[str, float] = {}
    seen: dict[str, str] = {}
    for key, value in raw.items():
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise _fail(path, f"credences.{key}", f"expected a number, found {value!r}")
        if not math.isfinite(value) or not 0 <= value <= 1:
            raise _fail(
                path,
                f"credences.{key}",
                f"expected a finite number between 0 and 1, found {value!r}",
            )
        previous = seen.setdefault(identity_key(key), key)
        if previous != key:
            raise _fail(
                path,
                f"credences.{key}",
                f"expected each cluster once, found both {previous!r} and {key!r} (keys are "
                "compared ignoring case, '_', '-' and spaces); keep one of them",
            )
        out[key] = float(value)
    total = math.fsum(out.values())
    if abs(total - 1.0) > CREDENCE_SUM_TOLERANCE:
        fix = f"divide each value by {total:.12g}" if total > 0 else "give one a value above 0"
        raise _fail(
            path,
            "credences",
            f"expected values summing to 1 (within {CREDENCE_SUM_TOLERANCE:g}), found a sum of "
            f"{total:.12g}; fix the values so they add up to 1 ({fix})",
        )
    return out


def _source_table(data: Mapping[str, Any], path: Path) -> dict[str, Any] | None:
    """The optional ``[source]`` table, checked like a scenario's ``[feedback.agents.<name>]``."""
    table = data.get("source")
    if table is None:
        return None
    if not isinstance(table, dict) or not isinstance(table.get("source"), str):
        raise _fail(
            path,
            "source",
            f"expected a table with a 'source' kind, e.g. [source] source = \"ollama\", "
            f'model = "llama3.1:8b"; found {table!r}',
        )
    try:
        check_agent_table(f"{path}: [source]", table, default_source="ollama", default_model="*")
    except ScenarioError as error:
        raise ClusterDefinitionError(str(error)) from None
    return dict(table)


def parse_cluster(data: Mapping[str, Any], path: Path) -> Cluster:
    """Validate one parsed cluster TOML document; ``path``'s stem must equal ``name``.

    Raises:
        ClusterDefinitionError: A field is missing, unknown, or of the wrong type.
    """
    unknown = set(data) - _KNOWN_FIELDS
    if unknown:
        raise _fail(
            path, sorted(unknown)[0], f"unknown field (known: {', '.join(sorted(_KNOWN_FIELDS))})"
        )
    name = _string(data, "name", path, required=True)
    _refuse_odd_characters(path, "name", name)
    if name != path.stem:
        raise _fail(path, "name", f"must equal the file name {path.stem!r}, found {name!r}")
    kind = data.get("kind", "cluster")
    if kind not in KINDS:
        raise _fail(path, "kind", f"expected one of {', '.join(KINDS)}, found {kind!r}")
    title = _string(data, "title", path, required=True)
    order = data.get("order", 1000)
    if isinstance(order, bool) or not isinstance(order, int):
        raise _fail(path, "order", f"expected an integer, found {order!r}")
    aliases = data.get("aliases", [])
    if not isinstance(aliases, list) or not all(isinstance(a, str) and a for a in aliases):
        raise _fail(path, "aliases", f"expected a list of strings, found {aliases!r}")
    for alias in aliases:
        _refuse_odd_characters(path, "aliases", alias)
    instruction = data.get("instruction")
    if instruction is not None and (not isinstance(instruction, str) or not instruction.strip()):
        raise _fail(path, "instruction", f"expected a non-empty string, found {instruction!r}")
    fields: dict[str, Any] = {
        "name": name,
        "kind": kind,
        "title": title,
        "order": order,
        "aliases": tuple(aliases),
        "instruction": instruction,
        "description": _string(data, "description", path, required=False),
        "source": _source_table(data, path),
        "path": path,
        "credence_label": title,
    }
    if kind == "cluster":
        fields["credence_label"] = _string(data, "credence_label", path, required=True)
        _refuse_odd_characters(path, "credence_label", fields["credence_label"])
        fields["focus"] = _string(data, "focus", path, required=True)
        fields["key_principle"] = _string(data, "key_principle", path, required=True)
        fields["theories"] = _theories(data, path)
        if "credences" in data:
            raise _fail(path, "credences", "only allowed with kind = 'mixture'")
        if instruction is not None and "{credences}" not in instruction:
            raise _fail(path, "instruction", "a cluster's instruction must contain {credences}")
    elif kind == "mixture":
        fields["credences"] = _credences(data, path)
        if instruction is not None and "{credences}" not in instruction:
            raise _fail(path, "instruction", "a mixture's instruction must contain {credences}")
    else:  # unprompted
        if instruction is None:
            raise _fail(path, "instruction", "missing (an unprompted agent needs its instruction)")
    return Cluster(**fields)


def load_cluster(path: str | Path) -> Cluster:
    """Load and validate one ``<name>.toml`` cluster file.

    Raises:
        ClusterDefinitionError: The file is unreadable, not TOML, or a field is wrong.
    """
    path = Path(path)
    text = read_text(path, "cluster file", ClusterDefinitionError, max_bytes=MAX_CLUSTER_BYTES)
    data = parse_toml(text, path, "cluster file", ClusterDefinitionError, MAX_CLUSTER_CHARS)
    return parse_cluster(data, path)


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

    Names are compared ignoring case, ``_``, ``-`` and spaces. A later directory's file
    replaces an earlier one of the same name (listed in ``overridden``).

    Raises:
        ClusterDefinitionError: Two clusters of one directory share a name, two clusters
            share a credence label, or a mixture's credences name no cluster or one twice.
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

        Raises:
            ClusterDefinitionError: A directory is missing, a file is bad, or clusters collide.
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

    def __iter__(self):
        return iter(self.all())

    def __len__(self) -> int:
        return len(self._clusters)

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


_DEFAULT: ClusterRegistry | None = None


def default_registry() -> ClusterRegistry:
    """Return the registry of shipped clusters (loaded once)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = ClusterRegistry.load()
    return _DEFAULT
