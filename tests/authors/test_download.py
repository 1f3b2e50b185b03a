"""The authors' recordings fetched on first use: once, checked, converted; refused when tampered.

A loopback HTTP server (``http.server`` on 127.0.0.1, in a thread) serves small caches in
the authors' format at ``/<commit>/<path>``, as raw GitHub would, and counts the requests;
the tests pass a registry of those files (the real one, ``PINNED``, is checked against the
authors' repository by the last test when a mirror of it is given).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import torch
from authors_fakes import CleanRLAgent, findmilk_cache, save_agent, write_pickle
from tiny_cli import TINY

from amuled_ma.authors.caches import (
    convert_cache,
    model_of_file,
    model_slug,
    task_of_folder,
)
from amuled_ma.authors.download import (
    OFFLINE_ENV,
    URL_ENV,
    ensure_authors_base,
    ensure_recordings,
    models_ablation_recordings,
    replayed_recordings,
)
from amuled_ma.authors.pinned import BASE_POLICIES, COMMIT, PINNED, PinnedFile
from amuled_ma.authors.policies import authors_changes
from amuled_ma.cli import main
from amuled_ma.errors import AuthorsFetchError
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.scenario import load_scenario, user_recordings_dir

PATH = "models/FindMilk-v4_42/tiny-model_llm_cache.pickle"
NAME = "findmilk-tiny-model"


class Served:
    """What the loopback server answers: ``{url path: bytes}``, and the paths asked."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.asked: list[str] = []


@pytest.fixture
def server() -> Iterator[tuple[str, Served]]:
    """A loopback server of :class:`Served`; yields its base URL (the commit comes after)."""
    served = Served()

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            served.asked.append(self.path)
            body = served.files.get(self.path)
            self.send_response(200 if body is not None else 404)
            self.send_header("Content-Length", str(len(body or b"")))
            self.end_headers()
            self.wfile.write(body or b"")

        def log_message(self, *args: object) -> None:  # quiet
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/authors", served
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


@pytest.fixture
def online(monkeypatch) -> None:
    monkeypatch.delenv(OFFLINE_ENV, raising=False)  # tests/conftest.py sets it for the suite


@pytest.fixture
def fake(tmp_path: Path) -> tuple[bytes, PinnedFile]:
    """A FindMilk cache in the authors' format and its pin (SHA-256 by hashlib)."""
    data = write_pickle(tmp_path / "src" / PATH, findmilk_cache(seed=3)).read_bytes()
    return data, PinnedFile(PATH, hashlib.sha256(data).hexdigest(), len(data), NAME)


@pytest.fixture
def scenario(tmp_path: Path, monkeypatch):
    """A scenario replaying ``findmilk-tiny-model``, in a folder of no checkout."""
    folder = tmp_path / "scenarios"
    folder.mkdir()
    (folder / "s.toml").write_text(f'[feedback]\nrecording = "{NAME}"\n')
    monkeypatch.chdir(tmp_path)  # no .git above: no ../shared beside a checkout
    return load_scenario(folder / "s.toml")


