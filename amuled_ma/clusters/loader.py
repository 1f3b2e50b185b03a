"""Load and validate moral-cluster files (``prompts/clusters/<name>.toml``).

A moral cluster is data, not code: one TOML file per cluster agent. Three kinds exist:

- ``kind = "cluster"``: a moral cluster of the paper (focus, key principle, theories with
  key concepts and decision factors). It is described in the system prompt and is one
  coordinate of every credence vector. Its agent gets a one-hot credence on itself.
- ``kind = "mixture"``: an agent with a mixed credence vector over the ``cluster`` files
  (``credences = { consequentialist = 0.5, care = 0.5 }``); it adds nothing to the
  system prompt.
- ``kind = "unprompted"``: the paper's "moral agent" ablation: no credence vector, the
  state prompt ends with the file's ``instruction`` instead.

The full schema is in ``docs/clusters.md``. Every error names the file and the field.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from amuled_ma.errors import ClusterDefinitionError
from amuled_ma.resources import prompts_dir

#: Kinds of cluster files.
KINDS = ("cluster", "mixture", "unprompted")

#: The paper's sentence asking for a credence-weighted answer (``{credences}`` is the
#: comma-separated ``label: value`` list); word for word from the authors' code.
CREDENCE_INSTRUCTION = (
    "Behave as an agent that assigns the following credence values: {{{credences}}}. "
    "Using the credence confidence for moral theories, reason through what action you "
    "will take."
)

_KNOWN_FIELDS = {
    "name",
    "kind",
    "order",
    "title",
    "credence_label",
    "aliases",
    "focus",
    "key_principle",
    "theories",
    "credences",
    "instruction",
    "description",
}


@dataclass(frozen=True)
class Theory:
    """One ethical theory guiding a moral cluster.

    Attributes:
        name: Theory name, e.g. ``"Kantian Ethics"``.
        key_concepts: The theory's key concepts.
        decision_factors: Factors the theory takes into account when deciding.

    """

    name: str
    key_concepts: tuple[str, ...]
    decision_factors: tuple[str, ...]


@dataclass(frozen=True)
class Cluster:
    """One moral-cluster agent, as loaded from its TOML file.

    Attributes:
        name: Agent id (the file stem), e.g. ``"deontological"``.
        kind: ``"cluster"``, ``"mixture"`` or ``"unprompted"``.
        title: Display name used in the system prompt (``"Deontological Ethics"``).
        credence_label: Name used in credence sentences (``"Deontological"``).
        order: Position in the system prompt and in credence vectors (ascending).
        aliases: Other names of this agent (e.g. the recordings' ``"deontologist"``).
        focus: The cluster's focus (``kind="cluster"`` only).
        key_principle: The cluster's key principle (``kind="cluster"`` only).
        theories: The ethical theories guiding the cluster (``kind="cluster"`` only).
        credences: Credence per cluster name (``kind="mixture"`` only; ``None`` means
            one-hot on the cluster itself for ``kind="cluster"``).
        instruction: Last paragraph of the state prompt for ``kind="unprompted"``, or a
            template with ``{credences}`` overriding :data:`CREDENCE_INSTRUCTION`.
        description: Free text shown by ``amuled clusters list``.
        path: The file the cluster was loaded from.

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
    path: Path | None = field(default=None, compare=False)

    @property
    def names(self) -> tuple[str, ...]:
        """The cluster's name followed by its aliases."""
        return (self.name, *self.aliases)


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


def _string_list(value: Any, path: Path, key: str) -> tuple[str, ...]:
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
    out = {}
    for key, value in raw.items():
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise _fail(path, f"credences.{key}", f"expected a number, found {value!r}")
        if not math.isfinite(value) or value < 0:
            raise _fail(path, f"credences.{key}", f"expected a finite number >= 0, found {value!r}")
        out[key] = float(value)
    if sum(out.values()) <= 0:
        raise _fail(path, "credences", "all credences are 0")
    return out


def parse_cluster(data: Mapping[str, Any], path: Path) -> Cluster:
    """Validate one parsed cluster TOML document.

    Args:
        data: The parsed TOML.
        path: The file it came from (named in errors; its stem must equal ``name``).

    Returns:
        The validated cluster.

    Raises:
        ClusterDefinitionError: A field is missing, unknown, or of the wrong type.

    """
    unknown = set(data) - _KNOWN_FIELDS
    if unknown:
        raise _fail(
            path, sorted(unknown)[0], f"unknown field (known: {', '.join(sorted(_KNOWN_FIELDS))})"
        )
    name = _string(data, "name", path, required=True)
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
        "path": path,
        "credence_label": title,
    }
    if kind == "cluster":
        fields["credence_label"] = _string(data, "credence_label", path, required=True)
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
    """Load and validate one cluster file.

    Args:
        path: Path of a ``<name>.toml`` cluster file.

    Returns:
        The validated cluster.

    Raises:
        ClusterDefinitionError: The file is unreadable, not TOML, or a field is wrong.

    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise ClusterDefinitionError(f"{path}: cannot read cluster file: {error}") from error
    except tomllib.TOMLDecodeError as error:
        raise ClusterDefinitionError(f"{path}: not valid TOML: {error}") from error
    return parse_cluster(data, path)


def default_clusters_dir() -> Path:
    """Return the shipped ``prompts/clusters`` directory."""
    return prompts_dir() / "clusters"


class ClusterRegistry:
    """All known cluster agents: the shipped ones plus any extra directories.

    Files in a later directory replace a shipped cluster of the same name.

    Args:
        clusters: The clusters, in any order.

    """

    def __init__(self, clusters: Iterable[Cluster]) -> None:
        self._clusters: dict[str, Cluster] = {}
        for cluster in clusters:
            self._clusters[cluster.name] = cluster
        self._aliases: dict[str, str] = {}
        for cluster in self._clusters.values():
            for alias in cluster.aliases:
                self._aliases.setdefault(_norm(alias), cluster.name)
        for cluster in self._clusters.values():
            self._aliases[_norm(cluster.name)] = cluster.name
        for cluster in self._clusters.values():
            if cluster.kind == "mixture":
                for key in cluster.credences or {}:
                    target = self._resolve(key)
                    if target is None or self._clusters[target].kind != "cluster":
                        raise _fail(
                            cluster.path or Path(cluster.name),
                            f"credences.{key}",
                            "not the name of a kind = 'cluster' file (known: "
                            + ", ".join(c.name for c in self.panel())
                            + ")",
                        )

    @classmethod
    def load(
        cls, extra_dirs: Sequence[str | Path] = (), *, include_default: bool = True
    ) -> ClusterRegistry:
        """Load the shipped clusters and every ``*.toml`` of the extra directories.

        Args:
            extra_dirs: User directories of extra cluster files (later ones win).
            include_default: Whether to load the shipped ``prompts/clusters`` first.

        Returns:
            The registry.

        Raises:
            ClusterDefinitionError: A directory is missing or a file is malformed.

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
        return self._aliases.get(_norm(name))

    def get(self, name: str) -> Cluster:
        """Return the cluster called ``name`` (or one of its aliases).

        Raises:
            ClusterDefinitionError: No such cluster.

        """
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


def _norm(name: str) -> str:
    return " ".join(name.lower().replace("_", " ").replace("-", " ").split())


_DEFAULT: ClusterRegistry | None = None


def default_registry() -> ClusterRegistry:
    """Return the registry of shipped clusters (loaded once)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = ClusterRegistry.load()
    return _DEFAULT
