"""Command groups of the ``amuled`` CLI, one module each.

A module here defines ``register(subparsers)``: it adds its sub-parser and sets
``handler=<callable(args) -> int>`` with ``set_defaults``. Modules are discovered
automatically; names starting with ``_`` are skipped.
"""
