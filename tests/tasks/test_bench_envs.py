"""Smoke test of ``amuled bench envs`` (tiny sizes; the real figures are in docs/tasks.md)."""

from __future__ import annotations

import json

from amuled_ma.cli import main


def test_bench_envs_runs(tmp_path, capsys):
    out = tmp_path / "envs.json"
    argv = ["bench", "envs", "--copies", "1,8", "--steps", "5", "--gym-steps", "20"]
    assert main([*argv, "--repeats", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "gymnasium, 1 copy" in text and "batched, 8 copies" in text
    figures = json.loads(out.read_text())
    assert set(figures) == {"findmilk", "driving"}
    assert figures["driving"]["batched"][1]["copies"] == 8
