"""Experiments: plans of ``amuled run`` / ``ablate``, run folders and their records, jobs, Ray."""
