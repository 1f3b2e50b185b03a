"""Code runs only from code the user installed and named on the command line .

Each route by which a data file once imported and called a ``module:Class`` string (an
entry-point agent set with ``--set``, a cluster file's ``[source]`` read through
``--clusters-dir``, a ``policy`` source's ``module``, a ``rules`` source's ``policy``, a
run folder's ``config.json`` read by ``amuled view`` and ``amuled explain --state-from``)
now creates nothing, imports nothing and stops with one line naming ``--allow-plugin``;
the same plug-in named by ``--allow-plugin`` works.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from amuled_ma.beliefs import BeliefRequest, make_source
from amuled_ma.beliefs.sources.policy import PolicySource
from amuled_ma.cli import main
from amuled_ma.clusters import default_clusters_dir, plugins
from amuled_ma.commands._experiment import rerun_of
from amuled_ma.errors import ScenarioError

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
from tiny_cli import TINY  # noqa: E402

#: A module whose import leaves a mark: proof that a refused name was never imported.
MARKER = """
import os, pathlib
pathlib.Path(os.environ["AMULED_TEST_MARK"]).write_text("imported")

def rule(task, obs):
    return [1, 0, 0, 0]
"""


@pytest.fixture(autouse=True)
def _own_allow_list(monkeypatch):
    """Every test starts with nothing allowed, and leaves the list as it found it."""
    monkeypatch.setattr(plugins, "_ALLOWED", frozenset(), raising=False)


@pytest.fixture()
def marker(tmp_path, monkeypatch):
    """``(module name, mark file)``: a module that writes the mark file when imported."""
    folder = tmp_path / "mods"
    folder.mkdir()
    name = f"amuled_mark_{tmp_path.name.replace('-', '_')}"
    (folder / f"{name}.py").write_text(MARKER)
    mark = tmp_path / "IMPORTED"
    monkeypatch.setenv("AMULED_TEST_MARK", str(mark))
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.delitem(sys.modules, name, raising=False)
    return name, mark


def popen_touch(path: Path) -> str:
    """The attack of the issue: an entry-point agent that runs ``touch PATH``."""
    return f'{{source="entry-point", name="subprocess:Popen", options={{args=["touch","{path}"]}}}}'


def one_line(err: str, flag: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("amuled: error: ") and flag in lines[0], err
    assert "nothing was imported" in lines[0]
    return lines[0]


RULES = ["--set", 'feedback.source="rules"']


# ------------------------------------------------------------------ scenario and --set
def test_an_entry_point_agent_set_on_the_command_line_runs_nothing(tmp_path, capsys):
    touched = tmp_path / "X"
    argv = ["run", "findmilk", "--run-dir", str(tmp_path / "run"), "--jobs", "1", *TINY, *RULES]
    assert main([*argv, "--set", f"feedback.agents.care={popen_touch(touched)}"]) == 1
    one_line(capsys.readouterr().err, "--allow-plugin subprocess:Popen")
    assert not touched.exists()
    assert not (tmp_path / "run").exists()  # stopped before any run folder


def test_a_cluster_files_source_table_runs_nothing(tmp_path, capsys):
    touched = tmp_path / "X"
    folder = tmp_path / "clusters"
    folder.mkdir()
    care = (default_clusters_dir() / "care.toml").read_text()
    source = 'source = "entry-point"\nname = "subprocess:Popen"\n'
    source += f'options = {{ args = ["touch", "{touched}"] }}\n'
    (folder / "care.toml").write_text(f"{care}\n[source]\n{source}")
    argv = ["finetune", "findmilk", "--run-dir", str(tmp_path / "run"), *TINY, *RULES]
    assert main([*argv, "--clusters-dir", str(folder)]) == 1
    line = one_line(capsys.readouterr().err, "--allow-plugin subprocess:Popen")
    # the file that holds the import path is named, not the scenario that uses the cluster
    assert line.startswith(f"amuled: error: {folder / 'care.toml'}: [source] "), line
    assert "findmilk.toml" not in line, line
    assert not touched.exists()
    assert not (tmp_path / "run").exists()  # refused before any run or variant folder


def test_a_policy_sources_module_runs_nothing(tmp_path, capsys, marker):
    name, mark = marker
    weights = tmp_path / "virtue.pt"
    torch.save(torch.nn.Sequential(torch.nn.Linear(8, 4)).state_dict(), weights)
    touched = tmp_path / "X"
    for module, kwargs in (("subprocess:Popen", f'{{args=["touch","{touched}"]}}'),
                           (f"{name}:rule", "{}")):  # fmt: skip
        table = f'{{source="policy", path="{weights}", module="{module}", kwargs={kwargs}}}'
        argv = ["finetune", "findmilk", "--run-dir", str(tmp_path / "run"), *TINY, *RULES]
        assert main([*argv, "--set", f"feedback.agents.virtue={table}"]) == 1
        one_line(capsys.readouterr().err, f"--allow-plugin {module}")
    assert not touched.exists() and not mark.exists()


def test_a_rules_policy_imports_nothing(tmp_path, capsys, marker):
    name, mark = marker
    table = f'{{source="rules", policy="{name}:rule"}}'
    argv = ["finetune", "findmilk", "--run-dir", str(tmp_path / "run"), *TINY, *RULES]
    assert main([*argv, "--set", f"feedback.agents.care={table}"]) == 1
    one_line(capsys.readouterr().err, f"--allow-plugin {name}:rule")
    assert not mark.exists()
    with pytest.raises(ScenarioError, match=f"--allow-plugin {name}:rule"):
        make_source("rules", policy=f"{name}:rule")
    assert not mark.exists()
    # named on the command line: the rule runs
    plugins.set_allowed_plugins([f"{name}:rule"])
    source = make_source("rules", policy=f"{name}:rule")
    request = BeliefRequest("findmilk", "care", (0.0,) * 8, ("up", "down", "left", "right"))
    assert source.beliefs([request])[0].belief.tolist() == [1.0, 0.0, 0.0, 0.0]
    assert mark.exists()


def test_allowed_plug_ins_load_and_others_stay_refused(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(HERE))
    with pytest.raises(ScenarioError, match="--allow-plugin amuled_agent_helper:FixedAgent"):
        make_source("entry-point", name="amuled_agent_helper:FixedAgent")
    plugins.set_allowed_plugins(["amuled_agent_helper:FixedAgent", "amuled_agent_helper:TinyNet"])
    assert make_source("entry-point", name="amuled_agent_helper:FixedAgent").name == "fixed-agent"
    weights = tmp_path / "tiny.pt"
    from amuled_agent_helper import TinyNet

    torch.save(TinyNet().state_dict(), weights)
    assert PolicySource(weights, module="amuled_agent_helper:TinyNet").module_name
    with pytest.raises(ScenarioError, match="--allow-plugin subprocess:Popen"):
        make_source("entry-point", name="subprocess:Popen", options={"args": ["true"]})
    with pytest.raises(ScenarioError, match="expected an import path"):
        plugins.set_allowed_plugins(["os.system"])


def test_allow_plugin_is_a_checked_flag_and_the_resume_hint_restates_it(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["finetune", "findmilk", "--allow-plugin", "not a path"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--allow-plugin" in err and "pkg.module:attr" in err and len(err.splitlines()) == 1
    from amuled_ma.cli import build_parser

    args = build_parser().parse_args(
        ["run", "findmilk", "--allow-plugin", "my_pkg.agents:Agent", "--set", "x.y=1"]
    )
    hint = rerun_of("run", args, "--resume").line(tmp_path)
    assert "--allow-plugin my_pkg.agents:Agent" in hint


def test_an_installed_entry_point_needs_no_flag(monkeypatch):
    monkeypatch.syspath_prepend(str(HERE))
    from amuled_agent_helper import install_fixed_entry_point

    install_fixed_entry_point(monkeypatch)
    assert make_source("entry-point", name="fixed").name == "fixed-agent"
    # its value is the same installed code
    assert make_source("entry-point", name="amuled_agent_helper:FixedAgent").name == "fixed-agent"


# ------------------------------------------------------------------------- run folders
def test_a_run_folder_imports_nothing_when_viewed_or_explained(tmp_path, capsys, marker):
    """A run trained with an allowed plug-in: viewing it needs the flag again."""
    name, mark = marker
    sys.path.insert(0, str(HERE))
    run = tmp_path / "run"
    agent = 'feedback.agents.care={source="entry-point", name="amuled_agent_helper:FixedAgent"}'
    common = ["findmilk", "--run-dir", str(run), *TINY, *RULES, "--set", agent]
    allow = ["--allow-plugin", "amuled_agent_helper:FixedAgent"]
    try:
        assert main(["train", *common]) == 0
        assert main(["finetune", *common]) == 1  # the resume needs the flag again
        one_line(capsys.readouterr().err, "--allow-plugin amuled_agent_helper:FixedAgent")
        assert main(["finetune", *common, *allow]) == 0
        capsys.readouterr()
        explain = ["explain", "--state-from", str(run), "--variant", "finetune-amuled"]
        explain += ["--step", "0"]
        view = ["view", str(run), "--output", str(tmp_path / "view.html")]
        for argv in (view, explain):
            assert main(argv) == 1
            one_line(capsys.readouterr().err, "--allow-plugin amuled_agent_helper:FixedAgent")
            assert main([*argv, *allow]) == 0
            capsys.readouterr()
        # a record edited to name other code: refused, never imported
        config = run / "finetune-amuled" / "config.json"
        config.write_text(config.read_text().replace("amuled_agent_helper:FixedAgent", f"{name}:A"))
        assert f"{name}:A" in json.dumps(json.loads(config.read_text()))
        for argv in (view, explain):
            assert main([*argv, *allow]) == 1
            one_line(capsys.readouterr().err, f"--allow-plugin {name}:A")
        assert not mark.exists()
    finally:
        sys.path.remove(str(HERE))
