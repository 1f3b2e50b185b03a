"""amuled_ma.servers.local_server and ``amuled ollama``, with a fake ``ollama`` executable.

The fake is a small Python HTTP server answering ``/api/version`` and ``/api/tags`` on
``$OLLAMA_HOST``, so start/stop/state logic is tested in about a second without the real
binary; the real server is exercised in ``tests/integration/``.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from amuled_ma.cli import main
from amuled_ma.errors import BackendUnavailable, ModelNotFound
from amuled_ma.servers import local_server as llm_server
from amuled_ma.servers.hosts import preflight

FAKE_OLLAMA = r'''#!{python}
"""Fake ollama: 'serve' answers /api/version and /api/tags; 'create' records the model."""
import http.server, json, os, sys
from pathlib import Path

models_dir = Path(os.environ.get("OLLAMA_MODELS", "."))
models_file = models_dir / "fake-models.json"

def models():
    return json.loads(models_file.read_text()) if models_file.exists() else []

if sys.argv[1] == "create":
    models_file.parent.mkdir(parents=True, exist_ok=True)
    modelfile = Path(sys.argv[sys.argv.index("-f") + 1]).read_text()
    assert modelfile.startswith("FROM "), modelfile
    models_file.write_text(json.dumps(sorted(set(models()) | {sys.argv[2] + ":latest"})))
    sys.exit(0)
assert sys.argv[1] == "serve", sys.argv
assert os.environ["HOME"].endswith("home"), os.environ["HOME"]
assert "OLLAMA_MULTIUSER_CACHE" not in os.environ
host, port = os.environ["OLLAMA_HOST"].rsplit(":", 1)

class Handler(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        body = {"/api/version": {"version": "0.0.0-fake"},
                "/api/tags": {"models": [{"name": m} for m in models()]}}.get(self.path)
        self.send_response(200 if body else 404)
        self.end_headers()
        self.wfile.write(json.dumps(body or {}).encode())
    def log_message(self, *args):
        pass

http.server.HTTPServer((host, int(port)), Handler).serve_forever()
'''


@pytest.fixture
def fake_ollama(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fake ``ollama`` executable; PATH and the cache point away from real ones."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    binary = bindir / "ollama"
    binary.write_text(FAKE_OLLAMA.replace("{python}", sys.executable))
    binary.chmod(binary.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("AMULED_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("AMULED_OLLAMA_BIN", raising=False)
    monkeypatch.delenv("OLLAMA_HOST", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    return binary


@pytest.fixture
def gguf(tmp_path: Path) -> Path:
    path = tmp_path / llm_server.TINY_GGUF_NAME
    path.write_bytes(b"GGUF fake")
    return path


def _closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("127.0.0.1:8080", "http://127.0.0.1:8080"),
        ("http://localhost:1/", "http://localhost:1"),
        ("localhost", "http://localhost:11434"),
        ("https://example.org", "https://example.org:443"),
        ("[::1]:99", "http://[::1]:99"),
    ],
)
def test_normalize_host(given: str, expected: str) -> None:
    assert llm_server.normalize_host(given) == expected


def test_no_binary_error_says_how_to_install(fake_ollama: Path) -> None:
    with pytest.raises(BackendUnavailable) as info:
        llm_server.find_binary()
    message = str(info.value)
    assert "ollama.com" in message and ".ci/setup-ollama" in message and "PATH" in message


def test_binary_search_order(fake_ollama: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert llm_server.find_binary(fake_ollama) == fake_ollama
    with pytest.raises(BackendUnavailable, match="--binary"):
        llm_server.find_binary(fake_ollama.parent / "missing")
    monkeypatch.setenv("PATH", str(fake_ollama.parent))
    assert llm_server.find_binary() == fake_ollama
    monkeypatch.setenv("PATH", "")
    built = llm_server.cache_dir() / f"ollama-v{llm_server.OLLAMA_VERSION}" / "bin" / "ollama"
    built.parent.mkdir(parents=True)
    built.write_bytes(fake_ollama.read_bytes())
    built.chmod(0o755)
    assert llm_server.find_binary() == built
    monkeypatch.setenv("AMULED_OLLAMA_BIN", str(fake_ollama))
    assert llm_server.find_binary() == fake_ollama


def test_tiny_gguf_lookup(fake_ollama: Path, gguf: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("AMULED_TINY_GGUF", raising=False)
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    with pytest.raises(ModelNotFound, match="setup-ollama"):
        llm_server.find_tiny_gguf()
    monkeypatch.setenv("AMULED_TINY_GGUF", str(gguf))
    assert llm_server.find_tiny_gguf() == gguf


def test_preflight_unreachable_is_fast_and_clear() -> None:
    port = _closed_port()
    start = time.monotonic()
    with pytest.raises(BackendUnavailable) as info:
        preflight(f"127.0.0.1:{port}", "amuled-tiny", timeout=5.0)
    assert time.monotonic() - start < 5.0
    assert f"127.0.0.1:{port}" in str(info.value) and "amuled ollama up" in str(info.value)


def test_server_start_models_and_stop(fake_ollama: Path, gguf: Path, tmp_path: Path) -> None:
    server = llm_server.OllamaServer(fake_ollama, workdir=tmp_path / "srv")
    host = server.start(timeout=20)
    try:
        assert host.startswith("http://127.0.0.1:")
        assert preflight(host).version == "0.0.0-fake"
        with pytest.raises(ModelNotFound) as info:
            preflight(host, "amuled-tiny")
        assert "'amuled-tiny'" in str(info.value) and "amuled ollama up --tiny" in str(info.value)
        with pytest.raises(ModelNotFound, match=r"ollama pull llama3\.1:8b"):
            preflight(host, "llama3.1:8b")
        server.create_model("amuled-tiny", gguf)
        assert preflight(host, "amuled-tiny")
        assert preflight(host).models == ("amuled-tiny:latest",)
        pid = server.pid
    finally:
        server.stop()
    assert pid is not None and not llm_server._pid_alive(pid)
    assert llm_server.server_version(host, timeout=0.5) is None


def test_start_failure_quotes_the_log(tmp_path: Path) -> None:
    broken = tmp_path / "ollama"
    broken.write_text("#!/bin/sh\necho 'Error: listen tcp: address already in use' >&2\nexit 1\n")
    broken.chmod(0o755)
    with pytest.raises(BackendUnavailable, match="address already in use"):
        llm_server.OllamaServer(broken).start(timeout=10)


def test_cli_up_status_down(
    fake_ollama: Path, gguf: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    state_dir = tmp_path / "state"
    common = ["--state-dir", str(state_dir)]
    assert main(["ollama", "status", *common]) == 3
    assert "no server running" in capsys.readouterr().out

    assert (
        main(["ollama", "up", "--binary", str(fake_ollama), "--tiny", "--gguf", str(gguf), *common])
        == 0
    )
    try:
        _check_up_status_down(fake_ollama, state_dir, common, capsys)
    finally:
        llm_server.down(state_dir)  # never leave a server behind, whatever failed


def _check_up_status_down(
    fake_ollama: Path, state_dir: Path, common: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    out = capsys.readouterr()
    host = out.out.strip()
    assert host.startswith("http://127.0.0.1:") and "export OLLAMA_HOST=" in out.err
    state = llm_server.read_state(state_dir)
    assert state is not None and state.host == host and state.models == ["amuled-tiny"]
    assert state.is_ours()
    assert preflight(host, "amuled-tiny")

    # A second 'up' reuses the running server.
    assert main(["ollama", "up", "--binary", str(fake_ollama), *common]) == 0
    out = capsys.readouterr()
    assert out.out.strip() == host and "already running" in out.err

    assert main(["ollama", "status", "--json", *common]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["running"] and info["answering"] and info["pid"] == state.pid
    assert info["available_models"] == ["amuled-tiny:latest"]

    assert main(["ollama", "down", *common]) == 0
    assert f"stopped the Ollama server pid {state.pid}" in capsys.readouterr().out
    assert not llm_server._pid_alive(state.pid)
    assert llm_server.read_state(state_dir) is None
    assert main(["ollama", "down", *common]) == 0
    assert "nothing to stop" in capsys.readouterr().out


def test_down_never_kills_a_process_it_did_not_start(tmp_path: Path) -> None:
    """A stale state whose pid now belongs to another process: cleared, process untouched."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        deadline = time.monotonic() + 10  # until it has exec'd (no forked copy of pytest)
        while "time.sleep" not in " ".join(llm_server._pid_cmdline(other.pid)):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        state = llm_server.ServerState(
            pid=other.pid,
            host="http://127.0.0.1:1",
            binary="/usr/bin/ollama",
            version="x",
            models_dir="m",
            home="h",
            log="l",
            started_at=0.0,
        )
        llm_server.write_state(state, tmp_path)
        assert not state.is_ours()
        assert "no longer running" in llm_server.down(tmp_path)
        assert other.poll() is None
        assert llm_server.read_state(tmp_path) is None
    finally:
        other.kill()
        other.wait()


