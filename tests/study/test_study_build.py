"""amuled study build: the items are the policies' own decisions, blinded, rebuilt identically."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from sparse_files import sparse
from study_fixtures import free_port, hand_study, tiny_run
from tiny_cli import one_line

from amuled_ma.cli import main
from amuled_ma.experiments.run_folder import scenario_of_run
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.study.build import build_study
from amuled_ma.study.model import StudyError, public_item, read_study


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return tiny_run(tmp_path_factory.mktemp("studyrun"))


def files_of(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def test_build_twice_gives_the_same_bytes_and_another_seed_another_study(run, tmp_path):
    args = ["study", "build", str(run), "--variants", "amuled,base,human", "--items", "10"]
    assert main([*args, "--seed", "5", "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--seed", "5", "--out", str(tmp_path / "b")]) == 0
    assert main([*args, "--seed", "6", "--out", str(tmp_path / "c")]) == 0
    a, b, c = (files_of(tmp_path / x) for x in "abc")
    assert a == b
    assert len(a) == 2 + 11  # study.json, consent.html, 10 pairs + 1 attention check
    assert a["study.json"] != c["study.json"]


def test_items_are_the_policies_greedy_actions_in_states_they_met(run, tmp_path):
    study = build_study([run], ["amuled", "base", "human"], tmp_path / "s", items=12, seed=1)
    scenario = scenario_of_run(run)
    folders = {"amuled": "finetune-amuled", "base": "base", "human": "finetune-human-rules"}
    assert study.folders == [folders]
    policies = {v: load_policy(run / f / "model_last.pt", scenario.ppo) for v, f in folders.items()}
    pairs = [i for i in study.items if i.kind == "pair"]
    checks = [i for i in study.items if i.kind == "attention"]
    assert len(pairs) == 12 and len(checks) == 1
    assert checks[0].expected in ("A", "B") and checks[0].expected in checks[0].instruction
    labels = []
    for item in pairs:
        obs = torch.as_tensor([item.obs], dtype=torch.float32)
        for option in item.options:
            with torch.no_grad():
                greedy = int(action_log_probs(policies[option.variant], obs).argmax())
            assert option.action == greedy
            assert option.action_name == ("up", "down", "left", "right")[greedy]
        assert item.options[0].action != item.options[1].action
        labels.append(item.options[0].variant)
        # the robot in the picture stands where the observation says
        svg = (tmp_path / "s" / item.picture).read_text()
        assert f"robot at ({int(item.obs[0])}, {int(item.obs[1])})" in svg
        # the participant sees no variant name
        shown = json.dumps(public_item(item, svg))
        assert not any(v in shown for v in ("amuled", "base", "human"))
        assert item.panel is not None and len(item.panel.agents) == 5
        assert np.isclose(sum(item.panel.fused), 1.0, atol=1e-5)
    assert len(set(labels)) > 1  # the order is random: not always the same variant first
    assert read_study(tmp_path / "s") == study


def test_build_refuses_what_does_not_fit(run, tmp_path):
    with pytest.raises(StudyError, match="at least two variants"):
        build_study([run], ["amuled"], tmp_path / "x", items=3, seed=0)
    with pytest.raises(StudyError, match=r"no variant .* fit 'nosuch'.*variants found: base"):
        build_study([run], ["amuled", "nosuch"], tmp_path / "x", items=3, seed=0)
    build_study([run], ["amuled", "base"], tmp_path / "y", items=3, seed=0)
    (tmp_path / "y" / "consent.html").write_text("my own words")
    with pytest.raises(StudyError, match=r"holds a study already.*--force"):
        build_study([run], ["amuled", "base"], tmp_path / "y", items=3, seed=0)
    build_study([run], ["amuled", "base"], tmp_path / "y", items=3, seed=0, force=True)
    assert (tmp_path / "y" / "consent.html").read_text() == "my own words"


def test_a_study_json_over_64_mib_is_refused_unread_by_serve_with_one_line(tmp_path, capsys):
    from amuled_ma.study.model import MAX_STUDY_BYTES

    assert MAX_STUDY_BYTES == 64 * 2**20
    folder = hand_study(tmp_path / "s")
    assert len(read_study(folder).items) == 1  # under the cap: read as before
    path = sparse(folder / "study.json", 10 * 2**30)
    capsys.readouterr()
    assert main(["study", "serve", str(folder), "--port", str(free_port())]) == 1
    line = one_line(capsys.readouterr().err)
    assert line == (
        f"amuled: error: {path}: the study file is 10,737,418,240 bytes, more than the "
        "67,108,864 a study file may be (about 3 KB an item); it is not read; is it the right "
        "folder? Rebuild the study with 'amuled study build'"
    )


@pytest.mark.parametrize("picture", ["../../etc/passwd", "/etc/passwd", "states/../x.svg", "x.svg"])
def test_a_picture_outside_the_study_states_folder_is_refused(tmp_path, capsys, picture):
    """A study.json from elsewhere cannot make the server send another file of the machine."""
    folder = hand_study(tmp_path / "study")
    data = json.loads((folder / "study.json").read_text())
    data["items"][0]["picture"] = picture
    (folder / "study.json").write_text(json.dumps(data))
    assert main(["study", "serve", str(folder), "--port", str(free_port())]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "picture" in err and "Traceback" not in err, err
