"""``Scenario.recording_path``: recordings found by path or by name, in a fixed order."""

import pytest
from authors_fakes import findmilk_cache, write_pickle

from amuled_ma.cli import main
from amuled_ma.errors import ScenarioError
from amuled_ma.scenario import load_scenario, user_data_dir, user_recordings_dir


def scenario_with(tmp_path, recording):
    folder = tmp_path / "scenarios"
    folder.mkdir(exist_ok=True)
    path = folder / "s.toml"
    path.write_text(f'[feedback]\nrecording = "{recording}"\n')
    return load_scenario(path)


@pytest.fixture
def places(tmp_path, monkeypatch):
    """One copy of ``findmilk-x.json`` in each place, in lookup order."""
    checkout = tmp_path / "work" / "clone"
    (checkout / ".git").mkdir(parents=True)
    (checkout / "deep" / "er").mkdir(parents=True)
    monkeypatch.chdir(checkout / "deep" / "er")
    monkeypatch.setenv("AMULED_RECORDINGS", str(tmp_path / "env-recordings"))
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "data"))
    folders = [
        tmp_path / "scenarios" / "rec",  # as given: "rec/findmilk-x" relative to the file
        tmp_path / "env-recordings",
        tmp_path / "data" / "recordings",
        tmp_path / "work" / "shared" / "amuled-recordings",
    ]
    files = []
    for folder in folders:
        folder.mkdir(parents=True)
        files.append(folder / "findmilk-x.json")
        files[-1].write_text("{}")
    return files


@pytest.mark.parametrize("value", ["rec/findmilk-x", "rec/findmilk-x.json"])
def test_lookup_order(tmp_path, places, value):
    scenario = scenario_with(tmp_path, value)
    for expected in places:
        assert scenario.recording_path(required=True) == expected
        expected.unlink()
    with pytest.raises(ScenarioError) as info:
        scenario.recording_path(required=True)
    message = str(info.value)
    for path in places:
        assert str(path) in message, path
    assert "amuled import authors PATH" in message and "AMULED_RECORDINGS" in message
    assert str(tmp_path / "scenarios" / "s.toml") in message
    # without required: the value as given, as before (callers test .exists())
    assert scenario.recording_path() == (tmp_path / "scenarios" / value).resolve()


def test_a_bare_name_is_found_in_the_folders(tmp_path, places):
    places[0].unlink()
    assert scenario_with(tmp_path, "findmilk-x").recording_path() == places[1]
    assert scenario_with(tmp_path, "findmilk-x.json").recording_path() == places[1]


def test_places_that_do_not_apply_are_named(tmp_path, monkeypatch):
    monkeypatch.delenv("AMULED_RECORDINGS", raising=False)
    monkeypatch.chdir(tmp_path)  # tmp_path is in no checkout
    with pytest.raises(ScenarioError) as info:
        scenario_with(tmp_path, "nowhere").recording_path(required=True)
    message = str(info.value)
    assert "$AMULED_RECORDINGS: (not set)" in message
    assert "beside the checkout: (the current directory is in no checkout)" in message
    assert str(tmp_path / "user-data" / "recordings" / "nowhere.json") in message
    with pytest.raises(ScenarioError, match="recording is empty"):
        scenario_with(tmp_path, "").recording_path(required=True)


def test_user_data_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "d"))
    assert user_recordings_dir() == tmp_path / "d" / "recordings"
    monkeypatch.delenv("AMULED_DATA")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "x"))
    assert user_data_dir() == tmp_path / "x" / "amuled-ma"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert user_recordings_dir() == tmp_path / "home/.local/share/amuled-ma/recordings"


def test_imported_recording_found_by_name(tmp_path, monkeypatch):
    checkout = tmp_path / "moral_agent"
    write_pickle(checkout / "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle", findmilk_cache())
    monkeypatch.chdir(tmp_path)
    assert main(["import", "authors", str(checkout), "--only", "recordings"]) == 0
    found = scenario_with(tmp_path, "findmilk-gpt-4o-mini").recording_path(required=True)
    assert found == tmp_path / "user-data" / "recordings" / "findmilk-gpt-4o-mini.json"


def test_shipped_scenarios_still_find_the_shared_recordings(recordings_dir, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("AMULED_RECORDINGS", str(recordings_dir))  # where conftest found them
    for name, recording in (("findmilk", "findmilk-gpt-4o-mini.json"),
                            ("driving", "driving-gpt-4o-mini.json"),
                            ("findmilk-authors", "findmilk-gpt-4o-mini.json"),
                            ("driving-authors", "driving-gpt-4o-mini.json")):  # fmt: skip
        found = load_scenario(name).recording_path(required=True)
        assert found.name == recording
        assert found.read_bytes() == (recordings_dir / recording).read_bytes()
