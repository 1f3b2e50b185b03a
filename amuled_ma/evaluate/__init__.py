"""Evaluation of trained policies (metrics with confidence intervals) and the run report."""