def test_cli_without_binary_fails_clearly(
    fake_ollama: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["ollama", "up", "--state-dir", str(tmp_path / "s")]) == 1
    err = capsys.readouterr().err
    assert "no 'ollama' executable found" in err and "https://ollama.com/download" in err
    assert not (tmp_path / "s" / "state.json").exists()


def test_server_env_is_private(
    fake_ollama: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OLLAMA_MULTIUSER_CACHE", "1")
    monkeypatch.setenv("OLLAMA_MODELS", "/somewhere/else")
    server = llm_server.OllamaServer(fake_ollama, workdir=tmp_path)
    server.host = "http://127.0.0.1:5"
    env = server.env()
    assert env["OLLAMA_HOST"] == "127.0.0.1:5"
    assert env["OLLAMA_MODELS"] == str(tmp_path / "models")
    assert env["HOME"] == str(tmp_path / "home")
    assert env["OLLAMA_NUM_PARALLEL"] == "2"
    assert env["OLLAMA_FLASH_ATTENTION"] == "0"  # 2x slower on a CPU (docs/ollama.md)
    assert "OLLAMA_MULTIUSER_CACHE" not in env
    assert os.environ["OLLAMA_MULTIUSER_CACHE"] == "1"  # the caller's env is untouched
    tuned = llm_server.OllamaServer(
        fake_ollama, workdir=tmp_path, num_parallel=1, extra_env={"OLLAMA_DEBUG": "1"}
    ).env()
    assert tuned["OLLAMA_NUM_PARALLEL"] == "1" and tuned["OLLAMA_DEBUG"] == "1"
