"""Two real Ollama servers serve one fine-tune; one is killed with ``kill -9`` mid-run.

Run by ``test_live_host_pool.py`` inside a network namespace of its own (``unshare -n``, only
the loopback interface up), as ``python host_pool_netns.py WORKDIR``; not a test module.

1. Two private ``ollama serve`` on two loopback ports (one request slot each, the second
   reading the first's model directory), the tiny model registered once.
2. A base policy (2,048 steps), then ``amuled finetune findmilk --feedback amuled`` in this
   process with ``--set feedback.hosts=[A, B]``: the five clusters asked live through the
   pool (two copies x two steps, the tiny model's short reply, as ``amuled demo``).
3. A watcher thread kills (``SIGKILL`` to the server's process group: server and model
   runner) the first server that has answered a request and has another in flight.
4. ``amuled evaluate`` writes ``results.json`` and ``report.md``.

The last line of standard output is ``RESULT {json}``: the per-host figures, the source's
counters, every key written to the store (each write counted), the store's rows, the
commands' output. The servers are stopped whatever happens (an alarm after
:data:`LIMIT_S` and SIGTERM end the run through the same clean-up).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import json
import signal
import socket
import sqlite3
import sys
import threading
import time
from pathlib import Path
from typing import Any

#: Seconds the whole script may run before it stops itself (and its servers).
LIMIT_S = 480


def _stop(signum: int, frame: Any) -> None:
    raise SystemExit(f"stopped by signal {signum}")


def run(workdir: Path) -> dict[str, Any]:
    """Do the run; return what the outer test checks."""
    from amuled_ma.beliefs.sources import ollama as ollama_module
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.cli import main as cli
    from amuled_ma.servers import local_server as llm_server

    t0 = time.monotonic()
    out: dict[str, Any] = {"interfaces": sorted(name for _, name in socket.if_nameindex())}

    # every OllamaSource built in this process, to watch its pool
    sources: list[Any] = []
    original_init = ollama_module.OllamaSource.__init__

    @functools.wraps(original_init)  # keeps the signature: scenario keys are read from it
    def recording_init(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        sources.append(self)

    ollama_module.OllamaSource.__init__ = recording_init  # type: ignore[method-assign]
    # every key written to the belief store, each write counted
    written: list[str] = []
    original_put_many = BeliefStore.put_many

    def counting_put_many(self: Any, rows: Any) -> int:
        rows = list(rows)
        written.extend(str(row[0]) for row in rows)
        return original_put_many(self, rows)

    BeliefStore.put_many = counting_put_many  # type: ignore[method-assign]

    servers: list[llm_server.OllamaServer] = []
    try:
        first = llm_server.OllamaServer(workdir=workdir / "server-a", num_parallel=1)
        servers.append(first)
        first.start()
        first.create_model(
            llm_server.TINY_MODEL, llm_server.find_tiny_gguf(), llm_server.TINY_PARAMETERS
        )
        second = llm_server.OllamaServer(
            workdir=workdir / "server-b",
            num_parallel=1,
            extra_env={"OLLAMA_MODELS": str(first.models_dir)},  # the same model, read
        )
        servers.append(second)
        second.start()
        by_host = {first.host: first, second.host: second}
        out["hosts"] = list(by_host)
        out["servers_up_s"] = round(time.monotonic() - t0, 1)

        run_dir = workdir / "run"
        common = ["--run-dir", str(run_dir), "--no-progress"]
        base = ["train", "findmilk", *common, "--variant", "base"]
        base += ["--set", "base.total_steps=2048", "--set", "output.tensorboard=false"]
        with contextlib.redirect_stdout(io.StringIO()) as said:
            out["base_exit"] = cli(base)
        out["base_output"] = said.getvalue()
        out["base_done_s"] = round(time.monotonic() - t0, 1)

        hosts = json.dumps(list(by_host))
        finetune = ["finetune", "findmilk", *common, "--feedback", "amuled"]
        for setting in (
            'feedback.source="ollama"',
            f'feedback.model="{llm_server.TINY_MODEL}"',
            f"feedback.hosts={hosts}",
            "feedback.concurrency=2",
            "feedback.timeout_s=300.0",
            "feedback.ollama={reasoning = false, num_predict = 128}",
            "finetune.iterations=1",
            "finetune.num_envs=2",
            "finetune.num_steps_per_env=2",
            "ppo.num_mini_batches=2",  # 4 transitions an iteration: 2 per mini-batch
            "finetune.save_interval=1",
            "output.tensorboard=false",
        ):
            finetune += ["--set", setting]

        kill: dict[str, Any] = {}
        done = threading.Event()

        def watch() -> None:
            """Kill the first server that answered and has another request in flight."""
            while not done.is_set():
                for source in sources:
                    if len(source.hosts) < 2:
                        continue
                    pool = source.host_pool
                    for host in source.hosts:
                        if pool.stats(host).answered >= 1 and pool.in_flight(host) >= 1:
                            kill.update(
                                host=host,
                                at_s=round(time.monotonic() - t0, 1),
                                before=pool.as_dict(),
                                in_flight=pool.in_flight(host),
                            )
                            by_host[host].kill(signal.SIGKILL)  # kill -9, server + runner
                            return
                time.sleep(0.002)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        started = time.monotonic()
        with contextlib.redirect_stdout(io.StringIO()) as said:
            try:
                out["finetune_exit"] = cli(finetune)
            finally:
                done.set()
        out["finetune_s"] = round(time.monotonic() - started, 1)
        out["finetune_output"] = said.getvalue()
        watcher.join(timeout=5)
        out["kill"] = kill

        # the preflight's cost probe builds its own pool first (a warm-up and a timed
        # request); the fine-tune's pool is the last one built
        used = [s for s in sources if len(s.hosts) == 2 and s.stats.attempts]
        out["pool_sources"] = len(used)
        out["probe_attempts"] = [s.stats.attempts for s in used[:-1]]
        if used:
            out["figures"] = used[-1].server_stats()
            out["stats"] = dataclasses.asdict(used[-1].stats)
        out["written"] = written

        with contextlib.redirect_stdout(io.StringIO()) as said:
            out["evaluate_exit"] = cli(
                ["evaluate", str(run_dir), "--episodes", "4", "--modes", "greedy", "--no-progress"]
            )
        out["evaluate_output"] = said.getvalue()

        store = sqlite3.connect(run_dir / "beliefs.sqlite")
        try:
            out["store"] = {
                "rows": store.execute("SELECT COUNT(*) FROM beliefs").fetchone()[0],
                "distinct_keys": store.execute(
                    "SELECT COUNT(DISTINCT key) FROM beliefs"
                ).fetchone()[0],
                "sum_attempts": store.execute("SELECT SUM(attempts) FROM beliefs").fetchone()[0],
                "statuses": dict(
                    store.execute("SELECT status, COUNT(*) FROM beliefs GROUP BY status")
                ),
                "hosts": dict(
                    store.execute(
                        "SELECT json_extract(extra, '$.host'), COUNT(*) FROM beliefs GROUP BY 1"
                    )
                ),
            }
        finally:
            store.close()
        feedback = run_dir / "finetune-amuled" / "feedback.json"
        if feedback.is_file():
            out["feedback_json"] = json.loads(feedback.read_text())
        results = run_dir / "results.json"
        if results.is_file():
            variants = json.loads(results.read_text()).get("variants", {})
            feedback_entry = variants.get("finetune-amuled", {}).get("feedback") or {}
            out["results_servers"] = feedback_entry.get("llm_servers")
        report = run_dir / "report.md"
        out["report"] = report.read_text() if report.is_file() else ""
    finally:
        for server in servers:
            with contextlib.suppress(Exception):
                server.stop()
        out["wall_s"] = round(time.monotonic() - t0, 1)
    return out


def main() -> None:
    """``python host_pool_netns.py WORKDIR``: print ``RESULT {json}`` last."""
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGALRM, _stop)
    signal.alarm(LIMIT_S)
    out = run(Path(sys.argv[1]))
    print("RESULT " + json.dumps(out, default=str), flush=True)


if __name__ == "__main__":
    main()
