"""The packages of ``amuled_ma`` form layers, and no import runs upward.

From the top: the command line, the pipeline, the experiments, learning and evaluation, the
panel, beliefs, fusion / tasks / clusters, and at the bottom the scenario models, records,
errors and small helpers (``docs/design.md``, "Layers"). A module may import its own layer
and the layers below it. The graph (:mod:`import_graph`) holds every import at any nesting
level, lazy imports inside functions included (``if TYPE_CHECKING:`` aside: it never runs).
The package's own ``__init__`` (``amuled_ma``: the version and the Gymnasium ids) is loaded
before any of its modules by Python itself, so it belongs to no layer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from import_graph import PACKAGE, ROOT, Graph, import_graph

#: Top to bottom; each entry is a layer: the modules and packages in it (dotted, under
#: ``amuled_ma``). Every module of the package must fall in exactly one.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("cli", "__main__", "commands", "bench"),
    ("pipeline",),
    ("experiments", "authors", "study"),
    ("learn", "evaluate"),
    ("deliberation", "distill"),
    ("beliefs", "llm_server"),
    ("fusion", "tasks", "clusters"),
    ("scenario", "records", "variants"),  # descriptions: they import no domain package
    # small helpers
    (
        "errors",
        "urls",
        "resources",
        "file_hash",
        "file_limits",
        "torch_files",
        "run_lock",
        "safe_files",
        "tensorboard_log",
    ),
)


def layer_of(module: str, layers: Sequence[Sequence[str]], package: str = PACKAGE) -> int | None:
    """Index of the layer holding ``module`` (0 = top); None for the package itself.

    Raises:
        LookupError: The module is in no layer (a new package must be given one).

    """
    if module == package:
        return None
    rest = module[len(package) + 1 :]
    for index, members in enumerate(layers):
        if any(rest == m or rest.startswith(f"{m}.") for m in members):
            return index
    raise LookupError(f"{module} is in no layer of tests/test_layers.py LAYERS; add it to one")


def upward_imports(
    graph: Graph, layers: Sequence[Sequence[str]], package: str = PACKAGE
) -> list[str]:
    """Every import from a lower layer to a higher one: ``a (layer) -> b (layer) at file:line``."""
    found = []
    for source, targets in sorted(graph.items()):
        low = layer_of(source, layers, package)
        if low is None:
            continue
        for target, sites in sorted(targets.items()):
            high = layer_of(target, layers, package)
            if high is not None and high < low:
                at = ", ".join(f"{file}:{line}" for file, line in sites)
                found.append(
                    f"{source} ({'/'.join(layers[low])}) -> {target} "
                    f"({'/'.join(layers[high])}) at {at}"
                )
    return found


def test_the_checker_finds_a_hand_made_upward_import() -> None:
    layers = (("top",), ("mid",), ("low", "util"))
    graph: Mapping[str, dict[str, list[tuple[str, int]]]] = {
        "pkg": {"pkg.top": [("pkg/__init__.py", 1)]},  # the package itself: no layer
        "pkg.top.cmd": {"pkg.mid.a": [("pkg/top/cmd.py", 3)]},
        "pkg.mid.a": {"pkg.low": [("pkg/mid/a.py", 2)], "pkg.util": [("pkg/mid/a.py", 4)]},
        "pkg.low": {"pkg.util": [("pkg/low.py", 5)], "pkg.mid.a": [("pkg/low.py", 9)]},
        "pkg.util": {"pkg.top.cmd": [("pkg/util.py", 7)]},
    }
    assert upward_imports(graph, layers, "pkg") == [
        "pkg.low (low/util) -> pkg.mid.a (mid) at pkg/low.py:9",
        "pkg.util (low/util) -> pkg.top.cmd (top) at pkg/util.py:7",
    ]
    assert layer_of("pkg.mid.a", layers, "pkg") == 1
    try:
        layer_of("pkg.other", layers, "pkg")
    except LookupError as error:
        assert "pkg.other is in no layer" in str(error)
    else:  # pragma: no cover - the assertion above is the test
        raise AssertionError("a module outside every layer was accepted")


def test_every_module_is_in_one_layer() -> None:
    graph = import_graph(ROOT, PACKAGE)
    assert len(graph) > 50  # the whole package was read
    for module in graph:
        layer_of(module, LAYERS)
    flat = [m for layer in LAYERS for m in layer]
    assert len(flat) == len(set(flat)), "a name is in two layers"


def test_no_import_runs_upward() -> None:
    found = upward_imports(import_graph(ROOT, PACKAGE), LAYERS)
    assert not found, "imports that run upward through the layers:\n  " + "\n  ".join(found)
