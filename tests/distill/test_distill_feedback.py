"""Distilled feedback in the learner's feedback: fusion, memo refresh, accounting, wiring."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from job_settings import ablation_jobs, settings
from scenario_feedback import make_feedback
from test_distill_source import ACTIONS, MEMBERS, Panel

from amuled_ma.deliberation import MoralPanel
from amuled_ma.deliberation.panel_feedback import PanelFeedback
from amuled_ma.deliberation.summaries import summary_lines
from amuled_ma.distill import DistilledSource
from amuled_ma.errors import ScenarioError
from amuled_ma.experiments.plans import plan_jobs
from amuled_ma.experiments.run_folder import TrainJob
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

torch.set_num_threads(1)


def feedback(budget=0.25, **kwargs):
    inner = Panel()
    distilled = DistilledSource(
        inner, budget=budget, ensemble=2, hidden=8, seed=3, fit_steps=40, refit_every=2,
        **kwargs,
    )  # fmt: skip
    panel = MoralPanel("findmilk", list(MEMBERS), distilled, "bjs-dst", action_names=ACTIONS)
    return PanelFeedback("amuled", panel, distilled), distilled, inner


def obs(states):
    return torch.tensor([[float(s), 0.0] for s in states])


def test_model_answers_are_fused_as_answers_and_counted_apart():
    fb, distilled, _ = feedback()
    out = fb(obs(range(8)), task=None)
    assert out.shape == (8, 4) and np.allclose(out.sum(1), 1)
    summary = fb.summary()
    assert summary["statuses"]["distilled"] > 0 and summary["failure_rate"] == 0.0
    assert summary["mean_weight"]  # members were weighted: the model's beliefs were fused
    assert summary["distill"]["asked_states"] == distilled.ledger.asked_count == 2
    json.dumps(summary, allow_nan=False)
    lines = summary_lines(summary)
    assert any("feedback budget 25% (uncertainty): asked 2 of 8" in line for line in lines)
    assert any("beliefs from the distilled model" in line for line in lines)


def test_memoised_model_answers_are_refreshed_after_a_refit():
    fb, distilled, _ = feedback(budget=0.5)
    fb(obs(range(4)), task=None)  # 2 asked, 2 answered by the model
    answers = distilled.stats.model_answers
    fb(obs(range(4)), task=None)  # same generation: every state from the memo
    assert distilled.stats.model_answers == answers
    generation = distilled.generation
    fb(obs(range(4, 12)), task=None)  # 4 more asked: the model is refitted
    assert distilled.generation > generation
    before = distilled.stats.model_answers
    fb(obs(range(4)), task=None)  # the model's answers of the first call are asked again
    assert distilled.stats.model_answers == before + 2 * len(MEMBERS)
    per_state = fb.agent_report(per="states")["care"]
    assert per_state["total"] == 12  # each distinct state counted once
    assert fb.summary()["unique_states"] == 12


def test_make_feedback_distills_only_a_fine_tune_with_its_folder(tmp_path):
    scenario = load_scenario("findmilk").replace("feedback", source="rules")
    on = scenario.replace("feedback", **{"distill.enabled": True, "distill.budget": 0.5})
    plain = make_feedback("amuled", on, tmp_path)  # the viewer: no folder, the panel alone
    assert not isinstance(plain.source, DistilledSource)
    plain.close()
    tuned = make_feedback("cluster:care", on, tmp_path, state_dir=tmp_path / "ft", seed=9)
    assert isinstance(tuned.source, DistilledSource) and tuned.source.seed == 9
    assert tuned.source.fusion_rule == "mean"
    tuned.close()
    assert (tmp_path / "ft" / "distill.json").is_file()
    off = make_feedback("amuled", scenario, tmp_path, state_dir=tmp_path / "ft2")
    assert not isinstance(off.source, DistilledSource)
    off.close()


def _fused_only(tmp_path):
    road = [-1.0] * 6 + [0.0, 0.0, 1.0, 0.0, 0.0]
    states = [{"obs": road, "beliefs": None, "moral_agent": None,
               "fused_by_reference": [0.9, 0.05, 0.05], "error": False}]  # fmt: skip
    data = {"task": "Driving", "model": "gpt-4o-mini", "states": states,
            "clusters": ["consequentialist", "deontologist", "virtue", "care", "social justice"],
            "actions": ["straight", "right", "left"]}  # fmt: skip
    path = tmp_path / "driving-fused.json"
    path.write_text(json.dumps(data))
    return str(path)


def test_a_fused_only_recording_is_refused_before_any_work(tmp_path):
    recording = _fused_only(tmp_path)
    scenario = load_scenario("driving").replace(
        "feedback", recording=recording, **{"distill.enabled": True}
    )
    with pytest.raises(ScenarioError, match="cannot learn each panel member") as err:
        run = tmp_path / "run"
        plan_jobs([TrainJob("ft", scenario, run, Variant.finetune("amuled"), run / "ft")])
    assert recording in str(err.value) and 'feedback.recording="driving-llama-3_1-70b"' in str(
        err.value
    )
    with pytest.raises(ScenarioError, match="cannot learn each panel member"):
        make_feedback("amuled", scenario, tmp_path, state_dir=tmp_path / "ft")
    assert not (tmp_path / "ft").exists()


def test_the_budget_ablation_plans_each_budget_and_selection_and_the_full_run():
    scenario = load_scenario("findmilk")
    jobs = ablation_jobs("budget", scenario)
    folders = [variant.folder for variant, _ in jobs]
    assert folders == [
        "finetune-amuled-budget1",
        "finetune-amuled-budget0.3-uncertainty",
        "finetune-amuled-budget0.3-random",
        "finetune-amuled-budget0.1-uncertainty",
        "finetune-amuled-budget0.1-random",
        "finetune-amuled-budget0.03-uncertainty",
        "finetune-amuled-budget0.03-random",
        "finetune-amuled",
    ]
    distills = [sc.feedback.distill for _, sc in jobs]
    assert [d.budget for d in distills[:-1]] == [1.0, 0.3, 0.3, 0.1, 0.1, 0.03, 0.03]
    assert all(d.enabled for d in distills[:-1]) and not distills[-1].enabled
    # the full-feedback run is the run's own AMULED fine-tune (shared when finished there)
    assert settings(jobs[-1][1], Variant.finetune("amuled")) == settings(
        scenario, Variant.finetune("amuled")
    )
    # Driving: the fused-only recording is swapped for the per-cluster one
    driving = ablation_jobs("budget", load_scenario("driving"))
    assert {sc.feedback.recording for _, sc in driving} == {"driving-llama-3_1-70b"}


def test_distill_settings_count_for_a_resume_only_when_on():
    scenario = load_scenario("findmilk")
    variant = Variant.finetune("amuled")
    assert "distill" not in settings(scenario, variant)["feedback"]
    off = scenario.replace("feedback", **{"distill.budget": 0.5})  # off: changes nothing
    assert settings(off, variant) == settings(scenario, variant)
    on = scenario.replace("feedback", **{"distill.enabled": True})
    assert settings(on, variant)["feedback"]["distill"]["budget"] == 0.1
