"""Evaluation of trained policies (metrics with confidence intervals) and the run report.

- :mod:`~amuled_ma.evaluate.stats`: mean with a Student-t confidence interval.
- :mod:`~amuled_ma.evaluate.rollout`: the one rollout of evaluation episodes (task copies,
  seeds, greedy or sampled actions, episode boundaries), shared by the evaluator and the
  episode trace.
- :mod:`~amuled_ma.evaluate.evaluator`: N episodes per policy, greedy and sampled;
  ``results.json`` and ``results.csv``.
- :mod:`~amuled_ma.evaluate.report`: ``report.md`` with learning curves, bar charts,
  trajectory pictures and the fused-belief diagnostics.
- Looking inside a run (``amuled view``, ``amuled explain``, ``docs/viewer.md``):
  :mod:`~amuled_ma.evaluate.episode_trace` (one evaluation episode step by step),
  :mod:`~amuled_ma.evaluate.readonly_feedback` (a variant's feedback over the run's store,
  read-only), :mod:`~amuled_ma.evaluate.panel_answers` (the panel's answers with the raw
  replies), :mod:`~amuled_ma.evaluate.explain` (one state explained),
  :mod:`~amuled_ma.evaluate.viewer` (the HTML page), :mod:`~amuled_ma.evaluate.page_server`
  (serving it).
"""
