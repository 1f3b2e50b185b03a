"""Benchmarks, one module each (``add_arguments``, ``main``); its first line is its help."""
