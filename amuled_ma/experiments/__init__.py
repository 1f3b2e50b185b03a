"""Experiments: plans of ``amuled run`` / ``ablate``, run folders and their records, jobs, Ray.

This package sits above learning and evaluation (:mod:`amuled_ma.learn`,
:mod:`amuled_ma.evaluate`): it decides what is trained where, and keeps the run folders.
"""
