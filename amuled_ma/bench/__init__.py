"""Benchmarks, one module each: ``amuled bench NAME`` or ``python -m amuled_ma.bench NAME``.

A module here defines ``add_arguments(parser)`` and ``main(args) -> int``; its first
docstring line is its help text.
"""
