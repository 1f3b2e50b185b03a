"""The files of examples/ (the walkthrough of docs/clusters.md) load and mean what it says."""

from pathlib import Path

from amuled_ma.clusters import ClusterRegistry
from amuled_ma.deliberation.plan import cluster_registry, panel_of
from amuled_ma.scenario import TerminalSpec, load_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_example_cluster_joins_the_registry_without_overriding():
    registry = ClusterRegistry.load([EXAMPLES / "my_clusters"])
    assert "animal_welfare" in registry and registry.overridden == []
    assert registry.get("welfare").title == "Animal Welfare Ethics"
    assert [c.name for c in registry.panel()][-1] == "animal_welfare"


def test_mixed_panel_scenario_gives_each_agent_its_source():
    scenario = load_scenario(EXAMPLES / "mixed_panel.toml")
    registry = cluster_registry(scenario.feedback, scenario.resolve)
    agents, rule = panel_of("amuled", scenario.feedback, registry)
    assert [a.name for a in agents][-1] == "animal_welfare" and rule == "bjs-dst"
    assert scenario.feedback.agents["animal_welfare"] == TerminalSpec(source="terminal")
    assert scenario.feedback.agents["social_justice"].source == "ollama"
    assert scenario.feedback.source == "replay"
