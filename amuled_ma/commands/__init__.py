"""Command groups of the ``amuled`` CLI, one module each.

A module here defines ``register(subparsers)``: it adds its sub-parser and sets
``handler=<callable(args) -> int>`` with ``set_defaults``. Modules are discovered
automatically; names starting with ``_`` are skipped.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterator
from types import ModuleType


def public_modules(package: ModuleType) -> Iterator[tuple[str, ModuleType]]:
    """``(name, module)`` of each module of ``package`` not named ``_...``, sorted by name."""
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield info.name, importlib.import_module(f"{package.__name__}.{info.name}")
