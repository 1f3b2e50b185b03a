"""Evaluation of trained policies (metrics with confidence intervals) and the run report.

- `stats`: mean with a Student-t confidence interval.
- `rollout`: the one rollout of evaluation episodes (task copies,
  seeds, greedy or sampled actions, episode boundaries), shared by the evaluator and the
  episode trace.
- `evaluator`: N episodes per policy, greedy and sampled;
  ``results.json`` and ``results.csv``.
- `report`: ``report.md`` with learning curves, bar charts,
  trajectory pictures and the fused-belief diagnostics.
- Looking inside a run (``amuled view``, ``amuled explain``, ``docs/viewer.md``):
  `episode_trace` (one evaluation episode step by step),
  `readonly_feedback` (a variant's feedback over the run's store,
  read-only), `panel_answers` (the panel's answers with the raw
  replies), `explain` (one state explained),
  `viewer` (the HTML page), `page_server`
  (serving it).
"""
