"""The imports of ``amuled_ma``: the layers contract of ``pyproject.toml`` and no module cycle.

``lint-imports`` (import-linter) checks the layers of ``docs/design.md`` as declared in
``[tool.importlinter]``; its graph (grimp) holds every import, lazy ones inside functions
included, ``if TYPE_CHECKING:`` aside. The cycle rule is checked here with grimp, because
import-linter's ``acyclic_siblings`` squashes packages (``cli`` -> ``commands`` and
``commands.demo`` -> ``cli`` is a cycle to it, and no module cycle) and never sees a cycle
through a package's ``__init__`` and its own modules.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[1]


def module_cycles(graph: grimp.ImportGraph) -> list[str]:
    """Each import ``a -> b`` from which a chain of imports leads back to ``a``."""
    found = []
    for importer in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(importer)):
            back = graph.find_shortest_chain(importer=imported, imported=importer)
            if back:
                lines = graph.get_import_details(importer=importer, imported=imported)
                at = ", ".join(f"l.{d['line_number']}" for d in lines)
                found.append(f"{importer} -> {imported} ({at}), back: {' -> '.join(back)}")
    return found


def test_the_layers_contract_is_kept() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run(
        [str(lint), "--no-cache", "--config", "pyproject.toml"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    # the contract was read and checked (not an empty configuration)
    assert "No import runs upward through the layers" in done.stdout and " 0 broken" in done.stdout


def test_the_cycle_check_finds_one_through_a_package_init() -> None:
    graph = grimp.ImportGraph()
    graph.add_import(importer="pkg", imported="pkg.base", line_number=3, line_contents="")
    graph.add_import(importer="pkg.base", imported="pkg.rng", line_number=5, line_contents="")
    graph.add_import(importer="pkg.other", imported="pkg.rng", line_number=1, line_contents="")
    assert module_cycles(graph) == []
    graph.add_import(importer="pkg.rng", imported="pkg", line_number=9, line_contents="")
    assert module_cycles(graph) == [
        "pkg -> pkg.base (l.3), back: pkg.base -> pkg.rng -> pkg",
        "pkg.base -> pkg.rng (l.5), back: pkg.rng -> pkg -> pkg.base",
        "pkg.rng -> pkg (l.9), back: pkg -> pkg.base -> pkg.rng",
    ]


def test_amuled_ma_has_no_import_cycles() -> None:
    graph = grimp.build_graph("amuled_ma", exclude_type_checking_imports=True, cache_dir=None)
    assert len(graph.modules) > 50  # the whole package was read
    found = module_cycles(graph)
    assert not found, "imports that close a cycle:\n  " + "\n  ".join(found)
