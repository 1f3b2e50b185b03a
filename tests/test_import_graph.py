"""No import cycles between the modules of ``amuled_ma``.

The graph (:mod:`import_graph`) holds every import of an ``amuled_ma`` module at any nesting
level, ``if TYPE_CHECKING:`` aside; the test fails listing each cycle with the import lines
that close it.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from import_graph import PACKAGE, ROOT, describe, import_graph, strongly_connected


def test_cycle_finder_finds_a_hand_made_cycle() -> None:
    graph = {"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": [], "e": ["e", "a"]}
    assert strongly_connected(graph) == [["a", "b", "c"]]
    assert strongly_connected({"x": ["y"], "y": []}) == []


def test_graph_sees_function_level_relative_and_submodule_imports(tmp_path: Path) -> None:
    files = {
        "pkg/__init__.py": "from pkg.a import A\n",
        "pkg/a.py": "import typing\nif typing.TYPE_CHECKING:\n    import pkg.c\nA = 1\n",
        "pkg/b.py": "def f():\n    from . import a\n    from .sub import thing\n",
        "pkg/sub/__init__.py": "thing = 1\n",
        "pkg/sub/x.py": "from .. import b\nfrom ..sub import x\n",
        "pkg/c.py": "import pkg.sub.x\nclass C:\n    def g(self):\n        from pkg import b\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(textwrap.dedent(text))
    graph = import_graph(tmp_path, "pkg")
    assert {k: sorted(v) for k, v in graph.items()} == {
        "pkg": ["pkg.a"],
        "pkg.a": [],  # the TYPE_CHECKING import is not an edge
        "pkg.b": ["pkg.a", "pkg.sub"],
        "pkg.sub": [],
        "pkg.sub.x": ["pkg.b"],  # the self-import is not an edge
        "pkg.c": ["pkg.b", "pkg.sub.x"],
    }
    graph["pkg.b"]["pkg.c"] = [("pkg/b.py", 9)]  # close a cycle by hand
    (component,) = strongly_connected(graph)
    assert component == ["pkg.b", "pkg.c", "pkg.sub.x"]
    assert "pkg.c -> pkg.b  (pkg/c.py:4)" in describe(graph, component)


def test_amuled_ma_has_no_import_cycles() -> None:
    graph = import_graph(ROOT, PACKAGE)
    assert len(graph) > 50  # the whole package was read
    cycles = strongly_connected(graph)
    assert not cycles, "import cycles in amuled_ma:\n" + "\n".join(
        describe(graph, component) for component in cycles
    )
