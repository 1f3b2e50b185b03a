"""The package uses torch and rsl-rl through their public API only (a maintainer can upgrade)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import amuled_ma

PACKAGE = Path(amuled_ma.__file__).parent
#: rsl-rl objects whose attributes we must not write (its runner, algorithm, storage).
RSL_RL_OBJECTS = ("runner", "alg", "storage", "transition")
#: The one write we allow: the runner's public iteration counter, which ``learn`` leaves at
#: the iteration it ran (see ``Trainer._iterate``).
ALLOWED_WRITES = {"runner.current_learning_iteration"}


def sources() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def private_torch_uses(tree: ast.AST) -> list[str]:
    """Every attribute ``torch._x`` (or ``torch.<mod>._x``) read anywhere in a module."""
    found = []
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
            if isinstance(value, ast.Name) and value.id == "torch":
                found.append("torch." + ".".join(reversed(chain)))
    return found


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
