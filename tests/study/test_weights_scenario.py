"""``[feedback] weights = "..."``: checked on load and when planned, carried to the fusion.

A weights file names the panel's members; a scenario that names one gets a prior on the
``bjs-dst`` fusion of its ``amuled`` variant. A missing or extra member, a missing or broken
file, another fusion rule or a recording of fused beliefs only is one line naming the file
and the fix; the file's SHA-256 is an input of the run, so editing it and resuming is
refused.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from job_settings import ablation_jobs, settings, train_variant
from tiny_cli import TINY

from amuled_ma.cli import main
from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.errors import AmuledError, ScenarioError
from amuled_ma.files.resources import scenarios_dir
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import PAPER_CLUSTERS, load_scenario

#: Written in another order than [feedback].clusters, on another scale than 1.
WEIGHTS = {"care": 2.0, "virtue": 1.0, "consequentialist": 4.0, "deontological": 2.0,
           "social_justice": 1.0}  # fmt: skip


def weights_file(path: Path, weights: dict[str, float] = WEIGHTS) -> Path:
    data = {"members": list(weights), "weights": list(weights.values())}
    path.write_text(json.dumps(data))
    return path


def scenario_file(folder: Path, weights: str, fusion: str = "bjs-dst") -> Path:
    """The shipped FindMilk scenario with ``[feedback] weights`` set, its panel the rules."""
    text = (scenarios_dir() / "findmilk.toml").read_text()
    text = text.replace('source = "replay"', 'source = "rules"', 1)
    text = text.replace('fusion = "bjs-dst"', f'fusion = "{fusion}"\nweights = "{weights}"')
    path = folder / "findmilk.toml"
    path.write_text(text)
    return path


def test_the_prior_reaches_the_panel_in_the_panel_s_order(tmp_path):
    weights_file(tmp_path / "w.json")
    scenario = load_scenario(scenario_file(tmp_path, "w.json"))  # relative to the scenario
    plan = plan_panel("amuled", scenario)
    total = sum(WEIGHTS.values())
    assert plan.prior == pytest.approx([WEIGHTS[c] / total for c in PAPER_CLUSTERS], abs=1e-15)
    # the baselines keep their own rules: no prior
    for variant in ("cluster:care", "agg:mean", "moral", "human"):
        assert plan_panel(variant, scenario).prior is None


def test_the_feedback_s_panel_gets_the_prior(tmp_path):
    """The feedback built from the plan hands the prior to its panel (which fuses with it,
    tests/fusion/test_prior.py)."""
    from scenario_feedback import make_feedback

    weights_file(tmp_path / "w.json")
    scenario = load_scenario(scenario_file(tmp_path, "w.json"))
    feedback = make_feedback("amuled", scenario, tmp_path)
    try:
        rho = np.array([WEIGHTS[c] for c in PAPER_CLUSTERS])
        np.testing.assert_allclose(feedback.panel.prior, rho / rho.sum(), atol=1e-15)
        assert feedback.panel.fusion_rule == "bjs-dst"
    finally:
        feedback.close()
    plain = make_feedback("amuled", scenario.replace("feedback", weights=""), tmp_path)
    try:
        assert plain.panel.prior is None
    finally:
        plain.close()


@pytest.mark.parametrize(
    ("weights", "found"),
    [
        (
            {k: v for k, v in WEIGHTS.items() if k != "virtue"},
            "no weight for the panel member 'virtue'",
        ),
        ({**WEIGHTS, "loyalty": 1.0}, "weighs 'loyalty', which is not a member of the panel"),
    ],
)
def test_a_member_missing_or_extra_is_one_line_on_load(tmp_path, weights, found):
    path = weights_file(tmp_path / "w.json", weights)
    scenario = scenario_file(tmp_path, "w.json")
    with pytest.raises(ScenarioError) as info:
        load_scenario(scenario)
    text = str(info.value)
    assert found in text and str(path) in text and str(scenario) in text
    assert "amuled study fit-weights" in text and "\n" not in text


@pytest.mark.parametrize(
    ("content", "found"),
    [
        (None, "not found"),
        ("{not json", "is not JSON"),
        ('{"members": ["care"], "weights": [-1.0]}', "key weights: every weight must be"),
        ('{"members": ["care", "virtue"], "weights": [1.0]}', "weights has 1 values for 2 members"),
        ('{"members": ["care"], "weights": [1.0], "colour": 3}', "key colour"),
    ],
)
def test_a_broken_weights_file_is_one_line(tmp_path, content, found):
    path = tmp_path / "w.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ScenarioError) as info:
        load_scenario(scenario_file(tmp_path, "w.json"))
    text = str(info.value)
    assert found in text and str(path) in text and "\n" not in text


def test_another_rule_or_a_fused_only_recording_is_refused(tmp_path):
    weights_file(tmp_path / "w.json")
    with pytest.raises(ScenarioError) as info:
        load_scenario(scenario_file(tmp_path, "w.json", fusion="mean"))
    text = str(info.value)
    assert "[feedback].weights" in text and "'mean'" in text and "\n" not in text
    assert "the rules bjs-dst, mec, nash-vote, variance-vote, borda take" in text
    # Driving's paper recording keeps only the fused belief: nothing to weigh
    driving = load_scenario("driving").replace("feedback", weights=str(tmp_path / "w.json"))
    try:
        driving.recording_path(required=True)
    except ScenarioError:
        pytest.skip("the Driving recordings are not beside the checkout")
    with pytest.raises(ScenarioError) as info:
        plan_panel("amuled", driving)
    assert "keeps only the authors' fused belief" in str(info.value)
    # the ablation replays the per-cluster recording instead
    ((fixed, fixed_sc), (learned, learned_sc)) = ablation_jobs("weights", driving)
    assert plan_panel("amuled", learned_sc).prior is not None
    assert fixed_sc.feedback.weights == "" and learned.folder == "finetune-amuled-learned-weights"
    assert fixed.folder == "finetune-amuled"


def test_ablate_weights_without_a_file_is_one_line(tmp_path, capsys):
    argv = ["ablate", "findmilk", "--what", "weights", "--run-dir", str(tmp_path / "run")]
    assert main([*argv, *TINY]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--weights FILE" in err and "fit-weights" in err
    assert not (tmp_path / "run").exists()
    # a file that weighs other members: one line too, before any folder
    path = weights_file(tmp_path / "w.json", {"care": 1.0})
    assert main([*argv, "--weights", str(path), *TINY]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no weight for the panel member" in err
    assert not (tmp_path / "run").exists()


def test_editing_the_weights_file_and_resuming_is_refused(tmp_path):
    path = weights_file(tmp_path / "w.json")
    scenario = load_scenario("findmilk")
    for section, values in {
        "base": {"total_steps": 1024, "num_envs": 16, "num_steps_per_env": 16},
        "finetune": {"iterations": 2, "num_envs": 4, "num_steps_per_env": 8},
        "output": {"tensorboard": False},
        "feedback": {"source": "rules", "weights": str(path)},
    }.items():
        scenario = scenario.replace(section, **values)
    old = hashlib.sha256(path.read_bytes()).hexdigest()
    config = settings(scenario, "finetune:amuled")
    assert config["inputs"]["weights_sha256"] == old and config["feedback"]["weights"] == "w.json"
    for other in ("finetune:cluster:care", "finetune:agg:mean", "base"):
        assert "weights_sha256" not in settings(scenario, other).get("inputs", {})
    plain = scenario.replace("feedback", weights="")
    assert "weights" not in settings(plain, "finetune:amuled")["feedback"]

    run_dir = tmp_path / "run"
    train_variant(scenario, run_dir, Variant("base"))
    train_variant(scenario, run_dir, Variant.finetune("amuled"))
    record = json.loads((run_dir / "finetune-amuled" / "config.json").read_text())
    assert record["panel"]["weights"] == "w.json"
    assert record["training"]["inputs"]["weights_sha256"] == old

    weights_file(path, {**WEIGHTS, "care": 3.0})
    new = hashlib.sha256(path.read_bytes()).hexdigest()
    longer = scenario.replace("finetune", iterations=3)
    with pytest.raises(AmuledError) as err:
        train_variant(longer, run_dir, Variant.finetune("amuled"), resume=True)
    text = str(err.value)
    assert f"inputs.weights_sha256: {old!r} -> {new!r}" in text and "--force" in text
