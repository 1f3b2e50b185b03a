"""``amuled clusters list``."""

from __future__ import annotations

import json

from amuled_ma.cli import main


def test_clusters_list_table(capsys):
    assert main(["clusters", "list"]) == 0
    out = capsys.readouterr().out
    for name in ("consequentialist", "deontological", "virtue", "care", "social_justice"):
        assert name in out
    assert "moral_agent" in out and "unprompted" in out
    assert "amuled_ma.agents" in out


def test_clusters_list_user_dir_json(tmp_path, capsys):
    (tmp_path / "blend.toml").write_text(
        'name = "blend"\nkind = "mixture"\ntitle = "Blend"\ncredences = { care = 1.0 }\n'
    )
    assert main(["clusters", "list", "--clusters-dir", str(tmp_path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    blend = next(c for c in data["clusters"] if c["name"] == "blend")
    assert blend["kind"] == "mixture"
    assert blend["credences"]["Care Ethics"] == 1.0
    assert isinstance(data["agents"], dict)


def test_clusters_list_bad_file_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "bad.toml").write_text('name = "bad"\ntitle = "Bad"\n')
    assert main(["clusters", "list", "--clusters-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "bad.toml" in err and "'credence_label'" in err


def test_clusters_show(capsys):
    assert main(["clusters", "show", "deontologist", "--state", "HERE"]) == 0
    out = capsys.readouterr().out
    assert out.count("----- user -----") == 4 and out.count("----- assistant -----") == 3
    assert "HERE\n\nBehave as an agent that assigns the following credence values: " in out
    assert "Deontological: 1.0" in out


def test_clusters_list_shows_entry_point_agents(monkeypatch, capsys):
    from importlib.metadata import EntryPoint

    point = EntryPoint("terminal_human", "my_pkg.human:Source", "amuled_ma.agents")
    monkeypatch.setattr(
        "amuled_ma.clusters.plugins.entry_points",
        lambda group: [point] if group == "amuled_ma.agents" else [],
    )
    assert main(["clusters", "list"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.split() == ["terminal_human", "my_pkg.human:Source"]
