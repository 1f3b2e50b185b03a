"""Throughput of the bjs-dst fusion: vectorized numpy vs the per-state pure-Python reference.

``--n`` Dirichlet(1) belief matrices in one `fuse` call against ``--sample`` of them through
`fusion.reference`, checked equal; best of ``--repeats``, wall and CPU time. Targets:
100,000 matrices of 5 x 4 in under 0.5 s, and at least 100x the reference.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from amuled_ma.bench._output import best_time
from amuled_ma.fusion import fuse
from amuled_ma.fusion.reference import fuse_beliefs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument("--n", type=int, default=100_000, help="matrices to fuse (vectorized)")
    parser.add_argument("--clusters", type=int, default=5, help="clusters per matrix")
    parser.add_argument("--actions", type=int, default=4, help="actions per belief")
    parser.add_argument(
        "--sample", type=int, default=2_000, help="matrices fused by the pure-Python reference"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=10,
        help="timing repeats of the vectorized run (best is kept)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed of the beliefs")


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures; returns 0 (a benchmark, not a test)."""
    rng = np.random.default_rng(args.seed)
    beliefs = rng.dirichlet(np.ones(args.actions), size=(args.n, args.clusters))
    sample = beliefs[: min(args.sample, args.n)]
    sample_lists = sample.tolist()

    fuse(beliefs[:100])  # warm-up
    fused, vec_wall, vec_cpu = best_time(lambda: fuse(beliefs, "bjs-dst"), args.repeats)
    ref, ref_wall, ref_cpu = best_time(lambda: [fuse_beliefs(b) for b in sample_lists], 3)
    diff = float(np.max(np.abs(np.asarray(ref) - fused[: len(sample_lists)])))

    n_ref = len(sample_lists)
    print(
        f"fusion benchmark: rule bjs-dst, {args.clusters} clusters x {args.actions} actions, "
        f"float64, numpy {np.__version__}, Python {platform.python_version()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs visible"
    )
    print(
        f"  vectorized fuse():      {args.n:>9,} matrices in {vec_wall:7.4f} s wall "
        f"({vec_cpu:7.4f} s CPU) = {args.n / vec_wall:>12,.0f} matrices/s"
    )
    print(
        f"  pure-Python reference:  {n_ref:>9,} matrices in {ref_wall:7.4f} s wall "
        f"({ref_cpu:7.4f} s CPU) = {n_ref / ref_wall:>12,.0f} matrices/s"
    )
    ratio = (args.n / vec_wall) / (n_ref / ref_wall)
    ratio_cpu = (args.n / vec_cpu) / (n_ref / ref_cpu) if vec_cpu > 0 and ref_cpu > 0 else ratio
    print(
        f"  speed-up: {ratio:,.0f}x wall ({ratio_cpu:,.0f}x CPU time); best of "
        f"{args.repeats} and 3 runs; max |difference| on the sample: {diff:.1e}"
    )
    if args.n == 100_000 and args.clusters == 5 and args.actions == 4:
        time_ok = "met" if vec_wall < 0.5 else "NOT met"
        ratio_ok = "met" if ratio >= 100 else "NOT met"
        print(f"  targets: 100,000 in < 0.5 s: {time_ok}; >= 100x the reference: {ratio_ok}")
    return 0
