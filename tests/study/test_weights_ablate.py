"""``amuled ablate TASK --what weights --weights FILE`` on both tasks, tiny budgets.

AMULED with the paper's fixed weights and with learned ones, the same seed, replaying the
authors' recordings with per-cluster beliefs (FindMilk: gpt-4o-mini; Driving: its
``cluster_recording``, Llama 3.1 70B, since the paper's Driving recording keeps only fused
beliefs); evaluated and reported side by side.
"""

from __future__ import annotations

import hashlib
import json

import pytest
from tiny_cli import TINY

from amuled_ma.cli import main
from amuled_ma.scenario import PAPER_CLUSTERS

#: A prior a person might have written: the consequentialist trusted most.
WEIGHTS = dict(zip(PAPER_CLUSTERS, [0.5, 0.2, 0.1, 0.1, 0.1], strict=True))


@pytest.mark.parametrize("task", ["findmilk", "driving"])
def test_ablate_weights_trains_both_variants_and_reports_them(
    task, tmp_path, capsys, recordings_dir
):
    path = tmp_path / "weights.json"
    path.write_text(json.dumps({"members": list(WEIGHTS), "weights": list(WEIGHTS.values())}))
    run_dir = tmp_path / "run"
    argv = ["ablate", task, "--what", "weights", "--weights", str(path), "--run-dir", str(run_dir)]
    assert main([*argv, "--episodes", "2", "--jobs", "1", *TINY]) == 0
    out = capsys.readouterr().out
    assert f"ablate {task} --what weights: 2 variants x 1 seed(s) done" in out
    folder = run_dir / "ablate-weights"
    results = json.loads((folder / "results.json").read_text())["variants"]
    assert {"base", "finetune-amuled", "finetune-amuled-learned-weights"} <= set(results)
    report = (folder / "report.md").read_text()
    assert "finetune-amuled-learned-weights" in report
    assert "members weighted by `weights.json`" in report
    assert (folder / "ablation_weights.png").is_file()

    learned = json.loads((folder / "finetune-amuled-learned-weights" / "config.json").read_text())
    fixed = json.loads((folder / "finetune-amuled" / "config.json").read_text())
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert learned["training"]["inputs"]["weights_sha256"] == digest
    assert learned["panel"]["weights"] == "weights.json"
    assert (
        "weights_sha256" not in fixed["training"]["inputs"]
        and fixed["panel"].get("weights") is None
    )
    assert learned["seed"] == fixed["seed"]  # the same seed, side by side
    recording = learned["panel"]["recording"]
    assert recording == fixed["panel"]["recording"]
    # recorded by name as the scenario gives it: the per-cluster recording in both
    assert recording.removesuffix(".json") == (
        "findmilk-gpt-4o-mini" if task == "findmilk" else "driving-llama-3_1-70b"
    )
