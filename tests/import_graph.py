"""The module graph of ``amuled_ma``, read from its source (shared by the cycle and layer tests).

Every ``import`` and ``from ... import`` of an ``amuled_ma`` module is collected from the
source with :mod:`ast`, at any nesting level (module level and inside functions and
classes), except under ``if TYPE_CHECKING:``. Relative imports are resolved, and
``from pkg import name`` is an edge to ``pkg.name`` when that is a submodule, else to
``pkg`` (its ``__init__.py``). A cycle is a strongly connected component (Tarjan) of more
than one module (:func:`strongly_connected`).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "amuled_ma"

#: ``{module: {imported module: [(file, line), ...]}}``
Graph = dict[str, dict[str, list[tuple[str, int]]]]


def find_modules(root: Path, package: str) -> dict[str, Path]:
    """Map every module name of ``package`` (under ``root``) to its file."""
    modules = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST) -> Iterable[ast.Import | ast.ImportFrom]:
    """Every import node of ``tree``, skipping the bodies of ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def _owner(name: str, modules: Mapping[str, Path]) -> str | None:
    """The longest prefix of the dotted ``name`` that is a module of the package."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def _targets(
    node: ast.Import | ast.ImportFrom, module: str, modules: Mapping[str, Path]
) -> Iterable[str]:
    """The package modules one import statement of ``module`` loads."""
    if isinstance(node, ast.Import):
        for alias in node.names:
            target = _owner(alias.name, modules)
            if target is not None:
                yield target
        return
    base = node.module or ""
    if node.level:
        is_package = modules[module].name == "__init__.py"
        parts = module.split(".") if is_package else module.split(".")[:-1]
        parts = parts[: len(parts) - (node.level - 1)]
        base = ".".join([*parts, *([base] if base else [])])
    for alias in node.names:
        sub = f"{base}.{alias.name}"
        if alias.name != "*" and sub in modules:
            yield sub
        else:
            target = _owner(base, modules)
            if target is not None:
                yield target


def import_graph(root: Path, package: str) -> Graph:
    """Build the module graph of ``package`` (see the module docstring)."""
    modules = find_modules(root, package)
    graph: Graph = {name: {} for name in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        where = str(path.relative_to(root))
        for node in _imports(tree):
            for target in set(_targets(node, name, modules)) - {name}:
                graph[name].setdefault(target, []).append((where, node.lineno))
    return graph


def strongly_connected(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """Tarjan's algorithm (iterative): the components of more than one node, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def describe(graph: Graph, component: list[str]) -> str:
    """One cycle: its modules and every import between them, with file and line."""
    members = set(component)
    lines = [f"cycle of {len(component)} modules: {', '.join(component)}"]
    for source in component:
        for target, sites in sorted(graph[source].items()):
            if target in members:
                at = ", ".join(f"{file}:{line}" for file, line in sites)
                lines.append(f"  {source} -> {target}  ({at})")
    return "\n".join(lines)
