"""The package uses torch, rsl-rl, pickle and numpy through their public API only.

A maintainer must be able to upgrade them: no ``_``-prefixed attribute of theirs is read.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import amuled_ma

PACKAGE = Path(amuled_ma.__file__).parent
#: rsl-rl objects whose attributes we must not write (its runner, algorithm, storage).
RSL_RL_OBJECTS = ("runner", "alg", "storage", "transition")
#: The one write we allow: the runner's public iteration counter, which ``learn`` leaves at
#: the iteration it ran (see ``PopulationTrainer.iterate``).
ALLOWED_WRITES = {"runner.current_learning_iteration"}


def sources() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def private_torch_uses(tree: ast.AST) -> list[str]:
    """Every attribute ``torch._x`` (or ``torch.<mod>._x``) read anywhere in a module."""
    return private_uses(tree, "torch")


def private_uses(tree: ast.AST, root: str) -> list[str]:
    """Every attribute ``<root>._x`` (or ``<root>.<mod>._x``) read or imported in a module.

    ``import <root>._x``, ``from <root>._x import y`` and ``from <root> import _x`` count
    too (``np`` is read as ``numpy``).
    """
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] == root:
                names = [alias.name for alias in node.names]
                found += [f"{node.module}.{n}" for n in names if is_private(n)]
                if any(map(is_private, parts)):
                    found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [
                alias.name
                for alias in node.names
                if alias.name.split(".")[0] == root and any(map(is_private, alias.name.split(".")))
            ]
    aliases = {root, "np"} if root == "numpy" else {root}
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not (node.attr.startswith("__") and node.attr.endswith("__"))  # __version__
        ):
            chain = [node.attr]
            value = node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in aliases:
                found.append(f"{root}." + ".".join(reversed(chain)))
    return found


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def rsl_rl_writes(tree: ast.AST) -> list[str]:
    """Assignments to an attribute of an rsl-rl runner, algorithm, storage or transition."""
    found = []
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            targets = [node.target]
        for target in targets:
            while isinstance(target, ast.Subscript):
                target = target.value
            if isinstance(target, ast.Attribute):
                owner = target.value
                name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", "")
                if name in RSL_RL_OBJECTS:
                    found.append(f"{name}.{target.attr}")
    return [w for w in found if w not in ALLOWED_WRITES]


def test_checkers_find_what_they_look_for():
    bad = ast.parse("import torch\ntorch._foreach_add_(a, b)\nx = torch.nn._reduction\n")
    assert sorted(private_torch_uses(bad)) == ["torch._foreach_add_", "torch.nn._reduction"]
    writes = ast.parse("self.alg.storage.step = 0\nrunner.current_learning_iteration = 1\n")
    assert rsl_rl_writes(writes) == ["storage.step"]


def test_no_private_torch_api():
    offenders = {}
    for path in sources():
        uses = private_torch_uses(ast.parse(path.read_text(encoding="utf-8")))
        if uses:
            offenders[str(path.relative_to(PACKAGE))] = uses
    assert offenders == {}


def test_private_pickle_and_numpy_uses_are_found():
    bad = ast.parse(
        "import pickle\nimport numpy as np\nfrom pickle import _Unpickler\n"
        "from numpy._core import multiarray\nimport numpy._core.multiarray\n"
        "class U(pickle._Unpickler):\n    dispatch = pickle._Unpickler.dispatch\n"
        "x = np._core.multiarray.scalar\ny = pickle.HIGHEST_PROTOCOL\n"
    )
    assert sorted(private_uses(bad, "pickle")) == [
        "pickle._Unpickler",
        "pickle._Unpickler",
        "pickle._Unpickler",
    ]
    assert sorted(private_uses(bad, "numpy")) == [
        "numpy._core",  # from numpy._core import multiarray
        "numpy._core",  # np._core.multiarray.scalar
        "numpy._core.multiarray",  # import numpy._core.multiarray
    ]


def test_no_private_pickle_or_numpy_api():
    """The authors' caches are read with :mod:`pickletools`, not pickle's private reader."""
    offenders = {}
    for path in sources():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        uses = private_uses(tree, "pickle") + private_uses(tree, "numpy")
        if uses:
            offenders[str(path.relative_to(PACKAGE))] = uses
    assert offenders == {}


def test_no_write_into_rsl_rl_objects():
    offenders = {}
    for path in sources():
        writes = rsl_rl_writes(ast.parse(path.read_text(encoding="utf-8")))
        if writes:
            offenders[str(path.relative_to(PACKAGE))] = writes
    assert offenders == {}


def test_no_fast_path_copy_of_rsl_rl():
    assert not (PACKAGE / "learn" / "fast_ppo.py").exists()
    text = "\n".join(p.read_text(encoding="utf-8") for p in sources())
    assert not re.search(r"\bfast_ppo\b", text)


def test_installed_torch_and_rsl_rl_are_in_the_pinned_ranges():
    """CI installs the newest release within each pin; the pins are what CI tests."""
    import tomllib
    from importlib.metadata import version

    from packaging.requirements import Requirement

    pyproject = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text(encoding="utf-8"))
    pins = {
        req.name: req.specifier
        for req in map(Requirement, pyproject["project"]["dependencies"])
        if req.name in ("torch", "rsl-rl-lib")
    }
    assert set(pins) == {"torch", "rsl-rl-lib"}
    for name, spec in pins.items():
        assert spec.contains(version(name).split("+")[0]), (name, version(name), str(spec))
        assert any(s.operator == "<" for s in spec), f"{name} needs an upper bound: {spec}"
