"""The doc-page examples run (doctest) and the benchmark command works on a small run."""

from __future__ import annotations

import argparse
import doctest
import importlib

import pytest

import amuled_ma.bench.fusion as bench

MODULES = [
    "amuled_ma.fusion",
    "amuled_ma.fusion.rules",
    "amuled_ma.fusion.xiao",
    "amuled_ma.fusion.reference",
]


@pytest.mark.parametrize("name", MODULES)
def test_doctests(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0


def test_fuse_and_xiao_fusion_have_worked_examples():
    from amuled_ma.fusion import fuse, xiao_fusion

    for func in (fuse, xiao_fusion):
        assert ">>> " in func.__doc__ and "Example" in func.__doc__


def test_benchmark_runs_and_prints_figures(capsys):
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--n", "2000", "--sample", "20", "--repeats", "1"])
    assert bench.main(args) == 0
    out = capsys.readouterr().out
    assert "matrices/s" in out and "speed-up" in out
    assert "max |difference| on the sample" in out


def test_benchmark_is_discovered_by_the_cli(capsys):
    from amuled_ma.cli import main

    assert main(["bench", "fusion", "--n", "500", "--sample", "5", "--repeats", "1"]) == 0
    assert "speed-up" in capsys.readouterr().out
