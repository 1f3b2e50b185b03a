"""[feedback.agents]: scenario tables, entry-point agents, and the feedback they build."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from job_settings import settings
from scenario_feedback import make_feedback
from scenario_feedback import make_source as feedback_source

from amuled_ma.beliefs import BeliefRequest, make_source
from amuled_ma.beliefs.sources.routing import RoutedSource
from amuled_ma.clusters import plugins
from amuled_ma.errors import ScenarioError
from amuled_ma.fusion.reference import fuse_beliefs
from amuled_ma.scenario import OllamaSpec, TerminalSpec, load_scenario, scenario_from_dict

MILK = ("up", "down", "left", "right")
HERE = Path(__file__).resolve().parent
RECORDING = "findmilk-gpt-4o-mini.json"
#: Our cluster names -> the recording's agent names (the recording's own spelling).
RECORDED = {
    "consequentialist": "consequentialist",
    "deontological": "deontologist",
    "virtue": "virtue",
    "care": "care",
    "social_justice": "social justice",
}


def allow(monkeypatch: pytest.MonkeyPatch, *paths: str) -> None:
    """Allow import paths as ``--allow-plugin`` would, for this test only."""
    monkeypatch.setattr(plugins, "_ALLOWED", frozenset(paths))


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------- scenario tables
@pytest.mark.parametrize(
    ("tables", "message"),
    [
        (
            '[feedback.agents.care]\nsource = "rules"\nmodel = "x"\n',
            "[feedback.agents.care] unknown key 'model' for source = 'rules'; expected some "
            "of source, policy; fix or remove the key",
        ),
        (
            '[feedback.agents.care]\nsource = "psychic"\n',
            "[feedback.agents.care] key source expects one of replay, ollama, rules, "
            "terminal, entry-point, policy, found string ('psychic'); fix source",
        ),
        (
            '[feedback.agents.care]\nsource = "ollama"\n',
            "[feedback.agents.care] (source = 'ollama') has no model and [feedback].source "
            "is not 'ollama' (so [feedback].model is not an Ollama model); add "
            'model = "llama3.1:8b"',
        ),
        (
            '[feedback.agents.virtue]\nsource = "policy"\n',
            "[feedback.agents.virtue] (source = 'policy') has no path; add path = "
            '"policies/virtue.pt"',
        ),
        (
            '[feedback.agents.virtue]\nsource = "entry-point"\n',
            "[feedback.agents.virtue] (source = 'entry-point') has no name; add name = ",
        ),
        (
            '[feedback.agents.virtue]\nmodel = "x"\n',
            "[feedback.agents.virtue] has no key source; add source = one of replay, ollama",
        ),
        (
            '[feedback.agents.kindness]\nsource = "rules"\n',
            "[feedback.agents.kindness] names no agent of the panel: expected one of "
            "consequentialist, deontological, virtue, care, social_justice or moral_agent",
        ),
        (
            '[feedback.agents.care]\nsource = "rules"\n[feedback.agents.CARE]\nsource = "rules"\n',
            "[feedback.agents.CARE] and [feedback.agents.care] name the same agent 'care'",
        ),
        (
            '[feedback.agents.care]\nsource = "terminal"\nattempts = "3"\n',
            "[feedback.agents.care] key attempts expects integer (answer lines read per "
            "state), found string ('3'); fix the value",
        ),
        (
            '[feedback.agents.care]\nsource = "ollama"\nmodel = "m"\nnum_predit = 64\n',
            "[feedback.agents.care] unknown key 'num_predit' for source = 'ollama'",
        ),
        (
            '[feedback.agents.care]\nsource = "ollama"\nmodel = "m"\nconcurrency = 0\n',
            "[feedback.agents.care] key concurrency expects a number in [1, 1024]",
        ),
        (
            '[feedback.agents.care]\nsource = "entry-point"\nname = "a:B"\n'
            "options = { since = 1979-05-27 }\n",
            "[feedback.agents.care] key options.since expects a string, number, boolean, "
            "array or table, found datetime.date(1979, 5, 27)",
        ),
        (
            "[feedback.agents]\ncare = 3\n",
            '[feedback.agents.care] expects a table such as { source = "rules" }, found '
            "integer (3)",
        ),
    ],
)
def test_bad_agent_tables_name_the_file_the_table_and_the_fix(tmp_path, tables, message):
    path = write(tmp_path, tables)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value).startswith(f"{path}: ")
    assert message in str(info.value)


def test_a_nan_inside_an_agent_table_is_refused(tmp_path):
    path = write(
        tmp_path, '[feedback.agents.care]\nsource = "ollama"\nmodel = "m"\ntemperature = nan\n'
    )
    with pytest.raises(
        ScenarioError, match=r"\[feedback\]\.agents\.care\.temperature expects a finite"
    ):
        load_scenario(path)


def test_agent_tables_load_as_plain_data(tmp_path):
    path = write(
        tmp_path,
        """
        [feedback]
        source = "ollama"
        model = "amuled-tiny"
        [feedback.agents.care]
        source = "ollama"            # model: [feedback].model, as [feedback].source is ollama
        num_predict = 256
        [feedback.agents.social-justice]
        source = "terminal"
        person = "ann"
        [feedback.agents.virtue]
        source = "policy"
        path = "policies/virtue.pt"
        [feedback.agents.moral_agent]
        source = "entry-point"
        name = "my_pkg:Agent"
        options = { index = 2 }
        """.replace("\n        ", "\n"),
    )
    scenario = load_scenario(path)
    agents = scenario.feedback.agents
    # each table is a typed spec; only the keys it set are passed on
    assert agents["care"] == OllamaSpec(source="ollama", num_predict=256)
    assert agents["care"].given() == {"num_predict": 256}
    assert agents["social-justice"] == TerminalSpec(source="terminal", person="ann")
    assert agents["virtue"].path == "policies/virtue.pt"
    data = json.loads(json.dumps(scenario.to_dict()))
    assert data["feedback"]["agents"]["moral_agent"]["options"] == {"index": 2}
    # what a fine-tune learns from includes each agent's source
    config = settings(scenario, "finetune:amuled")
    assert config["feedback"]["agents"]["virtue"] == {
        "source": "policy",
        "path": "policies/virtue.pt",
    }
    assert "feedback" not in settings(scenario, "base")


# ---------------------------------------------------------------------- entry-point agents
def req(cluster="care") -> BeliefRequest:
    return BeliefRequest("findmilk", cluster, (1.0, 2.0), MILK)


def test_an_entry_point_agent_by_module_and_class(monkeypatch):
    monkeypatch.syspath_prepend(str(HERE))
    allow(
        monkeypatch,
        "amuled_agent_helper:FixedAgent",
        "amuled_agent_helper:not_a_source",
        "no_such_module_xyz:Agent",
    )
    source = make_source("entry-point", name="amuled_agent_helper:FixedAgent", options={"index": 2})
    (result,) = source.beliefs([req()])
    assert result.status == "ok" and result.belief.tolist() == [0.0, 0.0, 1.0, 0.0]
    with pytest.raises(ScenarioError, match=r"built object, expected an amuled_ma\.beliefs"):
        make_source("entry-point", name="amuled_agent_helper:not_a_source")
    with pytest.raises(ScenarioError, match=r"with options \['colour'\] failed"):
        make_source("entry-point", name="amuled_agent_helper:FixedAgent", options={"colour": 1})
    with pytest.raises(ScenarioError, match=r"cannot import 'no_such_module_xyz:Agent'.*fix"):
        make_source("entry-point", name="no_such_module_xyz:Agent")


def test_an_entry_point_agent_by_installed_name(monkeypatch):
    monkeypatch.syspath_prepend(str(HERE))
    from amuled_agent_helper import install_fixed_entry_point

    install_fixed_entry_point(monkeypatch)
    source = make_source("entry-point", name="fixed", options={"index": 1})
    assert source.beliefs([req()])[0].belief.tolist() == [0.0, 1.0, 0.0, 0.0]
    with pytest.raises(ScenarioError, match=r"'ghost': no installed package .*installed: fixed"):
        make_source("entry-point", name="ghost")


# -------------------------------------------------------------------- feedback, end to end
def recorded_states(recordings_dir: Path, count: int) -> list[dict]:
    data = json.loads((recordings_dir / RECORDING).read_text())
    states = [
        s
        for s in data["states"]
        if s["beliefs"] and all(s["beliefs"].get(a) for a in RECORDED.values())
    ]
    return states[:count]


def test_amuled_feedback_fuses_four_replayed_agents_and_one_rule(tmp_path, recordings_dir):
    from amuled_ma.tasks.human import human_belief

    scenario = scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "feedback": {
                "source": "replay",
                "recording": str(recordings_dir / RECORDING),
                "store": str(tmp_path / "run" / "beliefs.sqlite"),
                "agents": {"care": {"source": "rules"}, "virtue": {"source": "replay"}},
            },
        }
    )
    feedback = make_feedback("amuled", scenario, tmp_path / "run")
    routed = feedback.source
    assert isinstance(routed, RoutedSource)
    # virtue's table asks for what [feedback].source gives: one shared replay source
    assert len(routed.members) == 2
    assert routed.source_for("virtue") is routed.source_for("consequentialist")
    assert routed.source_for("care") is not routed.source_for("virtue")

    states = recorded_states(recordings_dir, 4)
    obs = np.array([s["obs"] for s in states], dtype=np.float32)
    fused = feedback(torch.from_numpy(obs), None)

    clusters = list(scenario.feedback.clusters)
    for row, state in zip(fused, states, strict=True):
        care = human_belief("findmilk", np.asarray(state["obs"], dtype=np.float64))
        answers = [care if c == "care" else state["beliefs"][RECORDED[c]] for c in clusters]
        assert np.allclose(row, fuse_beliefs(answers), atol=1e-9)

    agents = feedback.summary()["agents"]
    assert all(agents[c]["ok"] == len(states) for c in clusters)
    assert feedback.agent_source("care") == (
        "rules (the task's rule 'human'; the cluster's text is not read)"
    )
    assert feedback.agent_source("virtue") == f"replay ({RECORDING})"
    rows = list(routed.source_for("care").store.iter_rows())
    assert {r.cluster: r.identity["source"] for r in rows} == {
        "consequentialist": "replay",
        "deontological": "replay",
        "virtue": "replay",
        "care": "rules",
        "social_justice": "replay",
    }
    feedback.close()


def test_preflight_names_every_agent_source_and_fix_before_anything_is_written(tmp_path):
    scenario = scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "feedback": {
                "source": "rules",
                "agents": {
                    "care": {
                        "source": "ollama",
                        "model": "llama3.1:8b",
                        "host": "http://127.0.0.1:9",
                        "check_timeout_s": 2.0,
                    },
                    "virtue": {"source": "policy", "path": str(tmp_path / "virtue.pt")},
                    "deontological": {"source": "entry-point", "name": "no_such_mod_xyz:A"},
                    "social_justice": {"source": "replay", "recording": "no-such-recording"},
                },
            },
        }
    )
    run_dir = tmp_path / "run"
    with pytest.raises(ScenarioError) as info:
        make_feedback("amuled", scenario, run_dir)
    text = str(info.value)
    assert "4 belief sources of the panel cannot be used; fix each before training" in text
    lines = {line.split(":", 1)[0].strip(" -") for line in text.splitlines()[1:]}
    assert lines == {
        "[feedback.agents.care] (source 'ollama', model 'llama3.1",
        f"[feedback.agents.virtue] (source 'policy', path '{tmp_path / 'virtue.pt'}')",
        "[feedback.agents.deontological] (source 'entry-point', name 'no_such_mod_xyz",
        "[feedback.agents.social_justice] (source 'replay')",
    }
    assert "http://127.0.0.1:9" in text and "ollama serve" in text
    assert "not found; fix the path" in text
    assert "'no_such_mod_xyz:A' is an import path" in text
    assert "--allow-plugin no_such_mod_xyz:A" in text
    assert "[feedback.agents.social_justice] recording 'no-such-recording' not found" in text
    assert not run_dir.exists()


def test_members_of_every_kind_answer_through_one_store(tmp_path, monkeypatch):
    import io

    monkeypatch.syspath_prepend(str(HERE))
    allow(monkeypatch, "amuled_agent_helper:FixedAgent")
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(8, 4))
    torch.save(net.state_dict(), tmp_path / "virtue.pt")
    monkeypatch.setattr("sys.stdin", io.StringIO("3\n"))
    scenario = scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "feedback": {
                "source": "rules",
                "store": str(tmp_path / "beliefs.sqlite"),
                "agents": {
                    "virtue": {"source": "policy", "path": str(tmp_path / "virtue.pt")},
                    "deontological": {
                        "source": "entry-point",
                        "name": "amuled_agent_helper:FixedAgent",
                        "options": {"index": 1},
                    },
                    "care": {"source": "terminal", "person": "ann"},
                    "social_justice": {"source": "rules"},
                },
            },
        }
    )
    source = feedback_source(scenario, tmp_path, agents=list(scenario.feedback.clusters))
    assert source.needs_messages is True  # the person is shown the state prompt
    obs = (0.0, 0.0, 3.0, 3.0, 1.0, 0.0, 0.0, 1.0)
    chat = (("system", "s"), ("user", "state"))
    batch = [BeliefRequest("findmilk", c, obs, MILK, chat) for c in scenario.feedback.clusters]
    results = source.beliefs(batch)
    assert [r.source for r in results] == ["rules", "fixed-agent", "policy", "terminal", "rules"]
    assert results[1].belief.tolist() == [0.0, 1.0, 0.0, 0.0]
    assert results[3].belief.tolist() == [0.0, 0.0, 0.0, 1.0]
    with torch.no_grad():
        logits = net(torch.tensor([obs])).double()
    assert np.allclose(results[2].belief, torch.softmax(logits, -1).numpy()[0], atol=1e-6)
    # social_justice's rules table equals [feedback].source: one shared member
    assert source.source_for("social_justice") is source.source_for("consequentialist")
    # a plug-in's store rows name the entry point, not only its own identity
    ident = source.source_for("deontological").identity()
    assert ident["name"] == "amuled_agent_helper:FixedAgent" and ident["options"] == {"index": 1}
    source.close()


def test_a_fused_only_recording_cannot_serve_replay_members(tmp_path, recordings_dir):
    scenario = scenario_from_dict(
        {
            "task": {"name": "driving"},
            "feedback": {
                "source": "replay",
                "recording": str(recordings_dir / "driving-gpt-4o-mini.json"),
                "agents": {"care": {"source": "rules"}},
            },
        }
    )
    with pytest.raises(ScenarioError) as info:
        make_feedback("amuled", scenario, tmp_path / "run")
    text = str(info.value)
    assert "[feedback].source = 'replay'" in text and "agents consequentialist" in text
    assert "keeps only the authors' fused belief per state" in text
    assert not (tmp_path / "run").exists()


def test_preflight_alone_checks_a_panel_without_a_store(tmp_path, monkeypatch):
    from amuled_ma.deliberation.build import preflight
    from amuled_ma.deliberation.plan import plan_panel

    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(HERE))
    allow(monkeypatch, "amuled_agent_helper:FixedAgent")
    good = {"care": {"source": "entry-point", "name": "amuled_agent_helper:FixedAgent"}}
    scenario = scenario_from_dict(
        {"task": {"name": "findmilk"}, "feedback": {"source": "rules", "agents": good}}
    )
    preflight(plan_panel("amuled", scenario))
    assert list(tmp_path.iterdir()) == []  # no store, no folder

    bad = scenario.replace("feedback", agents={"care": {"source": "policy", "path": "v.pt"}})
    with pytest.raises(ScenarioError, match=r"\[feedback.agents.care\] \(source 'policy'"):
        preflight(plan_panel("cluster:care", bad))
