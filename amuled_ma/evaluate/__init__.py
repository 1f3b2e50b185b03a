"""Evaluation of trained policies (metrics with confidence intervals) and the run report.

- :mod:`~amuled_ma.evaluate.stats`: mean with a Student-t confidence interval.
- :mod:`~amuled_ma.evaluate.evaluator`: N episodes per policy, greedy and sampled;
  ``results.json`` and ``results.csv``.
- :mod:`~amuled_ma.evaluate.report`: ``report.md`` with learning curves, bar charts,
  trajectory pictures and the fused-belief diagnostics.
"""