def files_under(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def test_fetched_once_checked_then_converted_as_the_import_does(
    tmp_path, server, online, fake, scenario
):
    base, served = server
    data, pin = fake
    served.files[f"/authors/{COMMIT}/{PATH}"] = data
    cache, lines = tmp_path / "cache", []
    assert replayed_recordings(scenario.feedback) == [NAME]

    written = ensure_recordings(
        scenario.resolve, [NAME], pinned=[pin], cache=cache, base=base, say=lines.append
    )
    target = user_recordings_dir() / f"{NAME}.json"
    assert written == [target]
    assert served.asked == [f"/authors/{COMMIT}/{PATH}"]
    assert len(lines) == 2
    assert lines[0].startswith(f"fetching 1 file(s), {len(data) / 1e3:.0f} kB: {PATH}")
    assert f"from {base}/{COMMIT[:12]}/" in lines[0] and "under their terms" in lines[0]
    assert (cache / PATH).read_bytes() == data
    # the recording is the one the converter makes of the served cache
    assert target.read_text() == convert_cache(tmp_path / "src" / PATH).to_json()
    assert scenario.recording_path(required=True) == target

    # found locally now: nothing is asked, nothing said
    assert ensure_recordings(scenario.resolve, [NAME], pinned=[pin], cache=cache, base=base) == []
    # the recording gone, the cached file (its SHA-256 checked) is converted again, not fetched
    target.unlink()
    lines.clear()
    again = ensure_recordings(
        scenario.resolve, [NAME], pinned=[pin], cache=cache, base=base, say=lines.append
    )
    assert again == [target] and target.is_file()
    assert len(served.asked) == 1 and not lines[0].startswith("fetching")


@pytest.mark.parametrize("tamper", ["one byte changed", "one byte more"])
def test_a_tampered_file_is_refused_and_nothing_stays(
    tmp_path, server, online, fake, scenario, tamper
):
    base, served = server
    data, pin = fake
    bad = bytes([data[0] ^ 1]) + data[1:] if tamper == "one byte changed" else data + b"\0"
    served.files[f"/authors/{COMMIT}/{PATH}"] = bad
    cache = tmp_path / "cache"
    with pytest.raises(AuthorsFetchError) as info:
        ensure_recordings(scenario.resolve, [NAME], pinned=[pin], cache=cache, base=base, say=print)
    message = str(info.value)
    assert "\n" not in message and message.startswith("refusing ")
    assert ("SHA-256" in message) if tamper == "one byte changed" else ("more than" in message)
    assert f"nothing was kept in {cache}" in message and "amuled import authors" in message
    assert len(served.asked) == 1
    assert files_under(cache) == []  # no temporary file, no bad file
    assert files_under(user_recordings_dir()) == []


def test_offline_names_both_routes_at_once(tmp_path, server, fake, scenario, monkeypatch):
    base, served = server
    data, pin = fake
    served.files[f"/authors/{COMMIT}/{PATH}"] = data
    monkeypatch.setenv(OFFLINE_ENV, "1")
    start = time.monotonic()
    with pytest.raises(AuthorsFetchError) as info:
        ensure_recordings(scenario.resolve, [NAME], pinned=[pin], cache=tmp_path / "c", base=base)
    assert time.monotonic() - start < 2.0
    message = str(info.value)
    assert "\n" not in message and NAME in message
    assert "run without it to fetch" in message and "amuled import authors PATH" in message
    assert "AMULED_RECORDINGS" in message and served.asked == []


def test_an_unreachable_server_is_one_line_within_seconds(tmp_path, online, fake, scenario):
    _data, pin = fake
    start = time.monotonic()
    with pytest.raises(AuthorsFetchError) as info:
        ensure_recordings(
            scenario.resolve, [NAME], pinned=[pin], cache=tmp_path / "c", base="http://127.0.0.1:1"
        )
    assert time.monotonic() - start < 2.0
    message = str(info.value)
    assert "\n" not in message and message.startswith("could not fetch http://127.0.0.1:1/")
    assert "amuled import authors PATH" in message and files_under(tmp_path / "c") == []


def test_found_locally_or_unknown_is_never_fetched(tmp_path, server, online, fake, scenario):
    base, served = server
    _data, pin = fake
    (tmp_path / "scenarios" / f"{NAME}.json").write_text("{}")  # beside the scenario file
    assert (
        ensure_recordings(scenario.resolve, [NAME, "findmilk-other"], pinned=[pin], base=base) == []
    )
    assert served.asked == []


def test_the_demo_offline_and_the_run_unreachable_stop_in_one_line(tmp_path, monkeypatch, capsys):
    """The real registry through the command line: no recording anywhere, no fetch possible."""
    monkeypatch.setenv("AMULED_RECORDINGS", str(tmp_path / "none"))
    monkeypatch.setenv("AMULED_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)  # in no checkout: nothing beside it
    start = time.monotonic()
    code = main(["demo", "--offline", "--run-dir", str(tmp_path / "demo")])
    assert code == 1 and time.monotonic() - start < 2.0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "findmilk-gpt-4o-mini" in err
    assert "run without it to fetch 1.5 MB" in err and "amuled import authors PATH" in err

    monkeypatch.delenv(OFFLINE_ENV)
    monkeypatch.setenv(URL_ENV, "http://127.0.0.1:1")
    start = time.monotonic()
    code = main(["run", "driving", "--run-dir", str(tmp_path / "run"), *TINY])
    assert code == 1 and time.monotonic() - start < 5.0
    out, err = capsys.readouterr()
    assert "fetching 1 file(s), 2.0 MB: PickleCacheAndBaseModels/Drive/gpt-4o-mini" in out
    assert err.count("\n") == 1 and "could not fetch http://127.0.0.1:1/" + COMMIT in err
    assert not (tmp_path / "run").exists() and files_under(tmp_path / "cache") == []


def test_each_pin_names_the_recording_the_import_writes():
    for pin in PINNED:
        path = Path(pin.path)
        task = task_of_folder(path.parent.name)
        assert task is not None
        assert f"{task}-{model_slug(model_of_file(path))}" == pin.recording
    assert len({pin.recording for pin in PINNED}) == len(PINNED)


def test_the_models_ablation_fetches_every_recording_of_the_task_only_when_its_own_is_missing(
    tmp_path, monkeypatch
):
    folder = tmp_path / "scenarios"
    folder.mkdir()
    text = '[task]\nname = "findmilk"\n[feedback]\nrecording = "findmilk-gpt-4o-mini"\n'
    (folder / "s.toml").write_text(text)
    monkeypatch.chdir(tmp_path)
    scenario = load_scenario(folder / "s.toml")
    assert models_ablation_recordings(scenario.feedback, scenario.task.name, scenario.resolve) == [
        "findmilk-gpt-4o-mini",
        "findmilk-llama-3_1-70b",
        "findmilk-llama-3_1-8b",
        "findmilk-mistral-nemo",
    ]
    (folder / "findmilk-gpt-4o-mini.json").write_text("{}")  # found: compare those found
    assert models_ablation_recordings(scenario.feedback, scenario.task.name, scenario.resolve) == []


MIRROR_ENV = "AMULED_AUTHORS_MIRROR"


def mirror_blob(mirror: str, path: str) -> bytes:
    return subprocess.run(
        ["git", f"--git-dir={mirror}", "cat-file", "blob", f"{COMMIT}:{path}"],
        capture_output=True,
        check=True,
    ).stdout


def test_the_pins_are_the_authors_files_and_convert_to_the_shared_recording(
    tmp_path, server, online, scenario, recordings_dir
):
    """Each pin against the authors' git mirror; the smallest served and converted as shipped.

    Skips without a mirror (``$AMULED_AUTHORS_MIRROR``) or ``../shared/amuled-recordings``.
    """
    mirror = os.environ.get(MIRROR_ENV)
    if not mirror or not (Path(mirror) / "HEAD").is_file() or shutil.which("git") is None:
        pytest.skip(f"set {MIRROR_ENV} to a git mirror of temetski/moral_agent to run this test")
    for pin in [*PINNED, *BASE_POLICIES.values()]:
        blob = mirror_blob(mirror, pin.path)
        assert (hashlib.sha256(blob).hexdigest(), len(blob)) == (pin.sha256, pin.size), pin.path
    base, served = server
    pin = min(PINNED, key=lambda p: p.size)  # findmilk-mistral-nemo, 75 KB
    served.files[f"/authors/{COMMIT}/{pin.path}"] = mirror_blob(mirror, pin.path)
    written = ensure_recordings(scenario.resolve, [pin.recording], cache=tmp_path / "c", base=base)
    assert written[0].read_bytes() == (recordings_dir / f"{pin.recording}.json").read_bytes()


BASE_PATH = "models/FindMilk-v4_42/base.cleanrl_model"


@pytest.fixture
def base_pin(tmp_path: Path) -> tuple[bytes, PinnedFile, CleanRLAgent]:
    """A CleanRL FindMilk base policy (8 observations, 4 actions) and its pin."""
    agent = CleanRLAgent(8, 4, seed=4)
    data = save_agent(tmp_path / "src" / BASE_PATH, agent).read_bytes()
    pin = PinnedFile(
        BASE_PATH, hashlib.sha256(data).hexdigest(), len(data), "authors/findmilk/base"
    )
    return data, pin, agent


def test_the_authors_base_is_fetched_once_and_converted_into_the_runs_folder(
    tmp_path, server, online, base_pin
):
    base, served = server
    data, pin, agent = base_pin
    served.files[f"/authors/{COMMIT}/{BASE_PATH}"] = data
    runs, cache, lines = tmp_path / "runs", tmp_path / "cache", []
    kwargs = {"runs": runs, "pinned": {"findmilk": pin}, "cache": cache, "base": base}
    folder = ensure_authors_base("findmilk", say=lines.append, **kwargs)
    assert folder == runs / "authors" / "findmilk" / "base"
    assert served.asked == [f"/authors/{COMMIT}/{BASE_PATH}"]
    assert lines[0].startswith(f"fetching 1 file(s), {len(data) / 1e3:.0f} kB: {BASE_PATH}")
    assert "under their terms" in lines[0] and lines[-1] == f"converted to {folder}"
    # the converted policy acts as the served one (its actor's logits)
    scenario = load_scenario("findmilk").changed(authors_changes([64, 64]))
    obs = torch.rand(200, 8, generator=torch.Generator().manual_seed(2)) * 8
    with torch.no_grad():
        ours = action_log_probs(load_policy(folder / "model_last.pt", scenario.ppo), obs)
        theirs = torch.log_softmax(agent.actor(obs), dim=-1)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-5)
    # there now: never fetched again, even offline; a task without a pinned base: None
    assert ensure_authors_base("findmilk", offline=True, **kwargs) == folder
    assert len(served.asked) == 1
    assert ensure_authors_base("driving", **kwargs) is None


def test_a_tampered_base_is_refused_and_offline_names_both_routes(
    tmp_path, server, online, base_pin, monkeypatch
):
    base, served = server
    data, pin, _agent = base_pin
    served.files[f"/authors/{COMMIT}/{BASE_PATH}"] = data[:-1] + bytes([data[-1] ^ 1])
    runs, cache = tmp_path / "runs", tmp_path / "cache"
    kwargs = {"runs": runs, "pinned": {"findmilk": pin}, "cache": cache, "base": base}
    with pytest.raises(AuthorsFetchError, match="its SHA-256 is not the pinned") as error:
        ensure_authors_base("findmilk", say=lambda _: None, **kwargs)
    assert "amuled import authors PATH --only policies" in str(error.value)
    assert files_under(cache) == [] and files_under(runs) == []
    monkeypatch.setenv(OFFLINE_ENV, "1")
    with pytest.raises(AuthorsFetchError) as error:
        ensure_authors_base("findmilk", **kwargs)
    text = str(error.value)
    assert "\n" not in text and f"run without it to fetch {len(data) / 1e3:.0f} kB" in text
    assert "'amuled import authors PATH --only policies'" in text
    assert len(served.asked) == 1  # the tampered download only
